"""Servo and IBVS to a view taught by showing, with the camera's true mount off the hand-eye
calibration (the simulator's truth, which the cell does not share): each ends ``succeeded``
near the true TCP at teaching, and the error it claims bounds the true one."""

from __future__ import annotations

from pathlib import Path

import pytest

from estimator.transforms import pose_distance
from tests.support.cell import mount_off, running_cell, settled_tcp, sim_config


@pytest.mark.parametrize("mode", ["servo", "ibvs"])
def test_an_approach_to_a_taught_view_ends_near_it_and_its_claim_holds(
        tmp_path: Path, mode: str) -> None:
    with running_cell(sim_config(tmp_path, sim=mount_off(tmp_path))) as cell:
        taught = cell.teach("test", "view", samples=5)
        T_taught = settled_tcp(cell)
        cell.jog_step("test", frame="base", translation_mm=[25.0, -15.0, 10.0],
                      rotation_deg=[0.0, 0.0, 6.0], speed_mm_s=100.0)
        settled_tcp(cell)
        kw: dict[str, object] = {"view": taught.view} if mode == "ibvs" \
            else {"standoff_mm": 0.0}
        job = cell.approach("test", T_target_tcp=taught.T_target_tcp, mode=mode, wait=True,
                            wait_timeout_s=60.0, **kw)
        assert job.state == "succeeded", job.error_message
        d_mm, d_deg = pose_distance(settled_tcp(cell), T_taught)
        assert d_mm < 0.5 and d_deg < 0.1, (d_mm, d_deg)
        result = job.result
        assert result is not None
        assert d_mm <= result.estimated_error_mm and d_deg <= result.estimated_error_deg
        if mode == "servo":  # the goal it converged on, not one the stopping frames restarted
            assert getattr(result, "goal_frames_averaged", 0) >= cell.config.servo.rest_frames
        else:  # the view taught from every frame of every sample
            assert taught.view is not None
            assert taught.view.frames == 5 * cell.config.teach.frames_per_sample
