"""The result models: the pose object as every output writes it, keys absent stay absent, each
kind read back by its kind and each approach and track by its mode."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from cell.results import (
    HomeResult,
    IbvsTrack,
    LookAndMoveApproach,
    Pose,
    ServoApproach,
    ServoTrack,
    result_from_json,
    result_json,
    result_of,
)
from estimator.transforms import T_from_pose, pose_dict

POSE = {"position_mm": [-480.0, -130.0, 350.0], "rotvec_rad": [3.1, 0.1, 0.0]}
BASIS = {"frame": "camera", "text": "the TCP against the goal the camera sees"}
CONSISTENCY: dict[str, Any] = {
    "verdict": "unchecked", "codes": [], "findings": [],
    "reprojection": {"rms_px": [0.1], "max_rms_px": 0.1, "limit_px": 1.0},
    "frame_spread": {"max_mm": 0.0, "max_deg": 0.0, "limit_mm": 0.5, "limit_deg": 0.2},
    "motion": {"target_at_rest": False, "checks": [], "judged": 0, "max_target_moved_mm": None,
               "max_target_moved_deg": None, "limit_mm": 0.5, "limit_deg": 0.15,
               "min_arm_motion_mm": 5.0, "min_arm_motion_deg": 2.0}}
SERVO_LOOP: dict[str, Any] = {
    "frames": 40, "failed_frames": 0, "stale_frames": 0, "gated_frames": 0,
    "T_base_target": POSE, "goal_T_base_tcp": POSE, "reached_T_base_tcp": POSE,
    "estimated_error_mm": 0.02, "estimated_error_deg": 0.01, "reach_error_mm": 0.01,
    "reach_error_deg": 0.002, "error_history": [{"t_s": 0.0, "error_mm": 5.0, "error_deg": 1.0}],
    "pose_interval_ms": None, "pose_latency_ms": {"median": 30.0, "p95": 40.0, "max": 45.0},
    "target_velocity_mm_s": [0.0, 0.1, 0.0]}
SERVO_APPROACH: dict[str, Any] = SERVO_LOOP | {
    "mode": "servo", "converged": True, "time_to_converge_s": 1.2, "first_locate_s": None,
    "estimated_error_basis": BASIS, "consistency": CONSISTENCY}


def test_pose_reads_and_writes_the_pose_object_of_every_output() -> None:
    T = T_from_pose([10.0, -20.0, 300.0], [0.1, -0.2, 3.0])
    pose = Pose.from_T(T)
    assert pose.json_dict() == pose_dict(T)
    assert np.allclose(pose.T(), T)
    assert Pose.model_validate(pose_dict(T)) == pose


def test_keys_absent_stay_absent_and_null_stays_null() -> None:
    result = result_of("approach", SERVO_APPROACH)
    assert isinstance(result, ServoApproach)
    out = result.json_dict()
    assert out == SERVO_APPROACH  # the fixed camera's and the closing keys stay absent
    assert out["first_locate_s"] is None and out["pose_interval_ms"] is None
    fixed = SERVO_APPROACH | {"camera_mount": "fixed", "pose_source": "live", "pose_age_s": None}
    assert result_of("approach", fixed).json_dict() == fixed


def test_each_kind_reads_back_its_own_model_through_the_stored_json() -> None:
    track = SERVO_LOOP | {"mode": "track", "duration_s": 2.0, "rms_error_mm": None}
    home = {"joints_deg": [0.0, -90.0, 90.0, -90.0, -90.0, 0.0], "T_base_tcp": POSE}
    for kind, data, model in (("approach", SERVO_APPROACH, ServoApproach),
                              ("track", track, ServoTrack), ("home", home, HomeResult)):
        result = result_of(kind, data)
        assert isinstance(result, model)
        again = result_from_json(kind, result_json(result))
        assert again == result and again.json_dict() == data


def test_nan_survives_the_store() -> None:
    ibvs: dict[str, Any] = {
        "mode": "ibvs_track", "frames": 3, "failed_frames": 0, "stale_frames": 0,
        "frames_with_too_few_dots": 0, "frames_missing_dots": 0, "min_dots_used": 6,
        "dots_taught": 6, "min_dot_border_px": None, "interaction": "mean",
        "image_error_px_rms": 0.1, "image_error_px_max": 0.2, "estimated_error_mm": 0.1,
        "estimated_error_deg": 0.01, "reached_T_base_tcp": POSE, "pose_latency_ms": None,
        "error_history": [], "view_error_mm": math.nan, "view_error_deg": math.nan,
        "phases_s": {"first_view": 0.01, "stopped": 2.0}, "gain_cap_per_s": None,
        "duration_s": 2.0}
    result = result_from_json("track", result_json(result_of("track", ibvs)))
    assert isinstance(result, IbvsTrack) and math.isnan(result.view_error_mm)
    assert result.json_dict()["phases_s"] == {"first_view": 0.01, "stopped": 2.0}


def test_a_result_is_closed_and_its_mode_says_which() -> None:
    with pytest.raises(ValidationError):
        result_of("approach", SERVO_APPROACH | {"no_such_key": 1})
    with pytest.raises(ValidationError):  # a servo's fields are no look-and-move result
        result_of("approach", SERVO_APPROACH | {"mode": "look_and_move"})
    with pytest.raises(ValidationError):
        LookAndMoveApproach.model_validate({"mode": "look_and_move"})
    with pytest.raises(ValueError, match="no result model"):
        result_of("jog", {})
