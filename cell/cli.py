"""The ``cell`` console script. Each feature registers its subcommand from ``cell.commands``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from cell.commands import COMMANDS


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cell", description="Vision-guided UR cell: estimation, commissioning, service."
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for register in COMMANDS:
        register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code: int = args.func(args)
    except BrokenPipeError:  # output piped into e.g. `head`: not an error of the command
        sys.stderr.close()
        return 0
    return code


if __name__ == "__main__":
    sys.exit(main())
