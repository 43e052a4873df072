"""Generate the Allegro v4 (right), Unitree Z1, Allegro-on-Z1 and Allegro-on-virtual-arm
URDF models for pydrake's Parser (URDF with Drake extensions).

Deterministic: the tables below transcribe specs/allegro_v4.md and specs/z1.md; running the
script twice writes byte-identical files. Usage:

    python scripts/build_allegro_models.py [--out models]

Writes models/allegro/{allegro_right,allegro_z1,allegro_arm}.urdf and models/z1/z1.urdf.

Modelling choices (not in the specs; documented here and in each file's header comment):
- Inertias: solid box / sphere / cylinder about the geometric centre with the spec masses
  (the spec gives masses only). The spec's link masses sum to 0.955 kg, less than the
  "about 1.2 kg" of the whole hand; the table is transcribed as given.
- Allegro PD gains (Drake actuator gains, N*m/rad and N*m*s/rad) are the vendor gains in
  PWM counts scaled by dexdrake.hands.allegro_units.NM_PER_PWM (1/200 N*m per count, full
  PWM 1200 <-> 6 N*m, an assumption: the spec says the PWM -> N*m mapping is undocumented). kp 2.5-5 N*m/rad holds a 0.5 kg object with
  friction 1 (about 2.5 N of pinch force per side needs 0.25 N*m at a 0.1 m lever, i.e.
  0.1 rad of command past contact); SAP integrates the PD implicitly, so it is stable at
  plant dt 2 ms. tests/test_allegro_z1_models.py closes the hand on a 0.5 kg box and lifts
  it 0.1 m (it drops the box with friction 0.1).
- Allegro drive: each finger actuator's effort limit is the driver's PWM limit
  (allegro_units.PWM_LIMITS, 1.35-3.4 N*m) in N*m, the most the drivers ever command; its
  reflected inertia and viscous damping are those of the HIL world's firmware emulator
  (ROTOR_INERTIA, ROTOR_DAMPING), so that the simulated hand is the HIL hand.
- Z1: link geometry is an approximation (cylinders sized to the joint offsets), masses are
  plausible values (arm about 4.4 kg). PD gains are the vendor's default LOWCMD gains in
  N*m/rad per specs/z1.md: kp = k*25.6, kd = 2000*0.0128 = 25.6.
- Hand mount: the hand's base (bottom of the palm box) sits 0.095 m below palm_link along
  palm +z. On the Z1 it is bolted to the flange face, 0.051 m along link06 +x (where the
  Unitree gripper sits), with palm +z (finger direction) = flange +x and the palm normal
  (+x of palm_link, the flexion side) = flange -z: X_link06_palm = (xyz 0.146 0 0,
  rpy 0 pi/2 0). With the flange pointing forward the palm faces down; pointing down, the
  palm faces forward.
- Z1 base welded to world at (-0.45, 0, 0): an object at the origin is 0.45 m in front.
- Virtual arm (sim only; the scene disables gravity on the robot instance): prismatic
  ARTx/y/z along world x/y/z, then revolute ARRx/y/z about world x/y/z (at q = 0) through
  the wrist point (the hand's base), light 0.01 kg intermediate links, the same wrist ->
  palm_link mount as on the Z1. The base is welded so that at q = 0 the palm faces down,
  fingers point +x and the palm grasp centre is 0.25 m above the world origin.
"""

from __future__ import annotations

import argparse
import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path

from dexdrake.hands.allegro_units import KD_VENDOR, KP_VENDOR, NM_PER_PWM, PWM_LIMITS
from dexdrake.hardware.allegro_emulator import EmulatorConfig
from dexdrake.hardware.z1_model import KD_SCALE, KP_SCALE

Vec = tuple[float, float, float]

# ---------------------------------------------------------------- Allegro v4 (right hand)
# specs/allegro_v4.md, kinematics table: name, parent, child, xyz, rpy, axis, lower, upper.
_FINGER_FLEX = [(0.0, 0.0, 0.0164), (0.0, 0.0, 0.054), (0.0, 0.0, 0.0384)]
_FINGER_LIMITS = [(-0.47, 0.47), (-0.196, 1.61), (-0.174, 1.709), (-0.227, 1.618)]
_FINGER_BASES = [  # finger: (xyz, rpy) of its spread joint in palm_link
    ((0.0, 0.0435, -0.001542), (-0.0872665, 0.0, 0.0)),  # index, joint_0.0
    ((0.0, 0.0, 0.0007), (0.0, 0.0, 0.0)),  # middle, joint_4.0
    ((0.0, -0.0435, -0.001542), (0.0872665, 0.0, 0.0)),  # ring, joint_8.0
]
THUMB_JOINTS = [
    ("joint_12.0", "palm_link", "link_12.0", (-0.0182, 0.019333, -0.045987),
     (0.0, -1.65806, -1.5708), (-1.0, 0.0, 0.0), 0.263, 1.396),
    ("joint_13.0", "link_12.0", "link_13.0", (-0.027, 0.005, 0.0399),
     (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), -0.105, 1.163),
    ("joint_14.0", "link_13.0", "link_14.0", (0.0, 0.0, 0.0177),
     (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), -0.189, 1.644),
    ("joint_15.0", "link_14.0", "link_15.0", (0.0, 0.0, 0.0514),
     (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), -0.162, 1.719),
]
FINGER_TIP_OFFSET = 0.0267  # link_3.0 -> link_3.0_tip (and 7, 11)
THUMB_TIP_OFFSET = 0.0423  # link_15.0 -> link_15.0_tip
HAND_VELOCITY = 7.0
# The fingers' drive as the HIL world's Allegro emulator models it (hardware/allegro_emulator.py:
# ddq = accel_per_pwm * pwm - damping * dq): the reflected inertia (kg*m^2, gear ratio 1) that
# NM_PER_PWM N*m per count accelerates at accel_per_pwm, and the viscous damping (N*m*s/rad).
ROTOR_INERTIA = NM_PER_PWM / EmulatorConfig.accel_per_pwm
ROTOR_DAMPING = ROTOR_INERTIA * EmulatorConfig.damping
TIP_RADIUS = 0.012
FINGER_BOX_XY = (0.0196, 0.0275)
FINGER_LENGTHS = (0.0164, 0.054, 0.0384, 0.0267)  # box L of links 0..3 (and 4..7, 8..11)
THUMB_LENGTHS = {13: 0.0177, 14: 0.0514, 15: 0.0423}
PALM_BOX = ((0.0408, 0.1130, 0.095), (-0.0093, 0.0, -0.0475))
THUMB_BASE_BOX = ((0.0358, 0.034, 0.0455), (-0.0179, 0.009, 0.0145))
PALM_MASS = 0.4154
FINGER_MASSES = (0.0119, 0.065, 0.0355, 0.0096)
TIP_MASS = 0.0168
THUMB_MASSES = {12: 0.0176, 13: 0.0119, 14: 0.038, 15: 0.0388}
FRICTION = 1.0
HAND_BASE_BELOW_PALM = 0.095  # palm box bottom, below palm_link along palm -z


def allegro_joints() -> list[tuple]:
    """The 16 revolute joints in bus order: (name, parent, child, xyz, rpy, axis, lo, hi)."""
    rows = []
    for f, (xyz0, rpy0) in enumerate(_FINGER_BASES):
        k = 4 * f
        rows.append((f"joint_{k}.0", "palm_link", f"link_{k}.0", xyz0, rpy0,
                     (0.0, 0.0, 1.0), *_FINGER_LIMITS[0]))
        for i in range(1, 4):
            rows.append((f"joint_{k + i}.0", f"link_{k + i - 1}.0", f"link_{k + i}.0",
                         _FINGER_FLEX[i - 1], (0.0, 0.0, 0.0), (0.0, 1.0, 0.0),
                         *_FINGER_LIMITS[i]))
    rows.extend(THUMB_JOINTS)
    return rows


def allegro_gains() -> list[tuple[float, float]]:
    """Drake (p, d) per hand joint in bus order: vendor gains * NM_PER_PWM (an assumption)."""
    return [(float(p) * NM_PER_PWM, float(d) * NM_PER_PWM) for p, d in zip(KP_VENDOR, KD_VENDOR)]


# ---------------------------------------------------------------- Unitree Z1
# specs/z1.md: name, parent, child, xyz (rpy 0), axis, lower, upper, effort.
Z1_JOINTS = [
    ("joint1", "link00", "link01", (0.0, 0.0, 0.0585), (0.0, 0.0, 1.0), -2.6180, 2.6180, 30.0),
    ("joint2", "link01", "link02", (0.0, 0.0, 0.045), (0.0, 1.0, 0.0), 0.0, 2.9671, 60.0),
    ("joint3", "link02", "link03", (-0.35, 0.0, 0.0), (0.0, 1.0, 0.0), -2.8798, 0.0, 30.0),
    ("joint4", "link03", "link04", (0.218, 0.0, 0.057), (0.0, 1.0, 0.0), -1.5184, 1.5184, 30.0),
    ("joint5", "link04", "link05", (0.07, 0.0, 0.0), (0.0, 0.0, 1.0), -1.3439, 1.3439, 30.0),
    ("joint6", "link05", "link06", (0.0492, 0.0, 0.0), (1.0, 0.0, 0.0), -2.7925, 2.7925, 30.0),
]
Z1_VELOCITY = math.pi
Z1_LOWCMD_KP = (20, 30, 30, 20, 15, 10)  # vendor default LOWCMD gains (specs/z1.md)
Z1_LOWCMD_KD = 2000
# Approximate link geometry: link -> (mass kg, cylinder radius, length, axis 'x'|'z', centre).
Z1_LINKS = {
    "link00": (0.472, 0.045, 0.0585, "z", (0.0, 0.0, 0.02925)),
    "link01": (0.673, 0.040, 0.045, "z", (0.0, 0.0, 0.0225)),
    "link02": (1.19, 0.030, 0.35, "x", (-0.175, 0.0, 0.0)),
    "link03": (0.839, 0.025, 0.218, "x", (0.109, 0.0, 0.0285)),
    "link04": (0.564, 0.030, 0.07, "x", (0.035, 0.0, 0.0)),
    "link05": (0.389, 0.030, 0.0492, "x", (0.0246, 0.0, 0.0)),
    "link06": (0.288, 0.030, 0.051, "x", (0.0255, 0.0, 0.0)),
}
Z1_FLANGE_FACE = 0.051  # along link06 +x (where the Unitree gripper sits)
Z1_BASE_XYZ = (-0.45, 0.0, 0.0)

# Mount: palm_link in the wrist frame (flange face / virtual-arm wrist): +z_palm = +x_wrist.
MOUNT_RPY = (0.0, math.pi / 2, 0.0)

# ---------------------------------------------------------------- virtual arm
# name, axis (world, at q = 0), type, lower, upper, effort, velocity, kp, kd.
ARM_JOINTS = [
    ("ARTx", (1.0, 0.0, 0.0), "prismatic", -0.25, 0.25, 200.0, 1.0, 2000.0, 100.0),
    ("ARTy", (0.0, 1.0, 0.0), "prismatic", -0.25, 0.25, 200.0, 1.0, 2000.0, 100.0),
    ("ARTz", (0.0, 0.0, 1.0), "prismatic", -0.3, 0.3, 200.0, 1.0, 2000.0, 100.0),
    ("ARRx", (1.0, 0.0, 0.0), "revolute", -1.5708, 1.5708, 30.0, math.pi, 60.0, 2.0),
    ("ARRy", (0.0, 1.0, 0.0), "revolute", -0.75, 1.5708, 30.0, math.pi, 60.0, 2.0),
    ("ARRz", (0.0, 0.0, 1.0), "revolute", -1.5708, 1.5708, 30.0, math.pi, 60.0, 2.0),
]
ARM_LINK_MASS = 0.01
ARM_LINK_INERTIA = 1e-5
PALM_GRASP_CENTRE = (0.055, 0.0, -0.03)  # in palm_link: 0.044 m in front of the palm face
ARM_GRASP_CENTRE_HEIGHT = 0.25  # world z of the grasp centre at q = 0 (above the origin)


def arm_wrist_position() -> Vec:
    """World position of the virtual arm's wrist (hand base) at q = 0.

    palm_link = wrist + (0.095, 0, 0), rotated by R_y(pi/2): a palm point p maps to
    wrist + (0.095 + p_z, p_y, -p_x). The grasp centre is put over the world origin.
    """
    cx, cy, cz = PALM_GRASP_CENTRE
    return (-(HAND_BASE_BELOW_PALM + cz), -cy, ARM_GRASP_CENTRE_HEIGHT + cx)


# ---------------------------------------------------------------- XML helpers
def _f(v: float) -> str:
    return repr(float(v)) if v != 0 else "0"


def _v(values: Sequence[float]) -> str:
    return " ".join(_f(v) for v in values)


def _origin(parent: ET.Element, xyz: Sequence[float], rpy: Sequence[float] = (0, 0, 0)) -> None:
    ET.SubElement(parent, "origin", xyz=_v(xyz), rpy=_v(rpy))


def _inertial(link: ET.Element, mass: float, com: Vec, ixx: float, iyy: float, izz: float,
              rpy: Vec = (0.0, 0.0, 0.0)) -> None:
    el = ET.SubElement(link, "inertial")
    _origin(el, com, rpy)
    ET.SubElement(el, "mass", value=_f(mass))
    ET.SubElement(el, "inertia", ixx=_f(ixx), ixy="0", ixz="0", iyy=_f(iyy), iyz="0",
                  izz=_f(izz))


def _box_inertia(mass: float, size: Vec) -> tuple[float, float, float]:
    x, y, z = size
    return (mass * (y * y + z * z) / 12, mass * (x * x + z * z) / 12,
            mass * (x * x + y * y) / 12)


def _geometry(parent: ET.Element, kind: str, **attrs: str) -> None:
    ET.SubElement(ET.SubElement(parent, "geometry"), kind, **attrs)


def _shape(link: ET.Element, kind: str, attrs: dict[str, str], xyz: Vec, rpy: Vec,
           colour: str, collide: bool = True) -> None:
    """A visual and (optionally) a collision element with friction FRICTION."""
    vis = ET.SubElement(link, "visual")
    _origin(vis, xyz, rpy)
    _geometry(vis, kind, **attrs)
    mat = ET.SubElement(vis, "material", name=colour)
    ET.SubElement(mat, "color", rgba={"dark": "0.2 0.2 0.2 1", "white": "0.9 0.9 0.9 1",
                                      "silver": "0.7 0.7 0.75 1"}[colour])
    if not collide:
        return
    col = ET.SubElement(link, "collision")
    _origin(col, xyz, rpy)
    _geometry(col, kind, **attrs)
    props = ET.SubElement(col, "drake:proximity_properties")
    ET.SubElement(props, "drake:mu_dynamic", value=_f(FRICTION))
    ET.SubElement(props, "drake:mu_static", value=_f(FRICTION))


def _box_link(robot: ET.Element, name: str, mass: float, size: Vec, centre: Vec,
              colour: str) -> None:
    link = ET.SubElement(robot, "link", name=name)
    _inertial(link, mass, centre, *_box_inertia(mass, size))
    _shape(link, "box", {"size": _v(size)}, centre, (0.0, 0.0, 0.0), colour)


def _joint(robot: ET.Element, name: str, kind: str, parent: str, child: str, xyz: Vec,
           rpy: Vec = (0.0, 0.0, 0.0), axis: Vec | None = None,
           limits: tuple[float, float, float, float] | None = None, damping: float = 0.0) -> None:
    j = ET.SubElement(robot, "joint", name=name, type=kind)
    ET.SubElement(j, "parent", link=parent)
    ET.SubElement(j, "child", link=child)
    _origin(j, xyz, rpy)
    if axis is not None:
        ET.SubElement(j, "axis", xyz=_v(axis))
    if limits is not None:
        lo, hi, effort, velocity = limits
        ET.SubElement(j, "limit", lower=_f(lo), upper=_f(hi), effort=_f(effort),
                      velocity=_f(velocity))
    if damping:
        ET.SubElement(j, "dynamics", damping=_f(damping))


def _transmission(robot: ET.Element, joint: str, p: float, d: float, rotor_inertia: float = 0.0) -> None:
    t = ET.SubElement(robot, "transmission", name=f"{joint}_trans")
    ET.SubElement(t, "type").text = "transmission_interface/SimpleTransmission"
    ET.SubElement(t, "joint", name=joint)
    act = ET.SubElement(t, "actuator", name=f"{joint}_act")
    ET.SubElement(act, "drake:controller_gains", p=_f(p), d=_f(d))
    if rotor_inertia:
        ET.SubElement(act, "drake:rotor_inertia", value=_f(rotor_inertia))


def _filter_group(robot: ET.Element, name: str, members: Sequence[str]) -> None:
    """Disable collisions among `members` (a group that ignores itself)."""
    g = ET.SubElement(robot, "drake:collision_filter_group", name=name)
    for m in members:
        ET.SubElement(g, "drake:member", link=m)
    ET.SubElement(g, "drake:ignored_collision_filter_group", name=name)


# ---------------------------------------------------------------- model parts
def add_allegro(robot: ET.Element) -> None:
    """Palm, 16 actuated joints, 4 fixed tip links and the hand's collision filters."""
    _box_link(robot, "palm_link", PALM_MASS, *PALM_BOX, "dark")
    joints = allegro_joints()
    for idx, (name, parent, child, xyz, rpy, axis, lo, hi) in enumerate(joints):
        k = int(child.split("_")[1].split(".")[0])
        if k == 12:
            mass, (size, centre) = THUMB_MASSES[12], THUMB_BASE_BOX
        else:
            length = THUMB_LENGTHS[k] if k > 12 else FINGER_LENGTHS[k % 4]
            mass = THUMB_MASSES[k] if k > 12 else FINGER_MASSES[k % 4]
            size, centre = (*FINGER_BOX_XY, length), (0.0, 0.0, length / 2)
        _box_link(robot, child, mass, size, centre, "dark")
        _joint(robot, name, "revolute", parent, child, xyz, rpy, axis,
               (lo, hi, PWM_LIMITS[idx] * NM_PER_PWM, HAND_VELOCITY), damping=ROTOR_DAMPING)
        if k in (3, 7, 11, 15):
            tip = f"{child}_tip"
            link = ET.SubElement(robot, "link", name=tip)
            inertia = 0.4 * TIP_MASS * TIP_RADIUS**2
            _inertial(link, TIP_MASS, (0.0, 0.0, 0.0), inertia, inertia, inertia)
            _shape(link, "sphere", {"radius": _f(TIP_RADIUS)}, (0.0, 0.0, 0.0),
                   (0.0, 0.0, 0.0), "white")
            offset = THUMB_TIP_OFFSET if k == 15 else FINGER_TIP_OFFSET
            _joint(robot, f"{name}_tip", "fixed", child, tip, (0.0, 0.0, offset))
    for (name, *_), (p, d) in zip(joints, allegro_gains()):
        _transmission(robot, name, p, d, ROTOR_INERTIA)
    # Adjacent links: Drake already filters parent-child pairs; these groups also filter
    # the palm against each finger's first two links (thumb: three), whose boxes overlap
    # the palm box near the knuckles.
    for finger, ks in (("index", (0, 1)), ("middle", (4, 5)), ("ring", (8, 9)),
                       ("thumb", (12, 13, 14))):
        _filter_group(robot, f"palm_{finger}", ["palm_link"] + [f"link_{k}.0" for k in ks])


def _cylinder_link(robot: ET.Element, name: str, mass: float, radius: float, length: float,
                   axis: str, centre: Vec, collide: bool) -> None:
    link = ET.SubElement(robot, "link", name=name)
    rpy = (0.0, math.pi / 2, 0.0) if axis == "x" else (0.0, 0.0, 0.0)
    i_axial = mass * radius**2 / 2
    i_trans = mass * (3 * radius**2 + length**2) / 12
    # Inertia expressed in the rotated cylinder frame (its z = the cylinder axis).
    _inertial(link, mass, centre, i_trans, i_trans, i_axial, rpy)
    _shape(link, "cylinder", {"radius": _f(radius), "length": _f(length)}, centre, rpy,
           "silver", collide)


def add_z1(robot: ET.Element) -> None:
    """The Z1 arm's 7 links, 6 actuated joints (vendor LOWCMD gains) and self-filtering."""
    for name, (mass, r, length, axis, centre) in Z1_LINKS.items():
        _cylinder_link(robot, name, mass, r, length, axis, centre, collide=True)
    for name, parent, child, xyz, axis, lo, hi, effort in Z1_JOINTS:
        _joint(robot, name, "revolute", parent, child, xyz, (0.0, 0.0, 0.0), axis,
               (lo, hi, effort, Z1_VELOCITY))
    for (name, *_), kp in zip(Z1_JOINTS, Z1_LOWCMD_KP):
        _transmission(robot, name, kp * KP_SCALE, Z1_LOWCMD_KD * KD_SCALE)
    # The link shapes are approximations: arm self-collision is left to the vendor
    # controller, so all Z1 links are filtered against each other.
    _filter_group(robot, "z1_arm", list(Z1_LINKS))


def add_virtual_arm(robot: ET.Element) -> str:
    """Six virtual joints from a world-welded base; returns the wrist link's name."""
    ET.SubElement(robot, "link", name="arm_base")
    _joint(robot, "arm_base_weld", "fixed", "world", "arm_base", arm_wrist_position())
    parent = "arm_base"
    for name, axis, kind, lo, hi, effort, velocity, kp, kd in ARM_JOINTS:
        child = f"arm_link_{name[2:].lower()}" if name != "ARRz" else "arm_wrist"
        link = ET.SubElement(robot, "link", name=child)
        _inertial(link, ARM_LINK_MASS, (0.0, 0.0, 0.0), *(3 * (ARM_LINK_INERTIA,)))
        _joint(robot, name, kind, parent, child, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), axis,
               (lo, hi, effort, velocity))
        _transmission(robot, name, kp, kd)
        parent = child
    return parent


def _mount(robot: ET.Element, wrist: str, face_offset: float) -> None:
    _joint(robot, "hand_mount", "fixed", wrist, "palm_link",
           (face_offset + HAND_BASE_BELOW_PALM, 0.0, 0.0), MOUNT_RPY)


def _robot(name: str, comment: str) -> ET.Element:
    robot = ET.Element("robot", {"name": name, "xmlns:drake": "http://drake.mit.edu"})
    robot.append(ET.Comment(comment))
    return robot


def build_models() -> dict[str, ET.Element]:
    """All four robots keyed by their path relative to the models folder."""
    header = " Generated by scripts/build_allegro_models.py; do not edit by hand. "
    hand = _robot("allegro_right", header + "Allegro v4 right hand (specs/allegro_v4.md). ")
    add_allegro(hand)

    z1 = _robot("z1", header + "Unitree Z1 (specs/z1.md); link shapes and masses are "
                "approximations. Base welded to world at (-0.45, 0, 0). ")
    add_z1(z1)
    _joint(z1, "z1_base_weld", "fixed", "world", "link00", Z1_BASE_XYZ)

    hz = _robot("allegro_z1", header + "Allegro v4 right hand on the Unitree Z1 flange: "
                "palm_link at xyz (0.146, 0, 0), rpy (0, pi/2, 0) in link06. Base welded to "
                "world at (-0.45, 0, 0). ")
    add_z1(hz)
    _joint(hz, "z1_base_weld", "fixed", "world", "link00", Z1_BASE_XYZ)
    _mount(hz, "link06", Z1_FLANGE_FACE)
    add_allegro(hz)

    arm = _robot("allegro_arm", header + "Allegro v4 right hand on a 6-DoF virtual arm "
                 f"(gravity-compensated by the scene). Wrist welded at {arm_wrist_position()}; "
                 "at q = 0 the palm faces down, fingers along +x, grasp centre 0.25 m above "
                 "the origin. ")
    wrist = add_virtual_arm(arm)
    _mount(arm, wrist, 0.0)
    add_allegro(arm)
    return {"allegro/allegro_right.urdf": hand, "z1/z1.urdf": z1,
            "allegro/allegro_z1.urdf": hz, "allegro/allegro_arm.urdf": arm}


def write_models(out: Path) -> list[Path]:
    """Write every model under `out`; returns the written paths."""
    written = []
    for rel, robot in build_models().items():
        ET.indent(robot)
        path = out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        text = ET.tostring(robot, encoding="unicode")
        path.write_text('<?xml version="1.0"?>\n' + text + "\n")
        written.append(path)
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path,
                        default=Path(__file__).resolve().parents[1] / "models",
                        help="models folder to write into (default: the repo's models/)")
    for path in write_models(parser.parse_args().out):
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
