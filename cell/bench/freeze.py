"""Freeze benchmark: how far the arm goes when the host stalls.

A host process streams servo twists at 50 mm/s through the UR adapter and ur_rtde to the
simulated controller; then either that process or its ur_rtde child is frozen (SIGSTOP) for
2 s. Measured from the simulated controller's own state (not through the frozen link): the
time from the freeze until the TCP stands, and the distance it travelled meanwhile. Without a
controller-side watchdog the arm would go on for the whole freeze (100 mm).
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import textwrap
import time
from typing import Any

import numpy as np

from fakes.ur_controller.process import ControllerProcess

SPEED_MM_S = 50.0
FREEZE_S = 2.0
TARGET_STILL_S = 0.25
TARGET_TRAVEL_MM = 10.0
STILL_SPEED_M_S = 1e-4  # under 0.1 mm/s counts as standing

_HOST = textwrap.dedent("""
    import sys, time
    import numpy as np
    from drivers.ur.adapter import URArm
    arm = URArm(sys.argv[1])
    arm.connect()
    arm.power_on()
    print("child", arm._client._proc.pid, flush=True)
    v = float(sys.argv[2])
    while True:
        arm.servo_twist(np.array([v, 0, 0, 0, 0, 0]), 500.0, 0.25)
        time.sleep(0.02)
""")


def still_after(ctl: ControllerProcess, t_freeze: float, p_freeze: np.ndarray,
                timeout_s: float = 5.0) -> tuple[float, float]:
    """Poll the controller's own TCP until it stands: (s after the freeze, mm travelled)."""
    last = np.asarray(ctl.state()["tcp_pose"][:3])
    last_t = time.monotonic()
    while time.monotonic() < t_freeze + timeout_s:
        time.sleep(0.01)
        p = np.asarray(ctl.state()["tcp_pose"][:3])
        now = time.monotonic()
        if np.linalg.norm(p - last) / (now - last_t) < STILL_SPEED_M_S:
            return last_t - t_freeze, 1000.0 * float(np.linalg.norm(last - p_freeze))
        last, last_t = p, now
    return math.inf, 1000.0 * float(np.linalg.norm(last - p_freeze))


def freeze_once(which: str) -> dict[str, float]:
    """One run: stream, freeze ``which`` ("host" or "child") for FREEZE_S, measure."""
    with ControllerProcess(powered=True) as ctl:
        host = subprocess.Popen([sys.executable, "-c", _HOST, ctl.host, str(SPEED_MM_S)],
                                stdout=subprocess.PIPE, text=True)
        try:
            assert host.stdout is not None
            child_pid = int(host.stdout.readline().split()[1])
            time.sleep(0.6)  # at speed
            pid = host.pid if which == "host" else child_pid
            p0 = np.asarray(ctl.state()["tcp_pose"][:3])
            t0 = time.monotonic()
            os.kill(pid, signal.SIGSTOP)
            still_s, moved_mm = still_after(ctl, t0, p0)
            time.sleep(max(0.0, t0 + FREEZE_S - time.monotonic()))
            os.kill(pid, signal.SIGCONT)
            return {"still_s": still_s, "moved_mm": moved_mm}
        finally:
            host.kill()
            host.wait(timeout=5.0)


def run_bench_freeze(runs: int = 3) -> dict[str, Any]:
    """``runs`` freezes of each process; the worst figures first."""
    report: dict[str, Any] = {"speed_mm_s": SPEED_MM_S, "freeze_s": FREEZE_S, "runs": runs,
                              "load_avg_1m": os.getloadavg()[0]}
    met = {}
    for which in ("child", "host"):
        results = [freeze_once(which) for _ in range(runs)]
        still = [r["still_s"] for r in results]
        moved = [r["moved_mm"] for r in results]
        report[which] = {"still_s_max": max(still), "moved_mm_max": max(moved),
                         "still_s_p50": float(np.median(still)),
                         "moved_mm_p50": float(np.median(moved))}
        met[f"{which}_still_within_{TARGET_STILL_S}_s"] = max(still) <= TARGET_STILL_S
        met[f"{which}_travel_within_{TARGET_TRAVEL_MM}_mm"] = max(moved) <= TARGET_TRAVEL_MM
    report["targets_met"] = met
    return report


def format_report(report: dict[str, Any]) -> str:
    lines = [f"freeze of {report['freeze_s']} s at {report['speed_mm_s']} mm/s, "
             f"{report['runs']} runs each (load {report['load_avg_1m']:.2f})"]
    for which in ("child", "host"):
        r = report[which]
        lines.append(f"  {which:5s}: still after max {r['still_s_max'] * 1000:.0f} ms "
                     f"(p50 {r['still_s_p50'] * 1000:.0f}), travelled max "
                     f"{r['moved_mm_max']:.1f} mm (p50 {r['moved_mm_p50']:.1f})")
    return "\n".join(lines)
