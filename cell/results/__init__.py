"""What the cell's jobs and answers return, as typed objects.

One model per job kind, owned here at the bottom of the cell so that the actions that build
them, the job store that keeps them and every interface that serialises them (HTTP, OPC UA,
Modbus, XML-RPC) share one definition. Pure data: nothing here moves or measures anything.
"""
