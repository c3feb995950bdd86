"""``cell serve [--config FILE] [--host H] [--port N]``: the cell service and its HTTP API.

Without ``--config`` it serves the built-in simulated cell (simulated UR controller driven
through ur_rtde, simulated camera, fake gripper on a pty). uvicorn imports the app factory by
name (``api.app:app_from_environment``) so the cell package does not depend on the API package.
"""

from __future__ import annotations

import argparse
import os

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
    p.set_defaults(func=_serve)


def _serve(args: argparse.Namespace) -> int:
    import uvicorn

    from cell.config import SAMPLE_TOKENS, ConfigError, load_config
    from cell.factory import all_simulated

    try:
        config = load_config(args.config)
    except ConfigError as err:
        return fail(err.code, str(err), False)
    sample = sorted(t.token for t in config.api.tokens if t.token in SAMPLE_TOKENS)
    if sample and not all_simulated(config):
        return fail("config_invalid", f"api.tokens: sample token(s) {', '.join(sample)} are "
                    "refused with real hardware; configure your own secret tokens", False)
    if args.config is not None:
        os.environ["CELL_CONFIG"] = os.path.abspath(args.config)
    else:
        os.environ.pop("CELL_CONFIG", None)
    import logging
    import logging.config

    from cell.logs import log_config
    from estimator.kernels import warm_up

    logging_config = log_config(args.log_format, args.log_level)
    logging.config.dictConfig(logging_config)
    log = logging.getLogger("cell.serve")

    def say(message: str) -> None:
        if args.log_format == "json":
            log.info(message)
        else:
            print(message, flush=True)

    # Compiled once per checkout (make install does it); loading takes a fraction of a second.
    say(f"estimator kernels ready in {warm_up():.1f} s")
    say(f"serving the cell on http://{args.host}:{args.port} (docs at /docs); state in "
        f"{os.path.dirname(os.path.abspath(config.api.job_db))}")
    uvicorn.run("api.app:app_from_environment", factory=True, host=args.host, port=args.port,
                log_level=args.log_level, log_config=logging_config)
    return 0
