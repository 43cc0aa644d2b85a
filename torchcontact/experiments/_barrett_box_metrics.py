"""Metrics of the BarrettHand box grasp: pose errors, contact-state scores, tip-over
detection and time per step, one function for every method."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from torchcontact.geometry import quat_conj, quat_log, quat_mul

#: Largest |detected − true| tip-over step (steps) of a detection on time.
TIP_TOLERANCE = 3


def geodesic_angle(a: Tensor, b: Tensor) -> Tensor:
    """``(*B,)`` angle (rad) of the rotation between unit quaternions ``(*B, 4)``:
    ``|Log(a⁻¹ ⊗ b)|``, in ``[0, π]``."""
    angle: Tensor = torch.linalg.vector_norm(quat_log(quat_mul(quat_conj(a), b)), dim=-1)
    return angle


def box_tracking_metrics(
    *,
    true_pose: Tensor,
    pose: Tensor,
    occluded: Tensor,
    true_tip: Tensor,
    tip: Tensor,
    true_states: Tensor | None = None,
    state_probs: Tensor | None = None,
    pair_names: Sequence[str] | None = None,
    wall: float | None = None,
    cpu: float | None = None,
) -> dict[str, float]:
    """Scores of one method over ``B`` trials of ``T`` steps.

    * ``pos_rmse_mm``, ``pos_rmse_occ_mm``: root mean square of the position error (mm)
      over all steps and trials, and over the occluded steps;
    * ``rot_rmse_deg``, ``rot_rmse_occ_deg``: the same of the geodesic angle
      (:func:`geodesic_angle`, degrees);
    * with the contact states: ``state_accuracy``, the share of (step, trial, pair) whose
      most probable state is the true one, and ``state_logprob``, the mean over (step,
      trial) of ``Σ_pairs log p(true state)`` (probabilities clamped at 1e-12); with
      ``pair_names``, ``state_accuracy_<name>`` of each pair;
    * tip-over, over the trials that tip (``true_tip >= 0``): ``tip_within``, the share
      detected within :data:`TIP_TOLERANCE` steps of the truth, and ``tip_step_error``, the
      mean ``|tip − true_tip|`` of those detected at all (NaN when none is);
      ``tip_false_alarms``, the share of the other trials with a detection; ``tip_trials``,
      the number of trials that tip;
    * with the times: ``ms_per_step`` and ``cpu_ms_per_step`` (seconds over ``T`` steps).

    Args:
        true_pose: ``(T, B, 7)`` true poses (position, unit quaternion).
        pose: ``(T, B, 7)`` estimated poses.
        occluded: ``(T,)`` bool, the occluded steps (at least one).
        true_tip: ``(B,)`` long true tip-over step, ``-1`` for none.
        tip: ``(B,)`` long detected tip-over step, ``-1`` for none.
        true_states: ``(T, B, P)`` long true contact state per pair (values in ``[0, C)``).
        state_probs: ``(T, B, P, C)`` the method's probability of each state.
        pair_names: ``P`` names of the pairs, for the per-pair accuracies.
        wall: wall-clock seconds of the method's run.
        cpu: CPU seconds of the method's run.

    Raises:
        ValueError: shapes that do not match, or no occluded step.
    """
    T, B = true_pose.shape[:2]
    if pose.shape != true_pose.shape or true_pose.shape[-1] != 7:
        raise ValueError(
            f"pose: expected shape {tuple(true_pose.shape)} (T, B, 7), got {tuple(pose.shape)}"
        )
    if occluded.shape != (T,) or occluded.dtype != torch.bool or not bool(occluded.any()):
        raise ValueError(f"occluded: expected a ({T},) bool mask with an occluded step")
    if true_tip.shape != (B,) or tip.shape != (B,):
        raise ValueError(f"true_tip, tip: expected shape ({B},)")
    position = (pose[..., :3] - true_pose[..., :3]).pow(2).sum(-1)
    angle = geodesic_angle(true_pose[..., 3:], pose[..., 3:]).pow(2)
    row = {
        "pos_rmse_mm": 1e3 * float(position.mean().sqrt()),
        "pos_rmse_occ_mm": 1e3 * float(position[occluded].mean().sqrt()),
        "rot_rmse_deg": math.degrees(float(angle.mean().sqrt())),
        "rot_rmse_occ_deg": math.degrees(float(angle[occluded].mean().sqrt())),
    }
    if (true_states is None) != (state_probs is None):
        raise ValueError("true_states and state_probs: give both or neither")
    if true_states is not None and state_probs is not None:
        if state_probs.shape[:-1] != true_states.shape or true_states.shape[:2] != (T, B):
            raise ValueError(
                f"state_probs: expected shape {(*true_states.shape, -1)} of true_states (T, B, P), "
                f"got {tuple(state_probs.shape)}"
            )
        # The index of a state is exact: equal longs mean the same state.
        right = (state_probs.argmax(-1) == true_states).double()
        row["state_accuracy"] = float(right.mean())
        if pair_names is not None:
            if len(pair_names) != true_states.shape[-1]:
                raise ValueError(
                    f"pair_names: expected {true_states.shape[-1]} names, got {len(pair_names)}"
                )
            for name, share in zip(pair_names, right.mean((0, 1)).tolist(), strict=True):
                row[f"state_accuracy_{name}"] = share
        p_true = state_probs.gather(-1, true_states[..., None]).squeeze(-1)
        row["state_logprob"] = float(p_true.clamp_min(1e-12).log().sum(-1).mean())
    tips = true_tip >= 0
    row["tip_trials"] = float(tips.sum())
    if bool(tips.any()):
        detected = tips & (tip >= 0)
        error = (tip - true_tip).abs()
        row["tip_within"] = float((detected & (error <= TIP_TOLERANCE))[tips].double().mean())
        row["tip_step_error"] = (
            float(error[detected].double().mean()) if bool(detected.any()) else math.nan
        )
    if bool((~tips).any()):
        row["tip_false_alarms"] = float((tip[~tips] >= 0).double().mean())
    if wall is not None:
        row["ms_per_step"] = 1e3 * wall / T
    if cpu is not None:
        row["cpu_ms_per_step"] = 1e3 * cpu / T
    return row


#: Columns of :func:`box_tracking_table`: key, title, format.
BOX_TABLE_COLUMNS = (
    ("particles", "particles", "{:.0f}"),
    ("pos_rmse_mm", "pos RMSE (mm)", "{:.2f}"),
    ("pos_rmse_occ_mm", "pos RMSE occl. (mm)", "{:.2f}"),
    ("rot_rmse_deg", "rot RMSE (deg)", "{:.2f}"),
    ("rot_rmse_occ_deg", "rot RMSE occl. (deg)", "{:.2f}"),
    ("state_accuracy", "contact-state acc.", "{:.3f}"),
    ("state_logprob", "log p(true states)", "{:.2f}"),
    ("tip_within", f"tip within {TIP_TOLERANCE} steps", "{:.2f}"),
    ("tip_step_error", "tip step error", "{:.1f}"),
    ("tip_false_alarms", "tip false alarms", "{:.2f}"),
    ("ms_per_step", "wall ms / step", "{:.1f}"),
    ("cpu_ms_per_step", "CPU ms / step", "{:.1f}"),
)


def box_tracking_table(metrics: dict[str, dict[str, float]]) -> str:
    """The metrics as a Markdown table, one row per method (columns no row has are left out;
    a missing cell reads ``–``)."""
    columns = [c for c in BOX_TABLE_COLUMNS if any(c[0] in row for row in metrics.values())]
    lines = [
        "| method | " + " | ".join(title for _, title, _ in columns) + " |",
        "|---" + "|--:" * len(columns) + "|",
    ]
    for method, row in metrics.items():
        cells = [fmt.format(row[key]) if key in row else "–" for key, _, fmt in columns]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
