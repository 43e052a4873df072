"""Hand descriptions: the single source of truth for each robot hand.

A description lives beside its model file as `models/<dir>/<name>.hand.yaml`. It names the
model, the actuated joints in policy order (and in hardware order where a real device
exists), the wrist, palm, fingertip and DexRep hand-point frames, the occupancy-grid anchor
and a default pre-grasp pose. Joint limits and PD gains are not repeated here: they are
read from the model file itself (see `joint_limits`).

Schema (YAML):
    name: adroit
    model: adroit/adroit.sdf         # relative to dexdrake.models
    policy_joints: [ARTx, ..., THJ0] # actuator i of the policy drives policy_joints[i]
    hardware_joints: [...] | null    # order on the real device's bus, if any
    arm_joints: [ARTx, ...]          # the arm part of policy_joints (prefix)
    wrist_body: wrist                # hand root: hand-state positions are relative to it
    palm: {body: palm, normal: [0, -1, 0], centre: [0.007, -0.05, 0.07]}
    fingertips: [{name: fftip, body: ffdistal, offset: [0, 0, 0.026]}, ...]
    dexrep_points: [{name: ..., body: ..., offset: [...]}, ...]
    occupancy: {body: mfproximal, offset: [0, -0.07, 0], size: 0.2, resolution: 10}
    pregrasp: {JOINT: value, ...}    # joints not named are 0 (clamped into their limits)
    closing: {JOINT: 1 | -1, ...}    # direction each finger joint moves to close the hand
    grasp_poses: {NAME: {JOINT: value}} # optional: named set-points for some joints, taken by the
                                     # open hand (GraspScript.open_pose) or replacing the
                                     # closing-direction rule (GraspScript.closed_pose), e.g. a
                                     # thumb posture or a fingertip pinch
    grasp_script: {FIELD: value}     # optional: overrides of systems.scripted_grasp.GraspScript
    grasp_expert: {FIELD: value}     # optional: overrides of systems.reactive_grasp.ReactiveRules
    palm_pose_action: {lower: [x, y, z], upper: [x, y, z], rotation: rad, step: m, step_rotation: rad}
                                     # optional (six-joint arms): the box (m, world) of the palm's
                                     # grasp centre and the rotation (rad) that actions of +-1
                                     # span when the arm is commanded by palm pose; optional step
                                     # and step_rotation: the move and turn from the measured palm
                                     # per action of 1 when commanded by palm steps
                                     # (dexdrake/hands/action_map.py)
    object_mass: {density: kg/m^3, min_kg: kg, max_kg: kg}
                                     # optional: what the objects of this hand's scenes weigh
                                     # (dexdrake/objects/mass.py); absent: the paper's 0.5 kg
    include: FILE                    # optional: a part shared by several descriptions (beside
                                     # this file, not itself a hand); this file's keys are laid
                                     # over it, mappings (pregrasp, ...) merged key by key
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np
import yaml

from dexdrake.errors import DexdrakeError, UnknownNameError
from dexdrake.objects.mass import ObjectMass
from dexdrake.paths import models_dir


@dataclass(frozen=True)
class BodyPoint:
    """A point fixed in a body: `offset` (m) expressed in the body frame."""

    name: str
    body: str
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Palm:
    body: str
    normal: tuple[float, float, float]  # unit, in the palm body frame, pointing out of the palm
    centre: tuple[float, float, float]  # grasp centre in the palm body frame


@dataclass(frozen=True)
class PalmPoseAction:
    lower: tuple[float, float, float]  # grasp-centre box (m, world frame)
    upper: tuple[float, float, float]
    rotation: float  # rad: the rotation-vector length of an action of 1
    step: float = 0.0  # m: the palm's move from its measured pose per action of 1 ("palm_step"; 0: none)
    step_rotation: float = 0.0  # rad: ... and its turn


@dataclass(frozen=True)
class OccupancyAnchor:
    body: str  # the grid moves and rotates with this body
    offset: tuple[float, float, float]  # grid centre in the body frame (m)
    size: float = 0.20  # cube edge (m)
    resolution: int = 10  # voxels per edge


@dataclass(frozen=True)
class HandDescription:
    name: str
    model: str
    policy_joints: tuple[str, ...]
    arm_joints: tuple[str, ...]
    wrist_body: str
    palm: Palm
    fingertips: tuple[BodyPoint, ...]
    dexrep_points: tuple[BodyPoint, ...]
    occupancy: OccupancyAnchor
    pregrasp: dict[str, float] = field(default_factory=dict)
    hardware_joints: tuple[str, ...] | None = None
    closing: dict[str, float] = field(default_factory=dict)
    grasp_poses: dict[str, dict[str, float]] = field(default_factory=dict)
    grasp_script: dict[str, float] = field(default_factory=dict)
    grasp_expert: dict[str, float] = field(default_factory=dict)
    palm_pose_action: PalmPoseAction | None = None
    object_mass: ObjectMass = ObjectMass()

    @property
    def model_path(self) -> Path:
        return models_dir() / self.model

    @property
    def num_actuators(self) -> int:
        return len(self.policy_joints)

    def joint_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) position limits in policy order, read from the model file."""
        return _model_limits(str(self.model_path), self.policy_joints)

    def pregrasp_vector(self) -> np.ndarray:
        """The pre-grasp pose in policy order, clamped into the joint limits."""
        lo, hi = self.joint_limits()
        q = np.array([self.pregrasp.get(j, 0.0) for j in self.policy_joints])
        return np.clip(q, lo, hi)

    def hardware_permutation(self) -> np.ndarray:
        """Index array p with q_hardware = q_policy[p] (finger joints only)."""
        if self.hardware_joints is None:
            raise DexdrakeError(f"hand {self.name!r} has no hardware joint order")
        return np.array([self.policy_joints.index(j) for j in self.hardware_joints])


def _point(d: dict) -> BodyPoint:
    return BodyPoint(d["name"], d["body"], tuple(float(x) for x in d.get("offset", (0, 0, 0))))


def _grasp_poses(d: dict, joints: tuple[str, ...]) -> dict[str, dict[str, float]]:
    poses = {str(name): {str(j): float(v) for j, v in pose.items()} for name, pose in (d.get("grasp_poses") or {}).items()}
    for name, pose in poses.items():
        unknown = sorted(set(pose) - set(joints))
        if unknown:
            raise DexdrakeError(f"hand {d['name']!r}: grasp pose {name!r} names unknown joints {unknown}")
    return poses


def _palm_pose_action(d: dict) -> PalmPoseAction | None:
    box = d.get("palm_pose_action")
    if box is None:
        return None
    lower, upper = (tuple(float(x) for x in box[k]) for k in ("lower", "upper"))
    step, step_rotation = float(box.get("step", 0.0)), float(box.get("step_rotation", 0.0))
    if (len(lower) != 3 or len(upper) != 3 or any(a >= b for a, b in zip(lower, upper)) or not box["rotation"] > 0
            or not (step >= 0 and step_rotation >= 0) or (step > 0) != (step_rotation > 0)):
        raise DexdrakeError(f"hand {d['name']!r}: palm_pose_action needs lower < upper (3 values each), "
                            f"a positive rotation and, when given, a positive step and step_rotation, got {box}")
    return PalmPoseAction(lower, upper, float(box["rotation"]), step, step_rotation)


def _object_mass(d: dict) -> ObjectMass:
    entry = d.get("object_mass") or {}
    numbers = isinstance(entry, dict) and all(isinstance(v, (int, float)) or (k == "density" and v is None)
                                              for k, v in entry.items())
    if not numbers or set(entry) - {"density", "min_kg", "max_kg"}:
        raise DexdrakeError(f"hand {d['name']!r}: object_mass takes the numbers density, min_kg and max_kg, "
                            f"got {entry!r}")
    return ObjectMass(**{k: None if v is None else float(v) for k, v in entry.items()})


def _from_dict(d: dict) -> HandDescription:
    arm = tuple(d.get("arm_joints") or ())
    policy = tuple(d["policy_joints"])
    if policy[: len(arm)] != arm:
        raise DexdrakeError(f"hand {d['name']!r}: arm_joints must be a prefix of policy_joints")
    return HandDescription(
        name=d["name"],
        model=d["model"],
        policy_joints=policy,
        arm_joints=arm,
        wrist_body=d["wrist_body"],
        palm=Palm(d["palm"]["body"], tuple(d["palm"]["normal"]), tuple(d["palm"]["centre"])),
        fingertips=tuple(_point(p) for p in d["fingertips"]),
        dexrep_points=tuple(_point(p) for p in d["dexrep_points"]),
        occupancy=OccupancyAnchor(
            d["occupancy"]["body"],
            tuple(d["occupancy"]["offset"]),
            float(d["occupancy"].get("size", 0.20)),
            int(d["occupancy"].get("resolution", 10)),
        ),
        pregrasp={k: float(v) for k, v in (d.get("pregrasp") or {}).items()},
        hardware_joints=tuple(d["hardware_joints"]) if d.get("hardware_joints") else None,
        closing={k: float(v) for k, v in (d.get("closing") or {}).items()},
        grasp_poses=_grasp_poses(d, policy),
        grasp_script=dict(d.get("grasp_script") or {}),
        grasp_expert=dict(d.get("grasp_expert") or {}),
        palm_pose_action=_palm_pose_action(d),
        object_mass=_object_mass(d),
    )


@cache
def _registry() -> dict[str, Path]:
    return {p.name.removesuffix(".hand.yaml"): p for p in models_dir().rglob("*.hand.yaml")}


def hand_names() -> list[str]:
    """Names of every shipped hand description."""
    return sorted(_registry())


@cache
def load_hand(name: str) -> HandDescription:
    """The description of hand `name`; raises UnknownNameError listing the valid names."""
    reg = _registry()
    if name not in reg:
        raise UnknownNameError("hand", name, reg)
    return _from_dict(_read(reg[name]))


def _read(path: Path) -> dict:
    """A description file as a mapping, over the shared part it names in `include`."""
    d = yaml.safe_load(path.read_text())
    if "include" not in d:
        return d
    merged = yaml.safe_load((path.parent / d.pop("include")).read_text())
    for key, value in d.items():
        base = merged.get(key)
        merged[key] = {**base, **value} if isinstance(base, dict) and isinstance(value, dict) else value
    return merged


@cache
def _model_limits(model_path: str, joints: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    plant = MultibodyPlant(0.0)
    (instance,) = Parser(plant).AddModels(model_path)
    lo, hi = [], []
    for j in joints:
        joint = plant.GetJointByName(j, instance)
        lo.append(joint.position_lower_limits()[0])
        hi.append(joint.position_upper_limits()[0])
    return np.array(lo), np.array(hi)
