"""Load the robot descriptions that ship inside the package, in ``torchcontact/models/``."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from torchcontact.robots._robot import Robot

ROBOT_NAMES = ("wam7", "bhand", "wam7_bhand", "parallel_jaw")
"""Names accepted by :func:`load`, one per ``torchcontact/models/<name>.urdf``."""


def models_dir() -> Path:
    """The directory of the robot descriptions installed with torchcontact.

    The URDFs are package data (``torchcontact/models/``), located through
    :mod:`importlib.resources`, so they are found wherever the package is installed.

    Returns:
        Its absolute path.

    Raises:
        FileNotFoundError: The directory is missing, or the package is not installed as files
            on disk (imported from a zip archive).
    """
    path = resources.files("torchcontact").joinpath("models")
    if not isinstance(path, Path) or not path.is_dir():
        raise FileNotFoundError(
            f"torchcontact robot descriptions not found: {path} is not a directory. They ship "
            "inside the package (torchcontact/models/); reinstall torchcontact with pip."
        )
    return path.resolve()


def load(name: str, *, coupled: bool = True) -> Robot:
    """Load one of torchcontact's robots.

    * ``"wam7"``: Barrett WAM, 7 revolute joints; base frame where the J1 and J2 axes meet, tool
      frame ``"wam_tool"`` (the DH frame 7, at (0, 0, 0.91) m at q = 0).
    * ``"bhand"``: BarrettHand BH8-280 in its wrist frame W (``"bhand_palm"``). Coupled: 4
      coordinates (``bhand_f1_spread`` driving F1 and F2 symmetrically, and the three inner joints,
      each driving its outer joint at 1/3); uncoupled: all 8 joints.
    * ``"wam7_bhand"``: the WAM with the hand's frame W on the tool frame (11 coordinates coupled).
    * ``"parallel_jaw"``: a two-finger parallel-jaw gripper for planar grasp scenes; coupled: one
      coordinate (each finger's distance from the centreline), uncoupled: both fingers independent.

    Sources and dimensions are documented in each ``torchcontact/models/<name>.urdf``.

    Args:
        name: One of :data:`ROBOT_NAMES`.
        coupled: Apply the mechanical couplings (URDF ``<mimic>`` tags) so that ``q`` holds the
            actuated coordinates (True), or make every joint an independent coordinate (False).

    Returns:
        A new :class:`Robot`.

    Raises:
        ValueError: ``name`` is not a known robot or ``coupled`` is not a bool.
        FileNotFoundError: The package's ``models/`` directory or the robot's file is missing.
    """
    if not isinstance(name, str) or name not in ROBOT_NAMES:
        raise ValueError(f"name must be one of {list(ROBOT_NAMES)}, got {name!r}")
    if not isinstance(coupled, bool):
        raise ValueError(f"coupled must be a bool, got {coupled!r}")
    path = models_dir() / f"{name}.urdf"
    if not path.is_file():
        raise FileNotFoundError(f"robot description {path} is missing")
    return Robot.from_urdf(path, coupled=coupled)
