"""``cell bench``: the estimator against OpenCV pipelines on identical rendered frames.

``--check`` turns the estimator's speed and accuracy targets (``TARGETS`` in
:mod:`cell.bench.estimator`) into the exit status: 1 when any is missed (the report is printed
either way), so a CI job or an integrator's script can gate on it.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable
from typing import Any

from cell.calibration.defaults import DEFAULT_VIEWS


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("bench", help="benchmark the estimator against OpenCV pipelines",
                       description="Times and pose errors on rendered 1280x800 frames "
                                   "(see cell/bench/estimator.py for what is measured and how).")
    p.add_argument("--frames", type=int, default=60, help="rendered frames (default 60)")
    p.add_argument("--scenes", type=int, default=1000,
                   help="random scenes for the 0.5 px accuracy comparison (default 1000)")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--config", metavar="CELL.toml", default=None,
                   help="take the camera from this config (default: the simulated cell)")
    p.add_argument("--check", action="store_true",
                   help="exit with status 1 when a target is missed")
    p.set_defaults(func=_bench)
    what = p.add_subparsers(dest="bench_command", required=False,
                            metavar="{approach,pick,drift,service,soak,bias,freeze,modbus,fixed,"
                                    "commissioning,controller,live-view,loops}")
    a = what.add_parser(
        "approach", help="servo vs look-and-move approach, conveyor tracking, lost target",
        description="On the simulated cell through the UR adapter and ur_rtde (see "
                    "cell/bench/approach.py): the same seeded placements for both approach "
                    "modes, conveyor tracking at 25/50/100/150 mm/s, then a lost-target stop, "
                    "in the realistic simulated world unless --world ideal.")
    a.add_argument("--placements", type=int, default=10, help="random placements (default 10)")
    a.add_argument("--seed", type=int, default=0, help="random seed")
    a.add_argument("--lost-after-s", type=float, default=None,
                   help="override [servo] lost_after_s (default: the config's, 0.1 s)")
    a.add_argument("--world", choices=("realistic", "ideal"), default="realistic",
                   help="the simulated truth: realistic (default; lens, mount, arm geometry, "
                        "camera timing, motion blur and light off what the cell believes) or "
                        "ideal (the config is the truth)")
    a.add_argument("--commissioned", action="store_true",
                   help="commission the simulated cell first, as an integrator does before a "
                        "cell works: the lens from a circle-grid plate into [camera], then the "
                        "hand-eye routine (the HTTP API's job) and Apply (its AX = XB result "
                        "when the verdict blames the arm's poses, docs/calibration.md)")
    a.add_argument("--no-ibvs", action="store_true",
                   help="skip the IBVS section (its own cells, cell/bench/ibvs.py)")
    a.add_argument("--check", action="store_true",
                   help="exit with status 1 when a target is missed")
    a.add_argument("--tracking", action="store_true",
                   help="only the tracking section: 30 runs at 25/50/100/150 mm/s (10 at 100 "
                        "and 150), false target_lost counted first, then covered-lens stops")
    a.add_argument("--tracking-runs", type=int, default=None,
                   help="with --tracking: this many runs at each speed instead")
    a.add_argument("--track-speeds", type=_speeds, default=None, metavar="MM_S[,MM_S...]",
                   help="with --tracking: these conveyor speeds instead (10 runs each unless "
                        "--tracking-runs), e.g. 30")
    a.set_defaults(func=_bench_approach)
    pk = what.add_parser(
        "pick", help="pick and place of parts of two layouts, missed grasps, a stop per phase",
        description="On the simulated cell through the UR adapter and ur_rtde with the "
                    "simulated gripper (see cell/bench/pick.py): parts of two layouts on "
                    "blocks in view, each picked and placed at its own taught place pose and "
                    "scored against the simulator's truth; a part moved after the last look; "
                    "a stop in each phase of the pick.")
    pk.add_argument("--parts", type=int, default=10,
                    help="parts in view, half of each layout (default 10, at most 10)")
    pk.add_argument("--seed", type=int, default=0, help="random seed")
    pk.add_argument("--missed-runs", type=int, default=None,
                    help="picks with the part moved after the last look (default: --parts)")
    pk.add_argument("--world", choices=("realistic", "ideal"), default="realistic",
                    help="the simulated truth (see cell bench approach --help)")
    pk.add_argument("--commissioned", action="store_true",
                    help="commission the simulated cell first (lens, then hand-eye and Apply), "
                         "as cell bench approach --commissioned does")
    pk.add_argument("--check", action="store_true",
                    help="exit with status 1 when a target is missed")
    pk.set_defaults(func=_bench_pick)
    dr = what.add_parser(
        "drift", help="the calibration check against a knocked camera: detection, false alarms",
        description="On the simulated cell, commissioned, the reference recorded at home (see "
                    "cell/bench/drift.py): checks with nothing changed (false alarms), then the "
                    "camera mount knocked by 0.2/0.5/1/2 mm and 0.1/0.2/0.3/1 deg in random "
                    "directions: each check's verdict and figure at the tool against the true "
                    "error of an approach made after the knock.")
    dr.add_argument("--repeats", type=int, default=3, help="knocks of each size (default 3)")
    dr.add_argument("--clean-checks", type=int, default=10,
                    help="checks with nothing changed (default 10)")
    dr.add_argument("--burners", type=int, default=0,
                    help="CPU-burning processes beside the clean checks (default 0)")
    dr.add_argument("--translations", type=float, nargs="*", default=None, metavar="MM",
                    help="knock sizes in mm (default 0.2 0.5 1 2)")
    dr.add_argument("--rotations", type=float, nargs="*", default=None, metavar="DEG",
                    help="knock sizes in deg (default 0.1 0.2 0.3 1)")
    dr.add_argument("--seed", type=int, default=0, help="random seed")
    dr.add_argument("--world", choices=("realistic", "ideal"), default="realistic")
    dr.add_argument("--no-commission", action="store_true",
                    help="skip commissioning (the configured lens and mount)")
    dr.add_argument("--check", action="store_true", help="exit 1 when a target is missed")
    dr.set_defaults(func=_bench_drift)
    svc = what.add_parser(
        "service", help="the simulated cell service under load: STOP, status, SSE, idle CPU",
        description="Serves the simulated cell, measures idle CPU by process, then runs 50 "
                    "status pollers, 10 SSE streams and 2 live views while STOP is sent 100+ "
                    "times with the arm jogging (see cell/bench/service.py).")
    svc.add_argument("--duration", type=float, default=20.0, help="load seconds (default 20)")
    svc.add_argument("--idle", type=float, default=5.0, help="idle seconds (default 5)")
    svc.add_argument("--pollers", type=int, default=50)
    svc.add_argument("--streams", type=int, default=10)
    svc.add_argument("--viewers", type=int, default=2)
    svc.add_argument("--viewer-image", choices=("jpg", "png"), default="jpg",
                     help="jpg: the live view as the operator page shows it (default); png: a "
                          "full-size still encoded per request")
    svc.add_argument("--stops", type=int, default=100, help="at least this many stops")
    svc.add_argument("--service-nice", type=int, default=-5,
                     help="the service's nice value, as the systemd unit sets it (default -5; "
                          "applied when the host allows it, see the report's \"nice\")")
    svc.add_argument("--inherit-nice", action="store_true",
                     help="serve at this process's own nice value instead")
    svc.set_defaults(func=_bench_service)
    sk = what.add_parser(
        "soak", help="production cycles on the simulated cell service: memory, fds, threads",
        description="Serves the simulated cell and runs home, locate, look-and-move, gripper "
                    "close/open (every 5th cycle a servo approach and a 5 s track) while status "
                    "and the live frame are polled at 7 Hz, an SSE stream and an RTDE reader "
                    "are open; reports RSS, fds, threads and the job database per minute and "
                    "their growth per hour (see cell/bench/soak.py).")
    sk.add_argument("--minutes", type=float, default=15.0, help="soak minutes (default 15)")
    sk.add_argument("--cycles", type=int, default=None,
                    help="stop after this many cycles (default: when the minutes are up)")
    sk.add_argument("--interfaces", action="store_true",
                    help="serve OPC UA, XML-RPC and Modbus too (on sim.toml's fixed ports)")
    sk.add_argument("--burners", type=int, default=0,
                    help="CPU-burning processes beside the soak for the whole run (default 0)")
    sk.add_argument("--out", metavar="FILE.json", default=None,
                    help="also write the JSON report here")
    sk.add_argument("--service-log", metavar="FILE", default=None,
                    help="keep the service's warnings and errors in this file")
    sk.add_argument("--service-nice", type=int, default=-5,
                    help="the service's nice value, as the systemd unit sets it (default -5; "
                         "applied when the host allows it, see the report's load)")
    sk.add_argument("--inherit-nice", action="store_true",
                    help="serve at this process's own nice value instead")
    sk.set_defaults(func=_bench_soak)
    bias = what.add_parser(
        "bias", help="the simulated camera's dot centre bias ([ibvs] centroid_bias_px)",
        description="Moves the simulated cell's target over two pixels in small steps and "
                    "measures the part of each dot's centre that averaging frames does not "
                    "remove (see cell/bench/centroid_bias.py).")
    bias.add_argument("--frames", type=int, default=30,
                      help="rendered frames averaged at each step (default 30)")
    bias.add_argument("--steps", type=int, default=41,
                      help="steps over the two pixels of each sweep (default 41)")
    bias.set_defaults(func=_bench_bias)
    frz = what.add_parser(
        "freeze", help="freeze the service or its ur_rtde child while the arm moves",
        description="Streams 50 mm/s twists to the simulated controller, freezes the host "
                    "process or its ur_rtde child for 2 s (SIGSTOP), and measures from the "
                    "controller's own state when the arm stood and how far it went (see "
                    "cell/bench/freeze.py).")
    frz.add_argument("--runs", type=int, default=3, help="freezes of each process (default 3)")
    frz.add_argument("--check", action="store_true",
                     help="exit with status 1 when a target is missed")
    frz.set_defaults(func=_bench_freeze)
    mb = what.add_parser(
        "modbus", help="STOP written over Modbus TCP to the simulated arm's receipt",
        description="A pymodbus client starts approaches over the handshake and stops each "
                    "mid-motion (see cell/bench/modbus.py).")
    mb.add_argument("--stops", type=int, default=100, help="stops (default 100)")
    mb.add_argument("--check", action="store_true",
                    help="exit with status 1 when the 20 ms p99 target is missed")
    mb.set_defaults(func=_bench_modbus)
    fx = what.add_parser(
        "fixed", help="locate accuracy of a fixed camera at 1 m, and approaches with it",
        description="Renders the fixed camera of cell/configs/sim-fixed.toml at random target "
                    "poses and compares each locate with the simulated truth (see "
                    "cell/bench/fixed.py).")
    fx.add_argument("--poses", type=int, default=20, help="target poses (default 20; 0: none)")
    fx.add_argument("--tilt-deg", type=float, default=30.0, help="largest tilt (default 30)")
    fx.add_argument("--distance-mm", type=float, default=1000.0,
                    help="camera to target (default 1000)")
    fx.add_argument("--seed", type=int, default=1, help="random seed")
    fx.add_argument("--approaches", type=int, default=0,
                    help="also run this many approaches on the simulated fixed-camera cell")
    fx.add_argument("--servo", action="store_true",
                    help="approach by the closed-loop servo instead of look-and-move")
    fx.add_argument("--lost-after-s", type=float, default=None,
                    help="override [servo] lost_after_s for --servo (default: the config's)")
    fx.add_argument("--stall-after-s", type=float, default=None,
                    help="override [servo] stall_after_s for --servo (default: the config's, "
                         "1 s; a 12 MP render here can take longer)")
    fx.add_argument("--preview", action="store_true",
                    help="approach on the colour image scaled 1/3 (1352x1013) instead of 12 MP")
    fx.add_argument("--ibvs", type=int, default=0, metavar="N",
                    help="also run N IBVS approaches to a taught view of the plate on the tool "
                         "(the camera off its configured pose by a few mm / tenths of a deg)")
    fx.add_argument("--render", type=int, default=0, metavar="N",
                    help="also time N renders and estimates per sensor (a frame's cost)")
    fx.set_defaults(func=_lazy("fixed"))
    cm = what.add_parser(
        "commissioning", help="hand-eye routine in the realistic simulated world vs its truth",
        description="Look-and-move approaches before and after the hand-eye routine on the "
                    "simulated cell with [sim] world = \"realistic\": true errors, the jobs' "
                    "own estimates and consistency verdicts (see cell/bench/commissioning.py).")
    cm.add_argument("--placements", type=int, default=5, help="random placements (default 5)")
    cm.add_argument("--views", type=int, default=DEFAULT_VIEWS,
                    help=f"routine views (default {DEFAULT_VIEWS}, with 30 deg tilts and 60 deg "
                         "rolls: enough to fit the arm's geometry with the mount)")
    cm.add_argument("--seed", type=int, default=0, help="random seed")
    cm.add_argument("--world", choices=("realistic", "ideal"), default="realistic")
    cm.set_defaults(func=_lazy("commissioning"))
    ctl = what.add_parser(
        "controller", help="the simulated controller's own timing and CPU on this machine",
        description="RTDE rate and gaps, mailbox round trip and servoL tracking of the "
                    "simulated controller, beside two CPU burners (see cell/bench/controller.py).")
    ctl.add_argument("--no-load", action="store_true", help="no CPU-burning processes")
    ctl.add_argument("--seconds", type=float, default=5.0, help="RTDE recording length")
    ctl.set_defaults(func=_lazy("controller"))
    lv = what.add_parser(
        "live-view", help="the service's CPU with 0, 1 and 5 live viewers",
        description="Serves the simulated cell and reads its CPU from /proc while viewers "
                    "fetch overlaid frames as the operator page does (see "
                    "cell/bench/live_view.py).")
    lv.add_argument("--seconds", type=float, default=15.0, help="seconds per step (default 15)")
    lv.set_defaults(func=_lazy("live_view"))
    lp = what.add_parser(
        "loops", help="servo and IBVS to a view taught with the camera's mount off",
        description="Teaches a view (at home, then nearer and tilted, in turn) on a simulated "
                    "cell whose camera mount is off the hand-eye calibration, jogs away and "
                    "approaches it in each mode; each run's true error beside the error the "
                    "job claims (see cell/bench/loops.py).")
    lp.add_argument("--repeats", type=int, default=3,
                    help="teaches, each followed by one run per jog and mode (default 3)")
    lp.add_argument("--burners", type=int, default=0,
                    help="CPU-burning processes beside the runs (default 0)")
    lp.add_argument("--teach-samples", type=int, default=5, metavar="N",
                    help="samples a teach takes, each [teach] frames_per_sample frames "
                         "(default 5); the view is taught again for every repeat")
    lp.add_argument("--arm", choices=("ur", "sim"), default="ur",
                    help="ur (default): through the UR adapter, ur_rtde and the simulated "
                         "controller, as `make run` serves the cell; sim: the in-process arm")
    lp.set_defaults(func=_lazy("loops"))


def _speeds(text: str) -> list[float]:
    """``--track-speeds``: conveyor speeds in mm/s, comma-separated, each 1..300."""
    try:
        speeds = [float(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of numbers: {text!r}") from None
    if not speeds or not all(1.0 <= v <= 300.0 for v in speeds):
        raise argparse.ArgumentTypeError(f"speeds are 1..300 mm/s: {text!r}")
    return speeds


def _bench_approach(args: argparse.Namespace) -> int:

    from cell.bench.approach import format_report, run_bench_approach
    from cell.commands.common import fail, progress_bars

    if args.placements < 1:
        return fail("invalid_argument", "--placements must be at least 1", args.json)
    if args.tracking:
        from cell.bench.approach import (
            TRACK_RUNS,
            format_tracking_report,
            run_bench_tracking,
        )

        n = args.tracking_runs
        if n is not None and n < 1:
            return fail("invalid_argument", "--tracking-runs must be at least 1", args.json)
        speeds = args.track_speeds
        if speeds is not None:
            runs: dict[float, int] | None = dict.fromkeys(speeds, n or 10)
        else:
            runs = None if n is None else dict.fromkeys(TRACK_RUNS, n)
        with progress_bars(not args.json) as progress:
            report = run_bench_tracking(runs=runs, progress=progress)
        return _report(args, report, format_tracking_report(report))
    with progress_bars(not args.json) as progress:
        report = run_bench_approach(placements=args.placements, seed=args.seed,
                                    progress=progress, lost_after_s=args.lost_after_s,
                                    world=args.world, ibvs=not args.no_ibvs,
                                    commissioned=args.commissioned)
    return _report(args, report, format_report(report))


def _bench_pick(args: argparse.Namespace) -> int:
    from cell.bench.pick import MAX_PARTS, format_report, run_bench_pick
    from cell.commands.common import fail, progress_bars

    if not 1 <= args.parts <= MAX_PARTS:
        return fail("invalid_argument", f"--parts must be 1 to {MAX_PARTS}", args.json)
    if args.missed_runs is not None and args.missed_runs < 0:
        return fail("invalid_argument", "--missed-runs must not be negative", args.json)
    with progress_bars(not args.json) as progress:
        report = run_bench_pick(parts=args.parts, seed=args.seed, world=args.world,
                                commissioned=args.commissioned, missed_runs=args.missed_runs,
                                progress=progress)
    return _report(args, report, format_report(report))


def _bench_drift(args: argparse.Namespace) -> int:
    from cell.bench.drift import format_report, run_bench_drift
    from cell.commands.common import fail, progress_bars

    if args.repeats < 1 or args.clean_checks < 0 or args.burners < 0:
        return fail("invalid_argument", "--repeats must be at least 1, --clean-checks and "
                    "--burners at least 0", args.json)
    sizes = {k: tuple(v) for k, v in (("translations_mm", args.translations),
                                      ("rotations_deg", args.rotations)) if v is not None}
    with progress_bars(not args.json) as progress:
        report = run_bench_drift(repeats=args.repeats, clean_checks=args.clean_checks,
                                 seed=args.seed, world=args.world,
                                 commissioned=not args.no_commission, burners=args.burners,
                                 progress=progress, **sizes)
    return _report(args, report, format_report(report))


def _bench_bias(args: argparse.Namespace) -> int:
    from cell.bench.centroid_bias import format_report, run_bench_bias
    from cell.commands.common import EXIT_OK, fail, print_json, progress_bars

    if args.frames < 1 or args.steps < 3:
        return fail("invalid_argument", "--frames must be at least 1 and --steps at least 3",
                    args.json)
    with progress_bars(not args.json) as progress:
        report = run_bench_bias(args.frames, args.steps, progress=progress)
    if args.json:
        print_json(report)
    else:
        print(format_report(report))
    return EXIT_OK


def _bench_freeze(args: argparse.Namespace) -> int:
    from cell.bench.freeze import format_report, run_bench_freeze
    from cell.commands.common import fail

    if args.runs < 1:
        return fail("invalid_argument", "--runs must be at least 1", args.json)
    report = run_bench_freeze(runs=args.runs)
    return _report(args, report, format_report(report))


def _bench(args: argparse.Namespace) -> int:

    from cell.bench.estimator import format_report, run_bench
    from cell.commands.common import fail, progress_bars
    from cell.config.schema import ConfigError, load_config

    if args.frames < 1 or args.scenes < 1:
        return fail("invalid_argument", "--frames and --scenes must be at least 1", args.json)
    try:
        camera = load_config(args.config).camera.model()
    except ConfigError as err:
        return fail(err.code, str(err), args.json)
    with progress_bars(not args.json) as progress:
        report = run_bench(camera, frames=args.frames, scenes=args.scenes, seed=args.seed,
                           progress=progress)
    return _report(args, report, format_report(report))


def _report(args: argparse.Namespace, report: dict[str, Any], text: str) -> int:
    """Print a benchmark's report (JSON or text); with ``--check``, exit 1 on a missed target."""
    from cell.commands.common import EXIT_NO, EXIT_OK, print_json

    if args.json:
        print_json(report)
    else:
        print(text)
    missed = [k for k, met in report["targets_met"].items() if not met]
    if args.check and missed:
        if not args.json:
            print(f"targets missed: {', '.join(missed)}", file=sys.stderr)
        return EXIT_NO
    return EXIT_OK


def _bench_service(args: argparse.Namespace) -> int:
    from cell.bench.service import ServiceBenchConfig, format_report, run_service_bench
    from cell.commands.common import EXIT_OK, fail, print_json

    if min(args.duration, args.idle) <= 0 or min(args.pollers, args.streams, args.viewers,
                                                 args.stops) < 0:
        return fail("invalid_argument", "durations must be positive and counts not negative",
                    args.json)
    cfg = ServiceBenchConfig(duration_s=args.duration, idle_s=args.idle, pollers=args.pollers,
                             streams=args.streams, viewers=args.viewers, min_stops=args.stops,
                             viewer_image=args.viewer_image,
                             service_nice=None if args.inherit_nice else args.service_nice)
    try:
        report = run_service_bench(cfg)
    except RuntimeError as err:
        return fail("bench_failed", str(err), args.json)
    if args.json:
        print_json(report)
    else:
        print(format_report(report))
    return EXIT_OK


def _bench_soak(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from cell.bench.soak import format_report, run_soak
    from cell.commands.common import EXIT_OK, fail, print_json, progress_bars

    if args.minutes <= 0 or (args.cycles is not None and args.cycles < 1) or args.burners < 0:
        return fail("invalid_argument", "--minutes must be positive, --cycles at least 1 and "
                    "--burners not negative", args.json)
    try:
        with progress_bars(not args.json) as progress:
            report = run_soak(args.minutes, max_cycles=args.cycles,
                              interfaces=args.interfaces, progress=progress,
                              burners=args.burners,
                              service_nice=None if args.inherit_nice else args.service_nice,
                              service_log=Path(args.service_log) if args.service_log else None)
    except RuntimeError as err:
        return fail("bench_failed", str(err), args.json)
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1))
    if args.json:
        print_json(report)
    else:
        print(format_report(report))
    return EXIT_OK


def _bench_modbus(args: argparse.Namespace) -> int:
    import json

    from cell.bench.modbus import run

    report = run(args.stops)
    print(json.dumps(report, indent=2))
    return 1 if args.check and not report["met"] else 0


def _lazy(module: str) -> Callable[[argparse.Namespace], int]:
    """The benchmark module's ``main``, imported only when it runs (it loads the simulator)."""

    def run(args: argparse.Namespace) -> int:
        return int(importlib.import_module(f"cell.bench.{module}").main(args) or 0)

    return run
