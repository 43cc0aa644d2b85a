"""Robot kinematics through pytorch-kinematics: the Barrett WAM, the BarrettHand, a parallel-jaw
gripper, and the Jacobians that map robot motion to contact-point motion.

Entry point: :func:`load` (``torchcontact.robots.load("wam7")``).
"""

from torchcontact.robots._coupling import JointCoupling
from torchcontact.robots._links import LinkInertial, LinkShape
from torchcontact.robots._load import ROBOT_NAMES, load, models_dir
from torchcontact.robots._robot import Robot

__all__ = [
    "ROBOT_NAMES",
    "JointCoupling",
    "LinkInertial",
    "LinkShape",
    "Robot",
    "load",
    "models_dir",
]
