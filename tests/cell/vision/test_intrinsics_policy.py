"""The cell computes with its configured intrinsics unless told to trust the device's."""

from __future__ import annotations

import logging

import pytest

from cell.vision.intrinsics import IntrinsicsPolicy
from estimator import CameraModel

CONFIGURED = CameraModel(806.4, 805.6, 643.0, 397.0, (-0.045, 0.012, 0.0, 0.0, 0.0), 1280, 800)
FACTORY = CameraModel(800.0, 800.0, 639.5, 399.5, (), 1280, 800)


def test_configured_intrinsics_win_and_the_difference_is_logged_once(
        caplog: pytest.LogCaptureFixture) -> None:
    policy = IntrinsicsPolicy(CONFIGURED)
    with caplog.at_level(logging.WARNING):
        assert policy.model_for(FACTORY) == CONFIGURED
        assert policy.model_for(FACTORY) == CONFIGURED
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1
    assert "focal 0.79 %" in warnings[0] and "3.5 px" in warnings[0]
    assert "intrinsics = \"device\"" in warnings[0]


def test_device_source_trusts_the_device() -> None:
    assert IntrinsicsPolicy(CONFIGURED, "device").model_for(FACTORY) == FACTORY


def test_a_frame_of_another_size_keeps_its_own_intrinsics(
        caplog: pytest.LogCaptureFixture) -> None:
    half = CameraModel(400.0, 400.0, 319.5, 199.5, (), 640, 400)
    with caplog.at_level(logging.WARNING):
        assert IntrinsicsPolicy(CONFIGURED).model_for(half) == half
    assert "640x400" in caplog.text and "1280x800" in caplog.text


def test_same_intrinsics_pass_silently(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        assert IntrinsicsPolicy(CONFIGURED).model_for(CONFIGURED) == CONFIGURED
    assert not caplog.records
