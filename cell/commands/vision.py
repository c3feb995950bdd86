"""``cell detect`` and ``cell estimate`` (filled in by the estimator work)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    _ = sub
