"""``python -m fakes.ur_controller.bench``: numbers for the simulated controller and the UR
adapter on this machine (stream rate, command round trips, CPU of the controller process)."""

from __future__ import annotations

import os
import statistics
import time

from fakes.ur_controller.process import ControllerProcess


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _cpu_percent(pid: int, seconds: float) -> float:
    c0, t0 = _cpu_s(pid), time.monotonic()
    time.sleep(seconds)
    return 100.0 * (_cpu_s(pid) - c0) / (time.monotonic() - t0)


def main() -> None:
    import rtde_control
    import rtde_receive

    from drivers.ur import URArm

    with ControllerProcess(powered=True) as ctl:
        pid = ctl.pid
        time.sleep(1.0)
        print(f"controller idle CPU: {_cpu_percent(pid, 2.0):.1f} %")
        r = rtde_receive.RTDEReceiveInterface(ctl.host)
        stamps: list[float] = []
        t_end = time.monotonic() + 2.0
        while time.monotonic() < t_end:
            ts = r.getTimestamp()
            if not stamps or ts != stamps[-1]:
                stamps.append(ts)
            time.sleep(0.0002)
        rate = (len(stamps) - 1) / (stamps[-1] - stamps[0])
        print(f"RTDE stream: {rate:.0f} Hz controller-side timestamps seen (asked 500 Hz)")
        c = rtde_control.RTDEControlInterface(ctl.host)
        print(f"controller CPU, 2 clients streaming at 500 Hz: {_cpu_percent(pid, 2.0):.1f} %")
        rtts = []
        for _ in range(50):
            t0 = time.perf_counter()
            c.getForwardKinematics()
            rtts.append(time.perf_counter() - t0)
        print(f"mailbox round trip (getForwardKinematics): median "
              f"{1000 * statistics.median(rtts):.1f} ms, max {1000 * max(rtts):.1f} ms")
        c.stopScript()
        c.disconnect()
        r.disconnect()

        arm = URArm(ctl.host)
        t0 = time.perf_counter()
        arm.connect()
        arm.power_on()
        print(f"URArm connect + power_on: {time.perf_counter() - t0:.2f} s")
        lat = []
        for _ in range(200):
            t0 = time.perf_counter()
            arm.tcp_pose()
            lat.append(time.perf_counter() - t0)
        print(f"URArm.tcp_pose(): median {1e3 * statistics.median(lat):.2f} ms, "
              f"max {1e3 * max(lat):.2f} ms")
        T0 = arm.tcp_pose()
        T1 = T0.copy()
        T1[2, 3] -= 100.0
        t0 = time.perf_counter()
        arm.move_linear(T1, 250.0, 1200.0)
        print(f"URArm.move_linear 100 mm @ 250 mm/s, 1200 mm/s^2: "
              f"{time.perf_counter() - t0:.3f} s (profile 0.608 s)")
        arm.disconnect()


if __name__ == "__main__":
    main()
