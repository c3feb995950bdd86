"""Universal Robots e-Series through ur_rtde: the adapter (:class:`drivers.ur.adapter.URArm`),
the ur_rtde child process that hosts the RTDE clients and the controller's watchdog
(``python -m drivers.ur.client_process``, started by the adapter), and the controller's codes.

Nothing is imported here: the child runs this package's ``client_process`` as its main
module, and importing the adapter first would load that module twice."""
