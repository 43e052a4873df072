"""Generate the project's Adroit-style hand on a 6-DoF virtual arm as SDFormat 1.9.

Writes models/adroit/adroit.sdf (30 actuated joints) and the fewer-finger variants
adroit_4f.sdf (no little finger), adroit_3f.sdf (thumb, index, middle) and adroit_2f.sdf
(thumb, index). Every number below transcribes /work/shared/specs/adroit.md (bodies,
joint axes and ranges, capsule/box collision geometry, masses, damping, armature) except the
PD gains and effort limits, which are this model's own (see GAINS). The output is
deterministic: run `python scripts/build_adroit_model.py` and commit the result.

Modelling choices (also written into each SDF's header comment):
- MuJoCo stacks the six arm joints on the forearm body; Drake needs one body per joint, so
  the arm is a chain arm_base -ARTx-> arm_tx -ARTy-> arm_ty -ARTz-> arm_tz -ARRx-> arm_rx
  -ARRy-> arm_ry -ARRz-> forearm of massless-looking (1 g) links that all coincide with the
  forearm base at q = 0. arm_base is welded to `world` at the spec's forearm pose.
- Inertia: each body's mass is spread over its spec collision shapes by volume (solid
  shapes, parallel-axis combined); bodies with no collision shape get a small solid sphere.
- Self-collision is filtered for the whole robot (one collision filter group ignoring
  itself): at q = 0 the palm box already overlaps the proximal capsules and neighbouring
  proximal capsules are 2 mm apart, and the source model does not collide hand geoms with
  each other either. Robot-vs-object/table contact is unaffected.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

Vec3 = tuple[float, float, float]
IDENTITY_QUAT = (1.0, 0.0, 0.0, 0.0)
FRICTION = 1.0

# ---------------------------------------------------------------------------------------
# PD gains, effort limits, joint damping and armature per joint group.
#   p, d: drake:controller_gains (N/m, N s/m or N m/rad, N m s/rad); SAP integrates the PD
#         implicitly, so these stay stable at plant dt 2 ms and 1 ms.
#   effort: actuator effort limit (N or N m), which SAP's PD constraint respects.
#   damping, armature: spec values (armature -> drake:rotor_inertia with gear ratio 1).
# Sizing (gravity is off on the robot instance; the arm is gravity compensated):
#   arm slides move ~5 kg: p = 5000 N/m gives w_n = sqrt(5000/5) ~ 32 rad/s (5 Hz, twice the
#     bandwidth a 100 Hz policy needs) and 1 mm sag under a 0.5 kg object's weight;
#     d = 300 plus joint damping 20 gives damping ratio ~1.0.
#   arm hinges: ~0.5 kg m^2 about the forearm base for ARRx/ARRy: p = 500 N m/rad -> 32 rad/s,
#     d = 15 + damping 20 -> ratio ~1.1 (ARRz, ~0.01 kg m^2, is overdamped, tau ~ 0.07 s).
#   wrist: ~0.002 kg m^2 + armature 0.005: p = 50 -> ~85 rad/s, d = 0.7 + 0.5 -> ratio ~1;
#     a 0.5 kg object 10 cm out deflects it 0.01 rad.
#   fingers/thumb: ~1e-4 kg m^2 + armature 0.001: p = 5 -> ~67 rad/s, d = 0.1 + 0.05 -> ratio
#     ~1. Holding 0.5 kg with friction 1 needs ~2.5 N normal force per side, i.e. ~0.2 N m at a
#     proximal joint (7 cm lever): 0.04 rad of squeeze error; the 2 N m limit allows ~30 N.
#     (MuJoCo's Adroit uses a gain of 1 here, i.e. 5x softer fingers.) Measured (SAP, dt 2 ms
#     and 1 ms alike, no overshoot above 1%): 2% settling ~100 ms for finger/thumb steps,
#     ~75 ms wrist, ~180-210 ms arm slides, ~250-280 ms arm hinges.
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Gains:
    p: float
    d: float
    effort: float
    damping: float
    armature: float


GAINS: dict[str, Gains] = {
    "arm_slide": Gains(p=5000.0, d=300.0, effort=500.0, damping=20.0, armature=0.001),
    "arm_hinge": Gains(p=500.0, d=15.0, effort=200.0, damping=20.0, armature=0.001),
    "wrist": Gains(p=50.0, d=0.7, effort=20.0, damping=0.5, armature=0.005),
    "finger": Gains(p=5.0, d=0.1, effort=2.0, damping=0.05, armature=0.001),
}


@dataclass(frozen=True)
class Joint:
    name: str
    kind: str  # "revolute" or "prismatic"
    axis: Vec3  # in the child body frame
    lower: float
    upper: float
    group: str  # key of GAINS


@dataclass(frozen=True)
class Shape:
    kind: str  # "capsule" (size = radius, half-length along z), "box" (half-extents), "sphere"
    size: tuple[float, ...]
    pos: Vec3


@dataclass(frozen=True)
class Body:
    name: str
    parent: str
    pos: Vec3
    quat: tuple[float, float, float, float]  # w, x, y, z
    mass: float
    joint: Joint | None  # the joint to the parent (None: welded to world)
    collisions: tuple[Shape, ...] = ()
    proxy_radius: float = 0.01  # inertia/visual sphere for bodies with no collision shape


def _x(name: str, lo: float, hi: float, group: str = "finger") -> Joint:
    return Joint(name, "revolute", (1.0, 0.0, 0.0), lo, hi, group)


def _y(name: str, lo: float, hi: float, group: str = "finger") -> Joint:
    return Joint(name, "revolute", (0.0, 1.0, 0.0), lo, hi, group)


# --- arm: spec "forearm | world | 0, -0.7, 0.2 | 0.0006, -0.0006, 0.7068, 0.7074" ----------
FOREARM_POS: Vec3 = (0.0, -0.7, 0.2)
FOREARM_QUAT = (0.0006, -0.0006, 0.7068, 0.7074)
ARM_LINK_MASS = 0.001
ARM_JOINTS = (
    Joint("ARTx", "prismatic", (1.0, 0.0, 0.0), -0.25, 0.25, "arm_slide"),
    Joint("ARTy", "prismatic", (0.0, 1.0, 0.0), 0.0, 0.2, "arm_slide"),
    Joint("ARTz", "prismatic", (0.0, 0.0, 1.0), -0.3, 0.5, "arm_slide"),
    Joint("ARRx", "revolute", (1.0, 0.0, 0.0), -0.75, 0.75, "arm_hinge"),
    Joint("ARRy", "revolute", (0.0, 1.0, 0.0), -0.75, 0.75, "arm_hinge"),
    Joint("ARRz", "revolute", (0.0, 0.0, 1.0), -0.75, 0.75, "arm_hinge"),
)
ARM_LINKS = ("arm_base", "arm_tx", "arm_ty", "arm_tz", "arm_rx", "arm_ry", "forearm")

FINGER_FLEX = (0.0, 1.571)
FINGER_ABD = (-0.436, 0.436)
PROXIMAL = Shape("capsule", (0.010, 0.0225), (0.0, 0.0, 0.0225))
MIDDLE = Shape("capsule", (0.008, 0.0125), (0.0, 0.0, 0.0125))
DISTAL = Shape("capsule", (0.007, 0.012), (0.0, 0.0, 0.012))
KNUCKLE_POS: dict[str, Vec3] = {
    "ff": (0.033, 0.0, 0.095),
    "mf": (0.011, 0.0, 0.099),
    "rf": (-0.011, 0.0, 0.095),
    "lf": (-0.017, 0.0, 0.044),  # lfknuckle sits on lfmetacarpal, not on the palm
}
FINGERTIP_OFFSET = 0.026
THUMBTIP_OFFSET = 0.0275
GRASP_CENTRE: Vec3 = (0.007, -0.05, 0.07)
FINGERS = ("ff", "mf", "rf", "lf", "th")  # in policy order
VARIANTS: dict[str, tuple[str, ...]] = {
    "adroit": ("ff", "mf", "rf", "lf", "th"),
    "adroit_4f": ("ff", "mf", "rf", "th"),
    "adroit_3f": ("ff", "mf", "th"),
    "adroit_2f": ("ff", "th"),
}


def arm_and_palm() -> list[Body]:
    """Arm chain, forearm, wrist and palm."""
    bodies = [Body("arm_base", "world", FOREARM_POS, FOREARM_QUAT, ARM_LINK_MASS, None)]
    for parent, child, joint in zip(ARM_LINKS[:-2], ARM_LINKS[1:-1], ARM_JOINTS[:-1]):
        bodies.append(Body(child, parent, (0.0, 0.0, 0.0), IDENTITY_QUAT, ARM_LINK_MASS, joint))
    bodies += [
        Body("forearm", "arm_ry", (0.0, 0.0, 0.0), IDENTITY_QUAT, 4.0, ARM_JOINTS[-1],
             (Shape("capsule", (0.05, 0.033), (0.0, 0.0, 0.29)),)),
        Body("wrist", "forearm", (0.0, 0.0, 0.396), IDENTITY_QUAT, 0.3,
             _y("WRJ1", -0.524, 0.175, "wrist"), proxy_radius=0.02),
        Body("palm", "wrist", (0.0, 0.0, 0.034), IDENTITY_QUAT, 0.3,
             _x("WRJ0", -0.785, 0.611, "wrist"),
             (Shape("box", (0.032, 0.0111, 0.049), (0.011, 0.0, 0.038)),
              Shape("box", (0.011, 0.0111, 0.025), (-0.032, 0.0, 0.014)))),
    ]
    return bodies


def finger(prefix: str) -> list[Body]:
    """Knuckle, proximal, middle, distal of ff/mf/rf/lf (lf with its metacarpal)."""
    up = prefix.upper()
    bodies = []
    knuckle_parent = "palm"
    if prefix == "lf":
        knuckle_parent = "lfmetacarpal"
        bodies.append(Body(
            "lfmetacarpal", "palm", (-0.017, 0.0, 0.044), IDENTITY_QUAT, 0.075,
            Joint("LFJ4", "revolute", (0.571, 0.0, 0.821), 0.0, 0.698, "finger"),
            (Shape("box", (0.0095, 0.0111, 0.025), (-0.0165, 0.0, 0.01)),)))
    bodies += [
        Body(f"{prefix}knuckle", knuckle_parent, KNUCKLE_POS[prefix], IDENTITY_QUAT, 0.008,
             _y(f"{up}J3", *FINGER_ABD), proxy_radius=0.008),
        Body(f"{prefix}proximal", f"{prefix}knuckle", (0.0, 0.0, 0.0), IDENTITY_QUAT, 0.014,
             _x(f"{up}J2", *FINGER_FLEX), (PROXIMAL,)),
        Body(f"{prefix}middle", f"{prefix}proximal", (0.0, 0.0, 0.045), IDENTITY_QUAT, 0.012,
             _x(f"{up}J1", *FINGER_FLEX), (MIDDLE,)),
        Body(f"{prefix}distal", f"{prefix}middle", (0.0, 0.0, 0.025), IDENTITY_QUAT, 0.010,
             _x(f"{up}J0", *FINGER_FLEX), (DISTAL,)),
    ]
    return bodies


def thumb() -> list[Body]:
    """thbase, thproximal, thhub, thmiddle, thdistal."""
    return [
        Body("thbase", "palm", (0.034, -0.009, 0.029), (0.924, 0.0, 0.3825, 0.0), 0.010,
             Joint("THJ4", "revolute", (0.0, 0.0, -1.0), -1.047, 1.047, "finger"),
             proxy_radius=0.01),
        Body("thproximal", "thbase", (0.0, 0.0, 0.0), IDENTITY_QUAT, 0.016,
             _x("THJ3", 0.0, 1.309), (Shape("capsule", (0.013, 0.019), (0.0, 0.0, 0.019)),)),
        Body("thhub", "thproximal", (0.0, 0.0, 0.038), IDENTITY_QUAT, 0.002,
             _x("THJ2", -0.262, 0.262), proxy_radius=0.006),
        Body("thmiddle", "thhub", (0.0, 0.0, 0.0), IDENTITY_QUAT, 0.016,
             _y("THJ1", -0.524, 0.524), (Shape("capsule", (0.011, 0.016), (0.0, 0.0, 0.016)),)),
        Body("thdistal", "thmiddle", (0.0, 0.0, 0.032), IDENTITY_QUAT, 0.016,
             _y("THJ0", -1.571, 0.0),
             (Shape("capsule", (0.0092, 0.013), (0.0, 0.0, 0.013)),)),
    ]


def bodies_for(fingers: tuple[str, ...]) -> list[Body]:
    """All bodies of a hand with the given fingers, in policy (= joint) order."""
    unknown = set(fingers) - set(FINGERS)
    if unknown:
        raise ValueError(f"unknown fingers {sorted(unknown)}; valid: {FINGERS}")
    bodies = arm_and_palm()
    for f in FINGERS:
        if f in fingers:
            bodies += thumb() if f == "th" else finger(f)
    return bodies


def site_frames(fingers: tuple[str, ...]) -> list[tuple[str, str, Vec3]]:
    """(frame name, body, offset) for the fingertip sites and the palm grasp centre."""
    frames = []
    for f in fingers:
        if f == "th":
            frames.append(("S_thtip", "thdistal", (0.0, 0.0, THUMBTIP_OFFSET)))
        else:
            frames.append((f"S_{f}tip", f"{f}distal", (0.0, 0.0, FINGERTIP_OFFSET)))
    frames.append(("S_grasp", "palm", GRASP_CENTRE))
    return frames


# --- inertia ------------------------------------------------------------------------------
def _volume(s: Shape) -> float:
    if s.kind == "capsule":
        r, hl = s.size
        return math.pi * r * r * 2 * hl + 4.0 / 3.0 * math.pi * r**3
    if s.kind == "box":
        return 8.0 * s.size[0] * s.size[1] * s.size[2]
    return 4.0 / 3.0 * math.pi * s.size[0] ** 3


def _solid_inertia(s: Shape, m: float) -> np.ndarray:
    """Rotational inertia of a solid shape of mass m about its centre (shape axes)."""
    if s.kind == "capsule":
        r, hl = s.size
        h = 2 * hl
        v_cyl, v_caps = math.pi * r * r * h, 4.0 / 3.0 * math.pi * r**3
        mc, ms = m * v_cyl / (v_cyl + v_caps), m * v_caps / (v_cyl + v_caps)
        izz = mc * r * r / 2 + ms * 2 * r * r / 5
        ixx = mc * (h * h / 12 + r * r / 4) + ms * (2 * r * r / 5 + h * h / 4 + 3 * h * r / 8)
        return np.diag([ixx, ixx, izz])
    if s.kind == "box":
        a, b, c = s.size
        return m / 3.0 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])
    return np.eye(3) * 2.0 / 5.0 * m * s.size[0] ** 2


def body_inertia(b: Body) -> tuple[np.ndarray, np.ndarray]:
    """(centre of mass, rotational inertia about it) in the body frame."""
    shapes = b.collisions or (Shape("sphere", (b.proxy_radius,), (0.0, 0.0, 0.0)),)
    vols = np.array([_volume(s) for s in shapes])
    masses = b.mass * vols / vols.sum()
    centres = np.array([s.pos for s in shapes])
    com = masses @ centres / b.mass
    inertia = np.zeros((3, 3))
    for s, m, c in zip(shapes, masses, centres):
        d = c - com
        inertia += _solid_inertia(s, m) + m * (d @ d * np.eye(3) - np.outer(d, d))
    return com, inertia


# --- SDF writing --------------------------------------------------------------------------
def _f(x: float) -> str:
    s = f"{x:.10g}"
    return "0" if s == "-0" else s


def _v(v) -> str:
    return " ".join(_f(x) for x in v)


def quat_to_rpy(q: tuple[float, float, float, float]) -> Vec3:
    """SDF roll-pitch-yaw (R = Rz(y) Ry(p) Rx(r)) of a w,x,y,z quaternion (normalised here)."""
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    r = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
    roll = math.atan2(r[2, 1], r[2, 2])
    pitch = math.atan2(-r[2, 0], math.hypot(r[0, 0], r[1, 0]))
    yaw = math.atan2(r[1, 0], r[0, 0])
    return roll, pitch, yaw


def _geometry(s: Shape) -> str:
    if s.kind == "capsule":
        return (f"<capsule><radius>{_f(s.size[0])}</radius>"
                f"<length>{_f(2 * s.size[1])}</length></capsule>")
    if s.kind == "box":
        return f"<box><size>{_v(2 * np.asarray(s.size))}</size></box>"
    return f"<sphere><radius>{_f(s.size[0])}</radius></sphere>"


def _colour(name: str) -> str:
    if name.startswith("arm_") or name == "forearm":
        return "0.45 0.45 0.5 1"
    return "0.85 0.7 0.55 1" if name not in ("palm", "wrist") else "0.75 0.6 0.45 1"


def _link(b: Body) -> list[str]:
    rel = "" if b.parent == "world" else f' relative_to="{b.parent}"'
    com, inertia = body_inertia(b)
    lines = [
        f'    <link name="{b.name}">',
        f"      <pose{rel}>{_v(b.pos)} {_v(quat_to_rpy(b.quat))}</pose>",
        "      <inertial>",
        f"        <mass>{_f(b.mass)}</mass>",
        f"        <pose>{_v(com)} 0 0 0</pose>",
        "        <inertia>"
        f"<ixx>{_f(inertia[0, 0])}</ixx><ixy>{_f(inertia[0, 1])}</ixy>"
        f"<ixz>{_f(inertia[0, 2])}</ixz><iyy>{_f(inertia[1, 1])}</iyy>"
        f"<iyz>{_f(inertia[1, 2])}</iyz><izz>{_f(inertia[2, 2])}</izz></inertia>",
        "      </inertial>",
    ]
    for i, s in enumerate(b.collisions):
        lines += [
            f'      <collision name="{b.name}_collision_{i}">',
            f"        <pose>{_v(s.pos)} 0 0 0</pose>",
            f"        <geometry>{_geometry(s)}</geometry>",
            "        <drake:proximity_properties>"
            f"<drake:mu_dynamic>{_f(FRICTION)}</drake:mu_dynamic>"
            f"<drake:mu_static>{_f(FRICTION)}</drake:mu_static>"
            "</drake:proximity_properties>",
            "      </collision>",
        ]
    visuals = b.collisions
    if not visuals and not b.name.startswith("arm_"):
        visuals = (Shape("sphere", (b.proxy_radius,), (0.0, 0.0, 0.0)),)
    for i, s in enumerate(visuals):
        lines += [
            f'      <visual name="{b.name}_visual_{i}">',
            f"        <pose>{_v(s.pos)} 0 0 0</pose>",
            f"        <geometry>{_geometry(s)}</geometry>",
            f"        <material><diffuse>{_colour(b.name)}</diffuse></material>",
            "      </visual>",
        ]
    lines.append("    </link>")
    return lines


def _joint(b: Body) -> list[str]:
    j = b.joint
    assert j is not None
    g = GAINS[j.group]
    axis = np.asarray(j.axis) / np.linalg.norm(j.axis)
    return [
        f'    <joint name="{j.name}" type="{j.kind}">',
        f"      <parent>{b.parent}</parent>",
        f"      <child>{b.name}</child>",
        "      <axis>",
        f"        <xyz>{_v(axis)}</xyz>",
        f"        <limit><lower>{_f(j.lower)}</lower><upper>{_f(j.upper)}</upper>"
        f"<effort>{_f(g.effort)}</effort></limit>",
        f"        <dynamics><damping>{_f(g.damping)}</damping></dynamics>",
        "      </axis>",
        f'      <drake:controller_gains p="{_f(g.p)}" d="{_f(g.d)}"/>',
        f"      <drake:rotor_inertia>{_f(g.armature)}</drake:rotor_inertia>",
        "      <drake:gear_ratio>1</drake:gear_ratio>",
        "    </joint>",
    ]


def _header(name: str, fingers: tuple[str, ...]) -> str:
    gains = "\n".join(
        f"    {k:9s}: p={_f(g.p)} d={_f(g.d)} effort={_f(g.effort)} "
        f"damping={_f(g.damping)} rotor_inertia={_f(g.armature)}"
        for k, g in GAINS.items())
    return f"""<!--
  {name}: dexdrake's Adroit-style hand on a 6-DoF virtual arm (fingers: {', '.join(fingers)}).
  GENERATED by scripts/build_adroit_model.py from specs/adroit.md; do not edit by hand.

  Arm: chain arm_base -ARTx-> arm_tx -ARTy-> arm_ty -ARTz-> arm_tz -ARRx-> arm_rx -ARRy->
  arm_ry -ARRz-> forearm of 1 g links, all at the forearm base at q = 0 (MuJoCo stacks the six
  joints on one body). arm_base is welded to world at the spec's forearm pose.

  Position servos: every joint has an actuator with Drake PD gains (drake:controller_gains),
  solved implicitly by SAP, so they are stable at plant dt 2 ms and 1 ms. Connect the plant's
  desired-state input port ([q_d; v_d]) to use them. Gains assume gravity is disabled on this
  model instance (gravity-compensated virtual arm):
{gains}
  arm slides: ~5 kg moved, w_n ~32 rad/s, damping ratio ~1, 1 mm sag under 5 N.
  arm hinges: ~0.5 kg m^2 about the base, w_n ~32 rad/s, ratio ~1.1 (ARRz overdamped).
  wrist: w_n ~85 rad/s, ratio ~1. fingers: w_n ~67 rad/s, ratio ~1 with the armature;
  p=5 N m/rad holds a 0.5 kg object (friction 1) with ~0.04 rad squeeze error, the 2 N m
  limit allows ~30 N fingertip force; tests/test_adroit_model.py closes the hand on a
  0.5 kg box under the down-facing palm and checks it is held. (MuJoCo's Adroit: finger
  gain 1, arm 500 with bias 200.)
  Commands are joint positions directly (MuJoCo's arm settles at 2.5*u; this one at u).

  Collision: spec capsules/boxes, friction 1. All robot self-collision is filtered (group
  "robot" ignores itself): the palm box overlaps the proximal capsules at q = 0.
  Frames: S_<finger>tip fingertip sites, S_grasp palm grasp centre (palm faces -y of palm).
-->
"""


def build_sdf(name: str, fingers: tuple[str, ...]) -> str:
    """The SDFormat text of hand `name` with the given fingers."""
    bodies = bodies_for(fingers)
    lines = [
        '<?xml version="1.0"?>',
        _header(name, fingers).rstrip("\n"),
        '<sdf xmlns:drake="http://drake.mit.edu" version="1.9">',
        f'  <model name="{name}">',
    ]
    for b in bodies:
        lines += _link(b)
    lines += [
        '    <joint name="arm_base_weld" type="fixed">',
        "      <parent>world</parent>",
        "      <child>arm_base</child>",
        "    </joint>",
    ]
    for b in bodies:
        if b.joint is not None:
            lines += _joint(b)
    for frame, body, offset in site_frames(fingers):
        lines += [
            f'    <frame name="{frame}" attached_to="{body}">',
            f'      <pose relative_to="{body}">{_v(offset)} 0 0 0</pose>',
            "    </frame>",
        ]
    lines.append('    <drake:collision_filter_group name="robot">')
    lines += [f"      <drake:member>{b.name}</drake:member>" for b in bodies if b.collisions]
    lines += [
        "      <drake:ignored_collision_filter_group>robot</drake:ignored_collision_filter_group>",
        "    </drake:collision_filter_group>",
        "  </model>",
        "</sdf>",
        "",
    ]
    return "\n".join(lines)


# --- hand descriptions (dexdrake/hands/description.py schema) -----------------------------
ARM_JOINT_NAMES = tuple(j.name for j in ARM_JOINTS)
OCCUPANCY_NORMAL_OFFSET = -0.08  # along the proximal link's y, i.e. along the palm normal -y
PREGRASP_FINGER = (0.0, 0.2, 0.2, 0.1)  # J3 (abduction), J2, J1, J0: slightly flexed
PREGRASP_THUMB = {"THJ4": 0.5, "THJ3": 0.6}  # THJ4 > 0 swings the thumb toward the fingers
# Arm start (the paper starts the hand at the mean first pose of the demos, near the object):
# palm down, grasp centre S_grasp at (0, -0.10, 0.28) in the world, 10 cm behind the object
# region and above the tallest library object (25 cm), so no object is touched at reset.
PREGRASP_ARM = {"ARTx": -0.0071, "ARTy": 0.1295, "ARTz": 0.1001}


def dexrep_points(fingers: tuple[str, ...]) -> list[tuple[str, str, Vec3, str]]:
    """(name, body, offset, comment) of the DexRep hand points: joints and tips, palm last."""
    zero: Vec3 = (0.0, 0.0, 0.0)
    points = []
    for f in fingers:
        up = f.upper()
        if f == "th":
            points += [
                ("th_base", "thproximal", zero, "THJ4/THJ3 axes"),
                ("th_hub", "thmiddle", zero, "THJ2/THJ1 axes"),
                ("th_distal", "thdistal", zero, "THJ0 axis"),
                ("thtip", "thdistal", (0.0, 0.0, THUMBTIP_OFFSET), "S_thtip"),
            ]
            continue
        if f == "lf":
            points.append(("lf_metacarpal", "lfmetacarpal", zero, "LFJ4 axis"))
        points += [
            (f"{f}_knuckle", f"{f}proximal", zero, f"{up}J3/{up}J2 axes"),
            (f"{f}_middle", f"{f}middle", zero, f"{up}J1 axis"),
            (f"{f}_distal", f"{f}distal", zero, f"{up}J0 axis"),
            (f"{f}tip", f"{f}distal", (0.0, 0.0, FINGERTIP_OFFSET), f"S_{f}tip"),
        ]
    points.append(("palm_centre", "palm", GRASP_CENTRE, "S_grasp"))
    return points


def occupancy_anchor(fingers: tuple[str, ...]) -> tuple[str, Vec3]:
    """(body, grid-centre offset): the middle-finger proximal link, else the index one with
    the offset shifted so the grid sits where the middle finger's would at q = 0."""
    if "mf" in fingers:
        return "mfproximal", (0.0, OCCUPANCY_NORMAL_OFFSET, 0.0)
    shift = np.subtract(KNUCKLE_POS["mf"], KNUCKLE_POS["ff"])
    return "ffproximal", (float(shift[0]), OCCUPANCY_NORMAL_OFFSET, float(shift[2]))


# The grasp expert's geometry for hands without the ring and little fingers (GraspScript
# overrides): the grasp centre moves across the palm toward the index finger (`side`, m), so
# that the object lies between the thumb and the fingers left, and up toward the object's top
# (`palm_depth`, m), where the fewer fingertips hold it.
GRASP_SCRIPT: dict[str, dict[str, float]] = {
    "adroit_3f": {"side": -0.03, "palm_depth": 0.02, "tall_palm_depth": 0.02},
    "adroit_2f": {"side": -0.035, "palm_depth": 0.02, "tall_palm_depth": 0.02},
}


def _flow(items) -> str:
    return "[" + ", ".join(items) + "]"


THUMB_OPPOSE = {"THJ4": 0.0, "THJ3": 1.31, "THJ1": -0.52, "THJ0": -1.05}  # rad: see build_hand_yaml


def closing_directions(fingers: tuple[str, ...]) -> dict[str, float]:
    """Sign of each joint's motion when the hand closes into a power grasp."""
    closing = {f"{f.upper()}J{j}": 1.0 for f in fingers if f != "th" for j in (2, 1, 0)}
    if "th" in fingers:
        closing.update({"THJ4": 1.0, "THJ3": 1.0, "THJ1": 1.0})
    return closing


def build_hand_yaml(name: str, fingers: tuple[str, ...]) -> str:
    """The hand-description YAML text of hand `name`."""
    joints = [b.joint.name for b in bodies_for(fingers) if b.joint is not None]
    finger_names = {"ff": "index", "mf": "middle", "rf": "ring", "lf": "little", "th": "thumb"}
    tips = [p for p in dexrep_points(fingers) if p[0].endswith("tip")]
    points = dexrep_points(fingers)
    occ_body, occ_offset = occupancy_anchor(fingers)
    pregrasp = dict(PREGRASP_ARM)
    for f in fingers:
        if f != "th":
            pregrasp.update({f"{f.upper()}J{3 - i}": v for i, v in enumerate(PREGRASP_FINGER)})
    if "th" in fingers:
        pregrasp.update(PREGRASP_THUMB)
    lines = [
        f"# {name}: Adroit-style hand on a 6-DoF virtual arm "
        f"({', '.join(finger_names[f] for f in fingers)}).",
        "# GENERATED by scripts/build_adroit_model.py; do not edit by hand.",
        f"name: {name}",
        f"model: adroit/{name}.sdf",
        f"# {len(joints)} actuators; actuator i of the model drives policy_joints[i].",
        f"policy_joints: {_flow(joints)}",
        "hardware_joints: null",
        f"arm_joints: {_flow(ARM_JOINT_NAMES)}",
        "wrist_body: wrist",
        "# The palm faces -y of the palm body; centre = frame S_grasp.",
        f"palm: {{body: palm, normal: [0, -1, 0], centre: {_flow(map(_f, GRASP_CENTRE))}}}",
        "# Fingertips in finger order, thumb LAST (frames S_<name> in the model).",
        "fingertips:",
    ]
    lines += [f"  - {{name: {n}, body: {b}, offset: {_flow(map(_f, o))}}}" for n, b, o, _ in tips]
    lines += [
        f"# DexRep hand points (n = {len(points)}): per finger its joint axes and tip, "
        "thumb after the fingers, palm centre last.",
        "dexrep_points:",
    ]
    lines += [f"  - {{name: {n}, body: {b}, offset: {_flow(map(_f, o))}}}  # {c}"
              for n, b, o, c in points]
    lines += [
        "# Occupancy grid (20 cm cube, 10^3 voxels) attached to the middle finger's proximal",
        "# link (index finger's when there is no middle finger, shifted to the same place).",
        f"# Its centre is {-OCCUPANCY_NORMAL_OFFSET * 100:.0f} cm along the palm normal (-y) "
        "from the knuckle: the cube then spans",
        "# y = -0.18..+0.02 m, i.e. from just behind the back of the hand (palm half-thickness",
        "# 1.1 cm) to 18 cm in front of the palm, and z = -0.1..+0.1 m around the knuckles,",
        "# covering the palm, the extended fingers and S_grasp (5 cm in front of the palm).",
        f"occupancy: {{body: {occ_body}, offset: {_flow(map(_f, occ_offset))}, "
        "size: 0.2, resolution: 10}",
        "# Open hand, fingers slightly flexed, thumb opposed (THJ4 > 0 turns it toward the",
        "# fingers, THJ3 flexes it under the palm). Unnamed joints are 0.",
        "pregrasp: {" + ", ".join(f"{k}: {_f(v)}" for k, v in pregrasp.items()) + "}",
        "# Closing directions (scripted power grasp): finger flexion J2..J0 and the thumb's",
        "# opposition (THJ4) and flexion (THJ3, THJ1) are positive.",
        "closing: {" + ", ".join(f"{k}: {_f(v)}" for k, v in closing_directions(fingers).items()) + "}",
    ]
    if "th" in fingers:
        lines += [
            "# Named closed poses the expert may choose per object (GraspScript.closed_pose): 'oppose'",
            "# swings the thumb tip under the palm against the object's near side instead of across",
            "# the palm (found by simulated grasp trials, `dexdrake expert choose`).",
            "grasp_poses: {oppose: {" + ", ".join(f"{k}: {_f(v)}" for k, v in THUMB_OPPOSE.items()) + "}}",
        ]
    if name in GRASP_SCRIPT:
        lines += [
            "# The grasp expert's geometry (GraspScript): the grasp centre toward the index finger and",
            "# the object's top, between the thumb and the fingers left.",
            "grasp_script: {" + ", ".join(f"{k}: {_f(v)}" for k, v in GRASP_SCRIPT[name].items()) + "}",
        ]
    return "\n".join(lines + [""])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default_out = Path(__file__).resolve().parents[1] / "models" / "adroit"
    parser.add_argument("--out", type=Path, default=default_out, help="output folder")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for name, fingers in VARIANTS.items():
        path = args.out / f"{name}.sdf"
        for path, text in ((args.out / f"{name}.sdf", build_sdf(name, fingers)),
                           (args.out / f"{name}.hand.yaml", build_hand_yaml(name, fingers))):
            path.write_text(text)
            print(f"wrote {path}")


if __name__ == "__main__":
    main()
