"""Read the subset of URDF our robot descriptions use, and build a float64 pytorch-kinematics chain.

pytorch-kinematics' own URDF reader converts every joint origin to float32 before composing it,
which leaves errors of order 1e-7 m / 1e-7 rad in each link transform. We read the XML ourselves,
keep the numbers as Python floats (float64), and hand pytorch-kinematics float64 frames; chains for
other dtypes are converted from that one, so a float32 chain is the float64 one rounded once.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import torch
from pytorch_kinematics.chain import Chain
from pytorch_kinematics.frame import Frame, Joint, Link
from pytorch_kinematics.transforms import Transform3d

_JOINT_KINDS = {"revolute": "revolute", "continuous": "revolute", "prismatic": "prismatic"}


@dataclass(frozen=True)
class UrdfMimic:
    """A ``<mimic>`` tag: this joint = ``multiplier`` * ``joint`` + ``offset``.

    Attributes:
        joint: Name of the joint that is mimicked.
        multiplier: Linear factor.
        offset: Constant term (rad or m).
    """

    joint: str
    multiplier: float
    offset: float


@dataclass(frozen=True)
class UrdfJoint:
    """One URDF joint.

    Attributes:
        name: Joint name.
        kind: ``"revolute"`` (also URDF ``continuous``), ``"prismatic"`` or ``"fixed"``.
        parent: Parent link name.
        child: Child link name.
        xyz: Origin translation in the parent link frame (m).
        rpy: Origin rotation, fixed-axis roll-pitch-yaw (rad): R = Rz(yaw) Ry(pitch) Rx(roll).
        axis: Joint axis in the child link frame (unit vector).
        lower: Lower limit (rad or m); ``-inf`` when unlimited.
        upper: Upper limit (rad or m); ``inf`` when unlimited.
        mimic: The ``<mimic>`` tag, if any.
    """

    name: str
    kind: str
    parent: str
    child: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]
    axis: tuple[float, float, float]
    lower: float
    upper: float
    mimic: UrdfMimic | None


@dataclass(frozen=True)
class UrdfInertial:
    """A link's ``<inertial>``: mass, centre of mass and inertia about it.

    Attributes:
        link: The link's name.
        mass: Mass in kg (``> 0``).
        xyz: Centre of mass in the link frame (m).
        rpy: Orientation of the inertia axes in the link frame (rad, as a joint origin's).
        inertia: ``(ixx, ixy, ixz, iyy, iyz, izz)`` about the centre of mass, inertia axes
            (kg m²).
    """

    link: str
    mass: float
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]
    inertia: tuple[float, float, float, float, float, float]


@dataclass(frozen=True)
class UrdfCollision:
    """One ``<collision>`` primitive of a link.

    URDF has no capsule element: a ``<cylinder radius="r" length="L"/>`` is read as the
    capsule of radius ``r`` around the segment of length ``L`` on the cylinder's axis (its z
    axis), i.e. the cylinder with hemispherical caps of radius ``r`` added at both ends; the
    ``<capsule radius length>`` element of some URDF dialects is read the same way.

    Attributes:
        link: The link's name.
        kind: ``"box"``, ``"sphere"`` or ``"capsule"``.
        size: box: the full side lengths ``(x, y, z)``; sphere: ``(radius,)``; capsule:
            ``(radius, length)`` (m).
        xyz: The primitive's centre in the link frame (m).
        rpy: The primitive's orientation in the link frame (rad, as a joint origin's).
    """

    link: str
    kind: str
    size: tuple[float, ...]
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]


@dataclass(frozen=True)
class UrdfModel:
    """A parsed URDF tree.

    Attributes:
        name: The robot's name attribute.
        root: Name of the root link (the base/world frame of the kinematics).
        links: All link names, in file order.
        joints: All joints, in file order.
        inertials: The links' ``<inertial>`` elements, in file order (links without one have
            none).
        collisions: Every link's ``<collision>`` primitives, in file order.
    """

    name: str
    root: str
    links: tuple[str, ...]
    joints: tuple[UrdfJoint, ...]
    inertials: tuple[UrdfInertial, ...] = ()
    collisions: tuple[UrdfCollision, ...] = ()


def _floats(
    text: str | None, default: tuple[float, float, float], *, where: str
) -> tuple[float, ...]:
    if text is None:
        return default
    try:
        values = tuple(float(token) for token in text.split())
    except ValueError as error:
        raise ValueError(f"{where}: cannot read numbers from {text!r}") from error
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"{where}: expected 3 finite numbers, got {text!r}")
    return values


def _vec3(values: tuple[float, ...]) -> tuple[float, float, float]:
    return (values[0], values[1], values[2])


def _parse_joint(element: ET.Element, *, source: str) -> UrdfJoint:
    name = element.get("name")
    kind = element.get("type")
    where = f"{source}: joint {name!r}"
    parent = element.find("parent")
    child = element.find("child")
    if name is None or kind is None or parent is None or child is None:
        raise ValueError(f"{where}: a joint needs a name, a type, a parent and a child")
    if kind != "fixed" and kind not in _JOINT_KINDS:
        raise ValueError(f"{where}: unsupported joint type {kind!r}")
    origin = element.find("origin")
    xyz = _floats(None if origin is None else origin.get("xyz"), (0.0, 0.0, 0.0), where=where)
    rpy = _floats(None if origin is None else origin.get("rpy"), (0.0, 0.0, 0.0), where=where)
    axis_element = element.find("axis")
    axis = _floats(
        None if axis_element is None else axis_element.get("xyz"), (1.0, 0.0, 0.0), where=where
    )
    norm = math.sqrt(sum(a * a for a in axis))
    if kind != "fixed" and norm == 0.0:
        raise ValueError(f"{where}: zero joint axis")
    lower, upper = -math.inf, math.inf
    limit = element.find("limit")
    if kind in ("revolute", "prismatic"):
        if limit is None:
            raise ValueError(f"{where}: a {kind} joint needs a <limit>")
        lower, upper = float(limit.get("lower", "0")), float(limit.get("upper", "0"))
        if not lower <= upper:
            raise ValueError(f"{where}: lower limit {lower} > upper limit {upper}")
    mimic_element = element.find("mimic")
    mimic = None
    if mimic_element is not None:
        mimicked = mimic_element.get("joint")
        if mimicked is None:
            raise ValueError(f"{where}: <mimic> needs a joint attribute")
        mimic = UrdfMimic(
            joint=mimicked,
            multiplier=float(mimic_element.get("multiplier", "1")),
            offset=float(mimic_element.get("offset", "0")),
        )
    return UrdfJoint(
        name=name,
        kind="fixed" if kind == "fixed" else _JOINT_KINDS[kind],
        parent=parent.get("link", ""),
        child=child.get("link", ""),
        xyz=_vec3(xyz),
        rpy=_vec3(rpy),
        axis=_vec3(tuple(a / norm for a in axis) if norm > 0.0 else axis),
        lower=lower,
        upper=upper,
        mimic=mimic,
    )


def _origin(element: ET.Element, *, where: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The ``xyz`` and ``rpy`` of ``element``'s ``<origin>`` (zeros when absent)."""
    origin = element.find("origin")
    xyz = _floats(None if origin is None else origin.get("xyz"), (0.0, 0.0, 0.0), where=where)
    rpy = _floats(None if origin is None else origin.get("rpy"), (0.0, 0.0, 0.0), where=where)
    return xyz, rpy


def _number(element: ET.Element, attribute: str, *, where: str, positive: bool = True) -> float:
    """A finite (and, with ``positive``, ``> 0``) number attribute of ``element``."""
    text = element.get(attribute)
    try:
        value = float(text) if text is not None else math.nan
    except ValueError as error:
        raise ValueError(f"{where}: cannot read {attribute}={text!r}") from error
    if not math.isfinite(value) or (positive and value <= 0.0):
        kind = "a finite number > 0" if positive else "a finite number"
        raise ValueError(f"{where}: {attribute} must be {kind}, got {text!r}")
    return value


def _parse_inertial(link: str, element: ET.Element, *, source: str) -> UrdfInertial:
    where = f"{source}: link {link!r} <inertial>"
    xyz, rpy = _origin(element, where=where)
    mass, inertia = element.find("mass"), element.find("inertia")
    if mass is None or inertia is None:
        raise ValueError(f"{where}: needs <mass> and <inertia>")
    names = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    values = tuple(_number(inertia, n, where=where, positive=False) for n in names)
    return UrdfInertial(
        link=link,
        mass=_number(mass, "value", where=where),
        xyz=_vec3(xyz),
        rpy=_vec3(rpy),
        inertia=(values[0], values[1], values[2], values[3], values[4], values[5]),
    )


def _parse_collision(link: str, element: ET.Element, *, source: str) -> UrdfCollision:
    where = f"{source}: link {link!r} <collision>"
    xyz, rpy = _origin(element, where=where)
    geometry = element.find("geometry")
    primitive = None if geometry is None or len(geometry) != 1 else geometry[0]
    if primitive is None:
        raise ValueError(f"{where}: needs a <geometry> with one primitive")
    size: tuple[float, ...]
    if primitive.tag == "box":
        size = _floats(primitive.get("size"), (math.nan,) * 3, where=where)
        if not all(value > 0.0 for value in size):
            raise ValueError(f"{where}: box size must be 3 numbers > 0, got {size}")
        kind = "box"
    elif primitive.tag == "sphere":
        kind, size = "sphere", (_number(primitive, "radius", where=where),)
    elif primitive.tag in ("cylinder", "capsule"):
        radius = _number(primitive, "radius", where=where)
        length = _number(primitive, "length", where=where, positive=False)
        if length < 0.0:
            raise ValueError(f"{where}: length must be >= 0, got {length}")
        kind, size = "capsule", (radius, length)
    else:
        raise ValueError(
            f"{where}: unsupported primitive <{primitive.tag}> (box, sphere, cylinder, capsule)"
        )
    return UrdfCollision(link=link, kind=kind, size=size, xyz=_vec3(xyz), rpy=_vec3(rpy))


def parse_urdf(text: str, *, source: str) -> UrdfModel:
    """Parse URDF text (links, joints, origins, axes, limits, mimic tags, inertials and
    collision primitives) in float64.

    Visual elements are not read. Collision primitives: ``<box>``, ``<sphere>``, and
    ``<cylinder>`` read as a capsule (see :class:`UrdfCollision`); meshes are rejected.

    Args:
        text: The URDF document.
        source: A name for error messages (usually the file path).

    Returns:
        The parsed tree.

    Raises:
        ValueError: The document is not a single tree of links and supported joints.
    """
    try:
        robot = ET.fromstring(text)
    except ET.ParseError as error:
        raise ValueError(f"{source}: not valid XML ({error})") from error
    if robot.tag != "robot":
        raise ValueError(f"{source}: the root element must be <robot>, got <{robot.tag}>")
    links = tuple(link.get("name", "") for link in robot.findall("link"))
    joints = tuple(_parse_joint(joint, source=source) for joint in robot.findall("joint"))
    if len(set(links)) != len(links) or "" in links:
        raise ValueError(f"{source}: link names must be present and unique")
    if len({j.name for j in joints}) != len(joints):
        raise ValueError(f"{source}: joint names must be unique")
    children = [j.child for j in joints]
    for j in joints:
        if j.parent not in links or j.child not in links:
            raise ValueError(f"{source}: joint {j.name!r} connects unknown links")
    if len(set(children)) != len(children):
        raise ValueError(f"{source}: a link has more than one parent joint")
    roots = [link for link in links if link not in children]
    if len(roots) != 1:
        raise ValueError(f"{source}: expected one root link, found {roots}")
    inertials: list[UrdfInertial] = []
    collisions: list[UrdfCollision] = []
    for link in robot.findall("link"):
        name = link.get("name", "")
        inertial = link.find("inertial")
        if inertial is not None:
            inertials.append(_parse_inertial(name, inertial, source=source))
        collisions.extend(
            _parse_collision(name, c, source=source) for c in link.findall("collision")
        )
    return UrdfModel(
        name=robot.get("name", ""),
        root=roots[0],
        links=links,
        joints=joints,
        inertials=tuple(inertials),
        collisions=tuple(collisions),
    )


def origin_matrix(xyz: tuple[float, float, float], rpy: tuple[float, float, float]) -> torch.Tensor:
    """An URDF origin as a float64 homogeneous transform ``(4, 4)``: Trans(xyz) · Rz Ry Rx."""
    roll, pitch, yaw = rpy
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    x, y, z = xyz
    return torch.tensor(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr, x],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr, y],
            [-sp, cp * sr, cp * cr, z],
            [0.0, 0.0, 0.0, 1.0],
        ],
        dtype=torch.float64,
    )


def build_chain(model: UrdfModel) -> Chain:
    """Build a float64, CPU pytorch-kinematics chain of ``model``.

    Each URDF link becomes a pytorch-kinematics frame of the same name; its joint is the URDF joint
    whose child it is.

    Args:
        model: The parsed URDF.

    Returns:
        A ``pytorch_kinematics.chain.Chain`` in float64 on the CPU.
    """
    by_parent: dict[str, list[UrdfJoint]] = {}
    for joint in model.joints:
        by_parent.setdefault(joint.parent, []).append(joint)

    def frame(link: str, joint: UrdfJoint | None) -> Frame:
        if joint is None:
            pk_joint = Joint(dtype=torch.float64)
        else:
            pk_joint = Joint(
                name=joint.name,
                offset=Transform3d(matrix=origin_matrix(joint.xyz, joint.rpy), dtype=torch.float64),
                joint_type=joint.kind,
                axis=torch.tensor(joint.axis, dtype=torch.float64),
                dtype=torch.float64,
                limits=None if joint.kind == "fixed" else (joint.lower, joint.upper),
            )
        node = Frame(link, link=Link(link), joint=pk_joint)
        node.children = [frame(j.child, j) for j in by_parent.get(link, [])]
        return node

    return Chain(frame(model.root, None), dtype=torch.float64)
