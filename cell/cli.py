"""The ``cell`` console script. Each feature registers its subcommand from ``cell.commands``.

Conventions every command shares: ``--json`` works in the same places for all of them (after
the last action word, as in ``cell calibrate hand-eye DIR --json``, or right after ``cell``)
and turns off progress bars; exit status 0 is success, 1 a result that says "no" (a missed
benchmark target, hand-eye data that disagree), 2 an error (printed as ``{"error": {"code",
"message"}}`` with ``--json``).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator, Sequence

from cell.commands import COMMANDS

NO_JSON = frozenset({"serve"})  # the service logs; --log-format json is its switch


def version() -> str:
    from importlib import metadata  # ~0.1 s of imports every command would pay at start

    try:
        return metadata.version("ur-vision-cell")
    except metadata.PackageNotFoundError:  # running from a source tree that is not installed
        return "unknown"


def _parsers(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                if name not in NO_JSON:
                    yield from _parsers(child)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cell", description="Vision-guided UR cell: estimation, commissioning, service."
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for register in COMMANDS:
        register(sub)
    # SUPPRESS: a level that does not see --json leaves what another level set.
    for p in _parsers(parser):
        p.add_argument("--json", action="store_true", default=argparse.SUPPRESS,
                       help="machine-readable output (no progress bars)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.json = getattr(args, "json", False)
    try:
        code: int = args.func(args)
    except BrokenPipeError:  # output piped into e.g. `head`: not an error of the command
        sys.stderr.close()
        return 0
    return code


if __name__ == "__main__":
    sys.exit(main())
