"""Pieces of the triangle-grasp pipeline: the schedule, the settings' checks, the table."""

from __future__ import annotations

import pytest
import torch

from torchcontact.experiments import TriangleGrasp, grasp_schedule, tracking_table


@pytest.mark.parametrize("steps", [8, 9, 13, 48, 80])
def test_every_phase_of_the_schedule_has_a_step(steps: int) -> None:
    close, opening, occluded = grasp_schedule(steps)
    phases = {
        "approach": range(close.start),
        "closing": range(close.start, close.stop),
        "hold": range(close.stop, opening.start),
        "opening": range(opening.start, opening.stop),
    }
    for name, phase in phases.items():
        assert len(phase) >= 1, name
    assert opening.stop == steps
    assert occluded.dtype == torch.bool
    assert occluded.shape == (steps,)
    seen = occluded.nonzero().squeeze(-1).tolist()
    assert seen == list(range(seen[0], seen[-1] + 1))  # one contiguous occlusion
    assert 0 < seen[0] <= seen[-1] < steps - 1


def test_settings_name_the_bad_one() -> None:
    TriangleGrasp().check()
    with pytest.raises(ValueError, match=r"^steps: expected an int >= 8"):
        TriangleGrasp(steps=7).check()
    with pytest.raises(ValueError, match=r"^friction_high: expected a finite number >= 0.4"):
        TriangleGrasp(friction_high=0.3).check()
    torch.testing.assert_close(
        TriangleGrasp(vision_sigma=0.002, vision_sigma_theta=0.01).vision_std(),
        torch.tensor([0.002, 0.002, 0.01], dtype=torch.float64),
    )


def test_table_leaves_out_missing_columns_and_dashes_missing_cells() -> None:
    metrics = {
        "rbpf": {"particles": 20.0, "pos_rmse_mm": 0.12345, "mode_accuracy": 0.9},
        "ekf": {"particles": 0.0, "pos_rmse_mm": 2.0},
    }
    assert tracking_table(metrics).splitlines() == [
        "| method | particles | pos RMSE (mm) | mode acc. |",
        "|---|--:|--:|--:|",
        "| rbpf | 20 | 0.123 | 0.900 |",
        "| ekf | – | 2.000 | – |",
    ]
