"""``python -m cell.bench.controller``: numbers for the simulated controller on this machine.

With two CPU-burning processes running (``--no-load`` to skip them): the RTDE stream as it
arrives at the client, on the host's clock (packages per second of host time, the largest and
99th-percentile gap between arrivals: what a client's control loop meets; the controller's own
timestamps only say the controller kept its cycle), read by a plain socket and through
ur_rtde (a new ``timestamp`` seen by polling), then the controller's timestamps as ur_rtde
records them, the
controller process's CPU, a mailbox round trip, and servoL tracking along a 200 mm line at
100 and 250 mm/s, streamed as ur_rtde's realtime_control example does (500 Hz, initPeriod /
waitPeriod, lookahead 0.1 s, gain 300): the largest distance of the actual TCP from the line
(path error), the largest and median distance from the target sent in the same cycle (which
includes the lag a real controller has too), and whether the controller tripped.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import os
import socket
import statistics
import struct
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from fakes.ur_controller.load import cpu_burners
from fakes.ur_controller.process import ControllerProcess


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rtde_record_stats(path: Path) -> tuple[float, float, int]:
    """(rows per second of controller time, max timestamp gap s, rows) of a ur_rtde recording."""
    with path.open() as f:
        stamps = [float(row["timestamp"]) for row in csv.DictReader(f)]
    span = stamps[-1] - stamps[0]
    gaps = np.diff(stamps)
    return (len(stamps) - 1) / span, float(gaps.max()), len(stamps)


def arrival_stats(arrivals_s: list[float]) -> dict[str, float]:
    """Packages per second of host time and the largest and p99 gaps (ms) between arrivals."""
    gaps = np.diff(arrivals_s)
    return {"per_s": (len(arrivals_s) - 1) / (arrivals_s[-1] - arrivals_s[0]),
            "gap_max_ms": 1000.0 * float(gaps.max()),
            "gap_p99_ms": 1000.0 * float(np.percentile(gaps, 99)), "n": float(len(arrivals_s))}


def raw_rtde_stream(host: str, seconds: float) -> tuple[float, float, int, list[float]]:
    """Every data package of a 500 Hz ``timestamp`` recipe, read by a plain socket client:
    (packages per second of controller time, max timestamp gap s, packages, and each
    package's arrival on the host clock, time.monotonic of the read that brought it)."""
    from fakes.ur_controller import rtde

    stamps: list[float] = []
    arrivals: list[float] = []
    with socket.create_connection((host, rtde.RTDE_PORT), timeout=2.0) as sock:
        sock.sendall(rtde.encode(rtde.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)))
        sock.sendall(rtde.encode(rtde.CONTROL_PACKAGE_SETUP_OUTPUTS,
                                 struct.pack(">d", 500.0) + b"timestamp"))
        sock.sendall(rtde.encode(rtde.CONTROL_PACKAGE_START))
        reader = rtde.PackageReader()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            data = sock.recv(65536)
            t_arrival = time.monotonic()
            for kind, payload in reader.feed(data):
                if kind == rtde.DATA_PACKAGE:
                    stamps.append(struct.unpack(">Bd", payload)[1])
                    arrivals.append(t_arrival)
    gaps = np.diff(stamps)
    return ((len(stamps) - 1) / (stamps[-1] - stamps[0]), float(gaps.max()), len(stamps),
            arrivals)


def ur_rtde_arrivals(r: object, seconds: float, poll_s: float = 0.0002) -> list[float]:
    """Host times at which ur_rtde's receive interface shows a new controller ``timestamp``
    (polled every ``poll_s``: the arrival as a client loop reading ur_rtde can see it)."""
    import rtde_receive

    assert isinstance(r, rtde_receive.RTDEReceiveInterface)
    arrivals: list[float] = []
    last = r.getTimestamp()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        ts = r.getTimestamp()
        if ts != last:
            arrivals.append(time.monotonic())
            last = ts
        time.sleep(poll_s)
    return arrivals


def servo_line(c: object, r: object, speed_mm_s: float, length_mm: float = 200.0
               ) -> dict[str, float]:
    """Stream servoL along -y and back; errors in mm."""
    import rtde_control
    import rtde_receive

    assert isinstance(c, rtde_control.RTDEControlInterface)
    assert isinstance(r, rtde_receive.RTDEReceiveInterface)
    start = np.array(r.getActualTCPPose())
    dt = 0.002
    n = int(length_mm / speed_mm_s / dt)
    path_err, target_err = [], []
    for leg in (1.0, -1.0):
        for i in range(1, n + 1):
            t_start = c.initPeriod()
            s = i / n if leg > 0 else 1.0 - i / n
            target = start.copy()
            target[1] -= s * length_mm / 1000.0
            c.servoL(target.tolist(), 0.5, 0.5, dt, 0.1, 300)
            actual = np.array(r.getActualTCPPose())
            target_err.append(1000.0 * float(np.linalg.norm(actual[:3] - target[:3])))
            off_line = actual[:3] - start[:3]
            off_line[1] = 0.0
            path_err.append(1000.0 * float(np.linalg.norm(off_line)))
            c.waitPeriod(t_start)
    c.servoStop(10.0)
    tripped = r.getSafetyMode() != 1
    return {"path_max": max(path_err), "target_max": max(target_err),
            "target_median": statistics.median(target_err), "tripped": float(tripped)}


@contextlib.contextmanager
def _maybe_load(load: bool) -> Iterator[None]:
    if load:
        with cpu_burners(2, max_s=300.0):
            yield
    else:
        yield


def main(args: argparse.Namespace) -> int:
    import rtde_control
    import rtde_receive

    with ControllerProcess(powered=True) as ctl, _maybe_load(not args.no_load):
        print(f"host load: {'2 CPU-burning processes' if not args.no_load else 'none'} "
              f"on {os.cpu_count()} cores")
        time.sleep(1.0)
        r = rtde_receive.RTDEReceiveInterface(ctl.host, 500.0)
        rate, gap, rows, arrivals = raw_rtde_stream(ctl.host, args.seconds)
        a = arrival_stats(arrivals)
        print(f"RTDE arrival at the client, host clock (plain socket reader, every package): "
              f"{a['per_s']:.1f} packages/s, gap between arrivals max {a['gap_max_ms']:.1f} ms, "
              f"p99 {a['gap_p99_ms']:.1f} ms, {rows} packages")
        a = arrival_stats(ur_rtde_arrivals(r, args.seconds))
        print(f"RTDE arrival through ur_rtde, host clock (a new timestamp polled every 0.2 ms): "
              f"{a['per_s']:.1f} updates/s, gap max {a['gap_max_ms']:.1f} ms, p99 "
              f"{a['gap_p99_ms']:.1f} ms")
        print(f"  the same plain-socket stream on the controller's own clock: {rate:.1f} "
              f"packages/s, max timestamp gap {1000 * gap:.1f} ms")
        with tempfile.TemporaryDirectory() as tmp:
            rec = Path(tmp) / "rec.csv"
            c0, t0 = _cpu_s(ctl.pid), time.monotonic()
            r.startFileRecording(str(rec), ["timestamp", "actual_q", "actual_TCP_pose"])
            time.sleep(args.seconds)
            r.stopFileRecording()
            cpu = 100.0 * (_cpu_s(ctl.pid) - c0) / (time.monotonic() - t0)
            rate, gap, rows = rtde_record_stats(rec)
        print(f"  ur_rtde startFileRecording (record_data), controller's clock: {rate:.1f} "
              f"rows/s (asked 500), max timestamp gap {1000 * gap:.1f} ms, {rows} rows; "
              f"controller CPU {cpu:.0f} %")
        c = rtde_control.RTDEControlInterface(ctl.host)
        rtts = []
        for _ in range(50):
            t1 = time.perf_counter()
            c.getForwardKinematics()
            rtts.append(time.perf_counter() - t1)
        print(f"mailbox round trip (getForwardKinematics): median "
              f"{1000 * statistics.median(rtts):.1f} ms, max {1000 * max(rtts):.1f} ms")
        for speed in (100.0, 250.0):
            res = servo_line(c, r, speed)
            print(f"servoL {speed:.0f} mm/s along 200 mm and back: path error max "
                  f"{res['path_max']:.3f} mm, distance to the cycle's target max "
                  f"{res['target_max']:.2f} mm (median {res['target_median']:.2f}), "
                  f"{'TRIPPED' if res['tripped'] else 'no protective stop'}")
            if res["tripped"]:
                print("  last stop:", ctl.state()["messages"][-1:])
                break
        c.stopScript()
        c.disconnect()
        r.disconnect()
    return 0
