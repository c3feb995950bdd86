"""The hand-eye routine's default number of views is one number: the routine's constant, the
API's request schema, the CLI's ``--views``, the operator page's field and every doc that
states a default."""

from __future__ import annotations

import re
from pathlib import Path

from api.http.routes.calibration import HandEyeRequest
from cell.calibration.defaults import DEFAULT_VIEWS
from cell.calibration.routine import RoutineSettings
from cell.cli import build_parser

ROOT = Path(__file__).resolve().parents[3]


def test_routine_api_cli_and_page_share_the_default_view_count() -> None:
    assert RoutineSettings().n_views == DEFAULT_VIEWS
    assert HandEyeRequest.model_json_schema()["properties"]["views"]["default"] == DEFAULT_VIEWS
    assert HandEyeRequest().views == DEFAULT_VIEWS
    args = build_parser().parse_args(["calibrate", "routine"])
    assert args.views == DEFAULT_VIEWS
    page = (ROOT / "api" / "http" / "static" / "index.html").read_text()
    field = re.search(r'<input data-testid="calib-views"[^>]*>', page)
    value = re.search(r'value="(\d+)"', field.group(0)) if field else None
    assert value and value.group(1) == str(DEFAULT_VIEWS)


def test_the_docs_state_the_same_default() -> None:
    stated = []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = " ".join(path.read_text().split())
        for m in re.finditer(r"(\d+) views by default|views? \(default (\d+)\)|"
                             r"default (\d+) views|default is (\d+) views|"
                             r"views: default (\d+)|default, (\d+) views", text):
            stated.append((path.name, next(g for g in m.groups() if g)))
    assert stated, "no doc states the routine's default"
    assert all(n == str(DEFAULT_VIEWS) for _, n in stated), stated
