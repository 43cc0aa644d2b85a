"""The URDF reader: agreement with pytorch-kinematics' own parser, and malformed files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import pytorch_kinematics as pk
import torch

from torchcontact.robots import ROBOT_NAMES, Robot, load, models_dir


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_agrees_with_pytorch_kinematics_own_parser(name: str) -> None:
    # pytorch-kinematics reads the same file independently (in float32): all frames agree to float32
    # precision at random configurations of every joint.
    rng = np.random.default_rng(31)
    robot = load(name, coupled=False)
    reference = pk.build_chain_from_urdf((models_dir() / f"{name}.urdf").read_text())
    assert tuple(reference.get_joint_parameter_names()) == robot.joint_names
    q = rng.uniform(robot.lower.numpy(), robot.upper.numpy(), size=(64, robot.dof))
    ours = robot.forward_kinematics(torch.from_numpy(q))
    theirs = reference.forward_kinematics(torch.from_numpy(q).float())
    assert set(ours) == set(theirs)
    for link, pose in ours.items():
        np.testing.assert_allclose(
            pose.numpy(), theirs[link].get_matrix().double().numpy(), atol=5e-6
        )


def test_models_directory_holds_every_robot() -> None:
    for name in ROBOT_NAMES:
        assert (models_dir() / f"{name}.urdf").is_file()


def _write(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "robot.urdf"
    path.write_text(f'<?xml version="1.0"?>\n<robot name="test">{body}</robot>\n')
    return path


JOINT = (
    '<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
    '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="0" velocity="0"/>{extra}</joint>'
)


def joint(name: str, parent: str, child: str, kind: str = "revolute", extra: str = "") -> str:
    return JOINT.format(name=name, kind=kind, parent=parent, child=child, extra=extra)


def test_custom_urdf_with_continuous_and_mimic(tmp_path: Path) -> None:
    body = (
        '<link name="a"/><link name="b"/><link name="c"/>'
        + joint("j1", "a", "b", kind="continuous")
        + joint("j2", "b", "c", extra='<mimic joint="j1" multiplier="2" offset="0.5"/>')
    )
    robot = Robot.from_urdf(_write(tmp_path, body))
    assert robot.joint_names == ("j1",)
    assert robot.lower.item() == -float("inf")
    torch.testing.assert_close(
        robot.coupling.to_full(torch.tensor([0.25], dtype=torch.float64)),
        torch.tensor([0.25, 1.0], dtype=torch.float64),
    )


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ('<link name="a"/><link name="b"/>', "expected one root link"),
        (
            '<link name="a"/><link name="b"/>' + joint("j", "a", "b", kind="planar"),
            "unsupported joint type",
        ),
        ('<link name="a"/><link name="b"/>' + joint("j", "a", "x"), "connects unknown links"),
        ('<link name="a"/><link name="a"/>', "link names must be present and unique"),
        (
            '<link name="a"/><link name="b"/><link name="c"/>'
            + joint("j", "a", "b")
            + joint("j", "b", "c"),
            "joint names must be unique",
        ),
        (
            '<link name="a"/><link name="b"/><link name="c"/>'
            + joint("j1", "a", "c")
            + joint("j2", "b", "c"),
            "more than one parent",
        ),
        (
            '<link name="a"/><link name="b"/><link name="c"/><link name="d"/>'
            + joint("j1", "a", "b")
            + joint("j2", "b", "c", extra='<mimic joint="j1"/>')
            + joint("j3", "c", "d", extra='<mimic joint="j2"/>'),
            "not an independent joint",
        ),
        (
            '<link name="a"/><link name="b"/><joint name="j" type="revolute"><parent link="a"/>'
            '<child link="b"/><origin xyz="0 0"/>'
            '<limit lower="0" upper="1" effort="0" velocity="0"/></joint>',
            "expected 3 finite numbers",
        ),
        (
            '<link name="a"/><link name="b"/><joint name="j" type="revolute"><parent link="a"/>'
            '<child link="b"/></joint>',
            "needs a <limit>",
        ),
    ],
)
def test_malformed_urdf(tmp_path: Path, body: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Robot.from_urdf(_write(tmp_path, body))


def test_not_xml(tmp_path: Path) -> None:
    path = tmp_path / "broken.urdf"
    path.write_text("<robot><link name='a'></robot>")
    with pytest.raises(ValueError, match="not valid XML"):
        Robot.from_urdf(path)
