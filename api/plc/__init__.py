"""The doors PLCs and robot programs use beside HTTP: OPC UA (with the Machine Vision
subset), Modbus TCP and the URScript XML-RPC endpoint. They share :mod:`api.remote` with
the HTTP API, so a command means the same through every door."""
