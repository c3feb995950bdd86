"""``cell serve [--config FILE] [--host H] [--port N] [--ssl-certfile F --ssl-keyfile F]``:
the cell service and its HTTP API (HTTPS when given a certificate and key).

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
    p.add_argument("--log-level", default="info")
    p.add_argument("--ssl-certfile", default=None,
                   help="serve HTTPS with this certificate (PEM); needs --ssl-keyfile")
    p.add_argument("--ssl-keyfile", default=None, help="the certificate's private key (PEM)")
    p.set_defaults(func=_serve)


def _serve(args: argparse.Namespace) -> int:
    import uvicorn

    from cell.config import SAMPLE_TOKENS, ConfigError, load_config
    from cell.factory import all_simulated

    if bool(args.ssl_certfile) != bool(args.ssl_keyfile):
        return fail("invalid_arguments", "--ssl-certfile and --ssl-keyfile go together", False)
    for path in (args.ssl_certfile, args.ssl_keyfile):
        if path and not os.path.isfile(path):
            return fail("invalid_arguments", f"no such file: {path}", False)
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
    from estimator.kernels import warm_up

    # Compiled once per checkout (make install does it); loading takes a fraction of a second.
    print(f"estimator kernels ready in {warm_up():.1f} s", flush=True)
    scheme = "https" if args.ssl_certfile else "http"
    print(f"serving the cell on {scheme}://{args.host}:{args.port} (docs at /docs)", flush=True)
    uvicorn.run("api.app:app_from_environment", factory=True, host=args.host, port=args.port,
                log_level=args.log_level, ssl_certfile=args.ssl_certfile,
                ssl_keyfile=args.ssl_keyfile)
    return 0
