"""Helpers shared by subcommands: JSON output and typed errors -> exit code 2."""

from __future__ import annotations

import json
import sys
from typing import Any


def print_json(obj: Any) -> None:
    json.dump(obj, sys.stdout, indent=2)
    sys.stdout.write("\n")


def fail(code: str, message: str, as_json: bool) -> int:
    """Report a failure the documented way and return exit status 2."""
    if as_json:
        print_json({"error": {"code": code, "message": message}})
    else:
        print(f"error ({code}): {message}", file=sys.stderr)
    return 2
