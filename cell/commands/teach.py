"""``cell teach {add,list,show,delete}``: taught reference poses on a running cell service.

A client of the HTTP API rather than a second owner of the hardware: the service holds the
arm and camera, and two processes driving one arm is how cells crash. ``add`` teaches at the
arm's current resting pose (jog it there first); ``approach`` then takes ``taught=NAME``.
"""

from __future__ import annotations

import argparse
import os
from typing import Any


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("teach", help="teach, list, show and delete named tool poses "
                       "(T_target_tcp) on a running cell service")
    p.add_argument("--url", default=os.environ.get("CELL_URL", "http://127.0.0.1:8000"),
                   help="the cell service (default $CELL_URL or http://127.0.0.1:8000)")
    p.add_argument("--token", default=os.environ.get("CELL_TOKEN"),
                   help="bearer token (default $CELL_TOKEN); teaching needs an operator token")
    what = p.add_subparsers(dest="teach_command", required=True, metavar="ACTION")
    add = what.add_parser("add", help="teach NAME at the arm's current pose")
    add.add_argument("name")
    add.add_argument("--samples", type=int, default=5, help="locates averaged (default 5)")
    add.add_argument("--max-spread-mm", type=float, default=None)
    add.add_argument("--max-spread-deg", type=float, default=None)
    add.add_argument("--no-replace", action="store_true", help="refuse if NAME is taught")
    what.add_parser("list", help="the taught poses")
    for name, text in (("show", "one taught pose"), ("delete", "forget a taught pose")):
        q = what.add_parser(name, help=text)
        q.add_argument("name")
    p.set_defaults(func=run)


def _client(args: argparse.Namespace) -> Any:
    """An httpx client for the service (tests substitute the in-process app's client)."""
    import httpx

    return httpx.Client(base_url=args.url, timeout=30.0)


def run(args: argparse.Namespace) -> int:
    import httpx

    from cell.commands.common import fail, print_json

    if not args.token:
        return fail("unauthorized", "no token: pass --token or set CELL_TOKEN", args.json)
    headers = {"Authorization": f"Bearer {args.token}"}
    cmd = args.teach_command
    try:
        client = _client(args)
        if cmd == "add":
            body: dict[str, Any] = {"name": args.name, "samples": args.samples,
                                    "replace": not args.no_replace}
            if args.max_spread_mm is not None:
                body["max_spread_mm"] = args.max_spread_mm
            if args.max_spread_deg is not None:
                body["max_spread_deg"] = args.max_spread_deg
            r = client.post("/api/v1/teach", json=body, headers=headers)
        elif cmd == "list":
            r = client.get("/api/v1/teach", headers=headers)
        elif cmd == "show":
            r = client.get(f"/api/v1/teach/{args.name}", headers=headers)
        else:
            r = client.delete(f"/api/v1/teach/{args.name}", headers=headers)
    except httpx.HTTPError as err:
        return fail("service_unreachable", f"cannot reach the cell at {args.url}: {err}",
                    args.json)
    try:
        out = r.json()
    except ValueError:
        return fail("bad_response", f"HTTP {r.status_code}: {r.text[:200]}", args.json)
    if r.status_code != 200:
        error = out.get("error", {}) if isinstance(out, dict) else {}
        return fail(error.get("code", f"http_{r.status_code}"),
                    error.get("message", r.text[:200]), args.json)
    if args.json:
        print_json(out)
    elif cmd == "list":
        for pose in out["taught"]:
            print(_line(pose))
        if not out["taught"]:
            print("no taught poses")
    else:
        print(_line(out["deleted"] if cmd == "delete" else out)
              + (" (deleted)" if cmd == "delete" else ""))
    return 0


def _line(pose: dict[str, Any]) -> str:
    t = pose["T_target_tcp"]
    pos = ", ".join(f"{v:.2f}" for v in t["position_mm"])
    rot = ", ".join(f"{v:.4f}" for v in t["rotvec_rad"])
    return (f"{pose['name']}: T_target_tcp position_mm [{pos}] rotvec_rad [{rot}], "
            f"{pose['samples']} samples, spread {pose['spread_mm']:.3f} mm / "
            f"{pose['spread_deg']:.3f} deg")
