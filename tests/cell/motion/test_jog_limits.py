"""A jog step larger than the configured step limits is refused before anything moves."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cell.errors import LimitError
from tests.support.cell import running_cell, sim_config


def test_oversized_jog_step_is_refused_and_moves_nothing(tmp_path: Path) -> None:
    with running_cell(sim_config(tmp_path)) as cell:
        before = cell.arm_state().T_base_tcp.copy()
        limits = cell.config.limits
        for translation, rotation in (([0.0, 0.0, limits.max_jog_step_mm + 1.0], [0, 0, 0]),
                                      ([0.0, 0.0, 5.0], [0.0, limits.max_jog_step_deg + 1.0, 0])):
            with pytest.raises(LimitError) as err:
                cell.jog_step("test", frame="tool", translation_mm=translation,
                              rotation_deg=rotation)
            assert err.value.code == "jog_step_limit"
        assert np.allclose(cell.arm_state().T_base_tcp, before)
