"""Bad inputs raise errors that name the argument at fault."""

from __future__ import annotations

import pytest
import torch

from torchcontact.robots import Robot, load


@pytest.fixture(scope="module")
def wam() -> Robot:
    return load("wam7")


def _q(*shape: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    return torch.zeros(shape, dtype=dtype)


def test_unknown_robot_name() -> None:
    with pytest.raises(ValueError, match="name must be one of"):
        load("ur5")


@pytest.mark.parametrize("shape", [(6,), (4, 8), (7, 1), ()])
def test_wrong_joint_count(wam: Robot, shape: tuple[int, ...]) -> None:
    # pytorch-kinematics would broadcast a short joint vector silently; we refuse it.
    with pytest.raises(ValueError, match=r"q must have shape \(\*B, 7\)"):
        wam.forward_kinematics(_q(*shape), "wam_tool")
    with pytest.raises(ValueError, match=r"q must have shape"):
        wam.jacobian(_q(*shape), "wam_tool")


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_q(wam: Robot, bad: float) -> None:
    q = _q(3, 7)
    q[1, 4] = bad
    with pytest.raises(ValueError, match="q contains NaN or inf"):
        wam.forward_kinematics(q)


def test_q_type_and_dtype(wam: Robot) -> None:
    with pytest.raises(ValueError, match=r"q must be a torch\.Tensor"):
        wam.forward_kinematics([0.0] * 7)
    with pytest.raises(ValueError, match="q must be float32 or float64"):
        wam.forward_kinematics(torch.zeros(7, dtype=torch.int64))


def test_unknown_link(wam: Robot) -> None:
    with pytest.raises(ValueError, match="link must be one of"):
        wam.forward_kinematics(_q(7), "wam_link8")
    with pytest.raises(ValueError, match="link must be one of"):
        wam.jacobian(_q(7), "bhand_palm")


def test_point_checks(wam: Robot) -> None:
    with pytest.raises(ValueError, match=r"point must have shape \(\*B, 3\)"):
        wam.jacobian(_q(7), "wam_tool", point=_q(2))
    with pytest.raises(ValueError, match="point must have the dtype and device of q"):
        wam.jacobian(_q(7), "wam_tool", point=_q(3, dtype=torch.float32))
    with pytest.raises(ValueError, match="point contains NaN or inf"):
        wam.jacobian(
            _q(7), "wam_tool", point=torch.tensor([0.0, float("nan"), 0.0], dtype=torch.float64)
        )
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: q \(4,\), point \(5,\)"):
        wam.jacobian(_q(4, 7), "wam_tool", point=_q(5, 3))


def test_contact_frame_checks(wam: Robot) -> None:
    point = _q(3)
    normal = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    tangents = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]], dtype=torch.float64)
    ok = {"point": point, "normal": normal, "tangents": tangents}
    wam.contact_jacobian(_q(7), "wam_tool", **ok)
    with pytest.raises(ValueError, match="normal must hold unit vectors"):
        wam.contact_jacobian(_q(7), "wam_tool", **{**ok, "normal": 2 * normal})
    with pytest.raises(ValueError, match="tangents must hold unit vectors"):
        wam.contact_jacobian(_q(7), "wam_tool", **{**ok, "tangents": 0.5 * tangents})
    with pytest.raises(ValueError, match="tangents must be orthogonal to normal"):
        wam.contact_jacobian(_q(7), "wam_tool", **{**ok, "tangents": normal.expand(2, 3)})
    with pytest.raises(ValueError, match=r"tangents must have shape \(\*B, D, 3\)"):
        wam.contact_jacobian(_q(7), "wam_tool", **{**ok, "tangents": tangents[0]})
    with pytest.raises(ValueError, match="normal must have the dtype and device of q"):
        wam.contact_jacobian(_q(7), "wam_tool", **{**ok, "normal": normal.float()})
    with pytest.raises(ValueError, match=r"normal must have shape \(\*B, 3\)"):
        wam.contact_jacobian(_q(7), "wam_tool", **{**ok, "normal": _q(2)})
    with pytest.raises(ValueError, match="batch shapes do not broadcast"):
        wam.contact_jacobian(
            _q(7), "wam_tool", **{**ok, "normal": normal.expand(3, 3), "point": _q(2, 3)}
        )


def test_coupling_to_full_checks() -> None:
    hand = load("bhand")
    with pytest.raises(ValueError, match=r"q must have shape \(\*B, 4\)"):
        hand.coupling.to_full(_q(8))
