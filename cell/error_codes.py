"""Every ``error.code`` the cell can answer, as one enum: :mod:`cell.errors` carries one, and
the API shows the enum in its OpenAPI schema, so a PLC programmer can switch on codes without
reading the source. ``tests/api/http/test_api_contract.py`` checks that every code raised in
the project is listed here."""

from __future__ import annotations

from enum import StrEnum


class ErrorCode(StrEnum):
    # authentication and the request itself
    unauthorized = "unauthorized"
    forbidden = "forbidden"
    invalid_request = "invalid_request"
    body_too_large = "body_too_large"
    unsupported_media_type = "unsupported_media_type"
    not_found = "not_found"
    method_not_allowed = "method_not_allowed"
    http_error = "http_error"
    internal_error = "internal_error"
    # state of the cell (409)
    busy = "busy"
    cancelled = "cancelled"
    interrupted = "interrupted"
    protective_stop = "protective_stop"
    emergency_stop = "emergency_stop"
    arm_not_ready = "arm_not_ready"
    arm_moving = "arm_moving"
    not_ready = "not_ready"
    not_jogging = "not_jogging"
    stale_pose = "stale_pose"
    motion_failed = "motion_failed"
    motion_timeout = "motion_timeout"
    # the controller's RTDE watchdog ended the control script: the host did not write in time
    controller_watchdog = "controller_watchdog"
    unlock_too_early = "unlock_too_early"
    no_motion_slot = "no_motion_slot"  # an internal refusal: a motion without the slot
    not_supported = "not_supported"  # a mode this cell cannot run (its camera mount)
    # servoing and tracking
    target_lost = "target_lost"
    pose_jump = "pose_jump"
    no_new_frame = "no_new_frame"
    servo_timeout = "servo_timeout"
    duration_limit = "duration_limit"
    tracking_lag = "tracking_lag"  # a track fell behind its target: the cell cannot keep up
    target_not_visible = "target_not_visible"
    # the calibration check
    calibration_drift = "calibration_drift"
    no_reference = "no_reference"
    # picking
    grasp_missed = "grasp_missed"
    grip_out_of_window = "grip_out_of_window"
    gripper_fault = "gripper_fault"
    no_tool_plate = "no_tool_plate"  # a fixed camera's IBVS: no dot plate on the tool in view
    spread_too_large = "spread_too_large"
    calibration_inconsistent = "calibration_inconsistent"
    reprojection_too_large = "reprojection_too_large"  # a result's consistency finding
    job_not_succeeded = "job_not_succeeded"
    taught_exists = "taught_exists"
    already_acknowledged = "already_acknowledged"
    # the estimator's refusals (409: the target is not located in this frame)
    estimation_failed = "estimation_failed"
    estimator_failed = "estimator_failed"
    too_few_blobs = "too_few_blobs"
    degenerate_geometry = "degenerate_geometry"
    not_converged = "not_converged"
    target_behind_camera = "target_behind_camera"
    no_correspondence = "no_correspondence"
    hand_eye_degenerate = "hand_eye_degenerate"
    intrinsics_failed = "intrinsics_failed"
    too_few_views = "too_few_views"
    # configured limits and bad values (422)
    outside_envelope = "outside_envelope"
    tilt_limit = "tilt_limit"
    move_too_far = "move_too_far"
    unreachable = "unreachable"  # no joint solution, a joint limit or a singularity on the way
    speed_limit = "speed_limit"
    accel_limit = "accel_limit"
    jog_speed_limit = "jog_speed_limit"
    jog_step_limit = "jog_step_limit"
    invalid_pose = "invalid_pose"
    invalid_standoff = "invalid_standoff"
    invalid_name = "invalid_name"
    invalid_camera_setting = "invalid_camera_setting"
    invalid_sim_fault = "invalid_sim_fault"  # a fault the simulated world cannot take
    ibvs_needs_taught = "ibvs_needs_taught"
    taught_without_view = "taught_without_view"
    taught_wrong_frame = "taught_wrong_frame"
    # not found (404)
    job_not_found = "job_not_found"
    taught_not_found = "taught_not_found"
    recipe_not_found = "recipe_not_found"
    recipe_target_not_found = "recipe_target_not_found"
    alarm_not_found = "alarm_not_found"
    image_not_found = "image_not_found"
    method_not_found = "method_not_found"
    not_simulated = "not_simulated"
    dataset_not_found = "dataset_not_found"
    # devices and files (503 and others)
    camera_lost = "camera_lost"
    camera_stalled = "camera_stalled"
    camera_stale = "camera_stale"
    camera_missing = "camera_missing"
    camera_unreadable = "camera_unreadable"
    arm_disconnected = "arm_disconnected"
    connection_lost = "connection_lost"
    device_timeout = "device_timeout"
    protocol_error = "protocol_error"
    driver_error = "driver_error"
    gripper_unavailable = "gripper_unavailable"
    image_log_disabled = "image_log_disabled"
    board_missing = "board_missing"
    board_unreadable = "board_unreadable"
    image_missing = "image_missing"
    image_unreadable = "image_unreadable"
    image_unwritable = "image_unwritable"
    pose_unreadable = "pose_unreadable"
    dataset_exists = "dataset_exists"
    dataset_invalid = "dataset_invalid"
    dataset_unwritable = "dataset_unwritable"
    taught_store_unreadable = "taught_store_unreadable"
    taught_store_write_failed = "taught_store_write_failed"
    recipe_store_unreadable = "recipe_store_unreadable"
    recipe_store_write_failed = "recipe_store_write_failed"
    recipe_number_taken = "recipe_number_taken"
    recipe_prepared = "recipe_prepared"
    invalid_recipe = "invalid_recipe"
    config_invalid = "config_invalid"
    config_write_failed = "config_write_failed"
    no_config_file = "no_config_file"
    storage_failed = "storage_failed"
