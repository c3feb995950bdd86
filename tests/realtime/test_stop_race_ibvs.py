"""STOP raced against an IBVS approach's final settle, on a loaded host.

After the streamed loop has stopped the arm, the settle averages frames of the still view and
then makes small guarded straight moves (``[ibvs] settle_frames``, ``settle_steps``). A STOP
that lands while those frames are gathered, between two steps, or while a step moves must
end the job ``cancelled`` (never ``succeeded``), and once it has answered ``stopped: true``
the arm must not move again. Each race starts the approach from a jogged pose with the
camera's true mount off the hand-eye calibration (so the settle has steps to make) and sends
STOP a random delay after the settle began; two CPU-burning processes run beside it. Outcomes
are the simulator's truth.
"""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import cell.servoing.image as image_law
from cell.service import Cell
from estimator.transforms import pose_distance
from fakes.ur_controller.load import cpu_burners
from tests.support.cell import mount_off, running_cell, settled_tcp, sim_config, standing_tcp, tcp
from tests.support.waiting import wait_until

RACES = 8
MAX_DELAY_S = 1.2  # past the frames gathered and into the first step's move
STILL_MM = 0.005  # the arm stands: two reads this close (a settle step is tenths of a mm)
SEED = 20261204


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cell]:
    tmp: Path = tmp_path_factory.mktemp("stop_race_ibvs")
    with cpu_burners(2, max_s=600.0), \
            running_cell(sim_config(tmp, sim=mount_off(tmp))) as c:
        wait_until(lambda: c.arm_state().ready, 30.0, "the simulated arm ready")
        yield c


def _settle_started(monkeypatch: pytest.MonkeyPatch) -> threading.Event:
    """Set when an IBVS settle begins (the streamed loop has stopped the arm)."""
    started = threading.Event()
    real = image_law.settle_on_views

    def watched(*args: Any, **kwargs: Any) -> Any:
        started.set()
        return real(*args, **kwargs)

    monkeypatch.setattr(image_law, "settle_on_views", watched)
    return started


def test_stop_during_the_ibvs_settle_cancels_it_and_nothing_moves_after(
        cell: Cell, monkeypatch: pytest.MonkeyPatch) -> None:
    taught = cell.teach("race", "view", samples=5)
    started = _settle_started(monkeypatch)
    rng = random.Random(SEED)
    delays = [float(d) for d in np.linspace(0.0, MAX_DELAY_S, RACES)]
    rng.shuffle(delays)
    landed = 0
    for k, delay in enumerate(delays):
        where = f"race {k} at {delay * 1000:.0f} ms after the settle began"
        cell.jog_step("race", frame="base", translation_mm=[25.0, -15.0, 10.0],
                      rotation_deg=[0.0, 0.0, 6.0], speed_mm_s=100.0)
        settled_tcp(cell)
        started.clear()
        job = cell.approach("race", T_target_tcp=taught.T_target_tcp, mode="ibvs",
                            view=taught.view, wait=False)
        if not started.wait(60.0):
            ended = cell.job(job.id)
            pytest.fail(f"{where}: the approach never settled ({ended.state}: "
                        f"{ended.error_message})")
        time.sleep(delay)
        answer = cell.stop("race", reason=where)
        T_at_answer = tcp(cell)
        ended = wait_until(lambda j=job.id: None if cell.job(j).state == "running"
                           else cell.job(j), 30.0, f"job {job.id} to end")
        assert answer["stopped"] is True, (where, answer)
        if answer["cancelled"] is None:  # the settle had ended before the stop: no race
            assert ended.state == "succeeded", (where, ended.state, ended.error_message)
            continue
        landed += 1
        assert ended.state == "cancelled", (where, ended.state, ended.error_message)
        T_still = standing_tcp(cell, STILL_MM)
        assert pose_distance(T_at_answer, T_still)[0] < 1.0, \
            f"{where}: the arm went on after STOP answered"
        time.sleep(0.3)
        assert pose_distance(T_still, tcp(cell))[0] < STILL_MM, \
            f"{where}: the arm moved again after it had stopped"
    assert landed >= RACES // 2, f"only {landed} of {RACES} stops landed in a settle"
