"""``cell serve [--config FILE] [--host H] [--port N] [--ssl-certfile F --ssl-keyfile F]
[--opcua-port N] [--xmlrpc-port N] [--modbus-port N]``: the cell service: its HTTP API (HTTPS
when given a certificate and key), and the OPC UA server, URScript XML-RPC endpoint and Modbus
TCP server it configures.

Without ``--config`` it serves the built-in simulated cell (simulated UR controller driven
through ur_rtde, simulated camera, fake gripper on its tool-flange relay). uvicorn imports the
app factory by name (``api.app:app_from_environment``) so the cell package does not depend on
the API package.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from types import FrameType

import uvicorn

from cell.commands.common import fail


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("serve", help="serve the cell's HTTP API (default: the simulated cell)")
    p.add_argument("--config", default=None, help="cell TOML (default: built-in simulated cell)")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--log-level", default="info",
                   choices=["critical", "error", "warning", "info", "debug"])
    p.add_argument("--log-format", default="text", choices=["text", "json"],
                   help="json: one JSON object per line on stderr (for journald and log "
                        "shippers)")
    p.add_argument("--ssl-certfile", default=None,
                   help="serve HTTPS with this certificate (PEM); needs --ssl-keyfile")
    p.add_argument("--ssl-keyfile", default=None, help="the certificate's private key (PEM)")
    p.add_argument("--opcua-port", type=int, default=None, metavar="N",
                   help="serve the [opcua] endpoint on this port instead (0: off)")
    p.add_argument("--xmlrpc-port", type=int, default=None, metavar="N",
                   help="serve the URScript XML-RPC endpoint on this port instead (0: off)")
    p.add_argument("--modbus-port", type=int, default=None, metavar="N",
                   help="serve Modbus TCP on this port instead of [modbus] port (0: off)")
    p.set_defaults(func=_serve)


def _serve(args: argparse.Namespace) -> int:
    from cell.config.endpoints import endpoints, with_ports
    from cell.config.schema import ConfigError, load_config
    from cell.runtime import check_startable

    if bool(args.ssl_certfile) != bool(args.ssl_keyfile):
        return fail("invalid_arguments", "--ssl-certfile and --ssl-keyfile go together", False)
    for path in (args.ssl_certfile, args.ssl_keyfile):
        if path and not os.path.isfile(path):
            return fail("invalid_arguments", f"no such file: {path}", False)
    for flag, port in (("--opcua-port", args.opcua_port), ("--xmlrpc-port", args.xmlrpc_port),
                       ("--modbus-port", args.modbus_port)):
        if port is not None and not 0 <= port <= 65535:
            return fail("invalid_argument", f"{flag} must be a port 0..65535, got {port}", False)
    try:
        config = with_ports(load_config(args.config), args.opcua_port, args.xmlrpc_port,
                            args.modbus_port)
        check_startable(config)  # before "serving", before any device is touched
    except ConfigError as err:
        return fail(err.code, str(err), False)
    if args.config is not None:
        os.environ["CELL_CONFIG"] = os.path.abspath(args.config)
    else:
        os.environ.pop("CELL_CONFIG", None)
    for name, port in (("CELL_OPCUA_PORT", args.opcua_port),
                       ("CELL_XMLRPC_PORT", args.xmlrpc_port),
                       ("CELL_MODBUS_PORT", args.modbus_port)):
        if port is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = str(port)
    import logging
    import logging.config

    from cell.supervision.logs import log_config, quiet_library_loggers
    from estimator.kernels import warm_up

    logging_config = log_config(args.log_format, args.log_level)
    logging.config.dictConfig(logging_config)
    quiet_library_loggers()
    log = logging.getLogger("cell.serve")

    def say(message: str) -> None:
        if args.log_format == "json":
            log.info(message)
        else:
            print(message, flush=True)

    # Before any thread starts (numba, the devices, uvicorn's pool): a bounded number of
    # malloc arenas, and their freed pages handed back every TRIM_PERIOD_S (~15 arenas kept
    # freed frame buffers resident; cell/supervision/memory.py, docs/performance.md)
    from cell.supervision.memory import (
        Trimmer,
        keep_heap,
        limit_arenas,
        lock_file_pages,
        trim_period_s,
    )

    limit_arenas()
    if trim_period_s() > 0:  # the trimmer hands back what glibc now keeps
        keep_heap()
    period = trim_period_s()
    if period > 0:
        Trimmer(period, lock_pages=True).start()
    # Compiled once per checkout (make install does it); loading takes a fraction of a second.
    say(f"estimator kernels ready in {warm_up():.1f} s")
    # what has run stays in RAM: a library page read back from disk while a thread holds
    # the interpreter's lock holds the whole service (cell/supervision/memory.py)
    locked, why = lock_file_pages()
    if why is None:
        log.info("library pages kept in RAM once used (%.0f MB mapped)", locked / 1e6)
    else:
        say(f"warning: library pages are not kept in RAM ({why}); under memory pressure the "
            "service may stand still while they are read back (LimitMEMLOCK=infinity)")
    scheme = "https" if args.ssl_certfile else "http"
    say(f"serving the cell on {scheme}://{args.host}:{args.port} (docs at /docs); state in "
        f"{os.path.dirname(os.path.abspath(config.api.job_db))}")
    for line in endpoints(config):
        say(f"serving {line}")
    server = _StopFirstServer(uvicorn.Config(
        "api.app:app_from_environment", factory=True, host=args.host, port=args.port,
        log_level=args.log_level, log_config=logging_config,
        ssl_certfile=args.ssl_certfile, ssl_keyfile=args.ssl_keyfile,
        timeout_graceful_shutdown=SHUTDOWN_GRACE_S))
    with contextlib.suppress(KeyboardInterrupt):  # uvicorn re-raises the Ctrl-C it handled
        server.run()
    return 0


SHUTDOWN_GRACE_S = 2  # open streams get this long after SIGTERM, and only after the arm stop


class _StopFirstServer(uvicorn.Server):
    """On SIGTERM/SIGINT the arm is stopped (and streams told to end) before uvicorn starts
    its graceful shutdown, which would otherwise wait for every client to leave first."""

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        from cell.runtime import SHUTDOWN_HOOKS

        for hook in list(SHUTDOWN_HOOKS):
            try:
                hook()
            except Exception as err:  # the shutdown itself must go on
                print(f"shutdown hook failed: {err!r}", file=sys.stderr, flush=True)
        super().handle_exit(sig, frame)
