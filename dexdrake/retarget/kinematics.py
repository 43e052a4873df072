"""Robot forward kinematics as a CasADi expression graph, extracted once from a Drake model.

`extract_tree` reads a model file with pydrake's MultibodyPlant and records, for every
body, the joint that connects it to its parent: the pose of the joint's frame on the parent
(X_PF), the pose of its frame on the child (X_CM), its type (revolute, prismatic or weld) and
axis. `symbolic_points` turns that tree into CasADi SX expressions for chosen body points as
functions of the joint vector (in a caller-given joint order); joints outside that order are
held at their default positions.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from dexdrake.errors import DexdrakeError

WORLD = "world"


@dataclass(frozen=True)
class TreeJoint:
    """The joint that attaches `child` to `parent` (both body names)."""

    name: str
    kind: str  # "revolute" | "prismatic" | "weld"
    parent: str
    child: str
    X_PF: np.ndarray  # 4x4, joint frame F in the parent body frame
    X_CM: np.ndarray  # 4x4, joint frame M in the child body frame
    axis: np.ndarray  # unit axis in F (= M) for revolute/prismatic; zeros for weld
    X_FM: np.ndarray  # 4x4 fixed F->M transform for weld joints; identity otherwise
    default: float  # position used when the joint is not a decision variable


@dataclass(frozen=True)
class KinematicTree:
    joints: dict[str, TreeJoint]  # keyed by child body name


def _h(X) -> np.ndarray:
    return np.asarray(X.GetAsMatrix4())


def extract_tree(model_path: str | Path) -> KinematicTree:
    """Every body's parent joint in `model_path` (SDF/URDF), read with pydrake.

    Raises DexdrakeError for joint types other than revolute, prismatic and weld, and for
    bodies that are not connected to the world by joints (floating bases).
    """
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    plant = MultibodyPlant(0.0)
    Parser(plant).AddModels(str(model_path))
    plant.Finalize()
    joints: dict[str, TreeJoint] = {}
    for index in plant.GetJointIndices():
        j = plant.get_joint(index)
        kind = j.type_name()
        if kind not in ("revolute", "prismatic", "weld"):
            raise DexdrakeError(
                f"{model_path}: joint {j.name()!r} has unsupported type {kind!r} "
                "(supported: revolute, prismatic, weld; anchor floating bases with a weld)"
            )
        axis = np.zeros(3)
        X_FM = np.eye(4)
        default = 0.0
        if kind == "revolute":
            axis = np.asarray(j.revolute_axis(), float)
            default = float(j.default_positions()[0])
        elif kind == "prismatic":
            axis = np.asarray(j.translation_axis(), float)
            default = float(j.default_positions()[0])
        else:
            X_FM = _h(j.X_FM())
        parent = j.parent_body().name() if j.parent_body().index() != plant.world_body().index() \
            else WORLD
        child = j.child_body().name()
        if child in joints:
            raise DexdrakeError(f"{model_path}: body {child!r} has two parent joints")
        joints[child] = TreeJoint(
            name=j.name(), kind=kind, parent=parent, child=child,
            X_PF=_h(j.frame_on_parent().GetFixedPoseInBodyFrame()),
            X_CM=_h(j.frame_on_child().GetFixedPoseInBodyFrame()),
            axis=axis / (np.linalg.norm(axis) or 1.0), X_FM=X_FM, default=default,
        )
    return KinematicTree(joints)


def _rot(axis: np.ndarray, theta) -> ca.SX:
    """Rodrigues' rotation about a fixed unit axis (CasADi SX)."""
    K = ca.SX(np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]],
                        [-axis[1], axis[0], 0]]))
    return ca.SX.eye(3) + ca.sin(theta) * K + (1 - ca.cos(theta)) * (K @ K)


def _compose(R1, p1, R2, p2):
    return R1 @ R2, p1 + R1 @ p2


def symbolic_points(
    tree: KinematicTree,
    joint_order: list[str] | tuple[str, ...],
    points: list[tuple[str, np.ndarray]],
) -> tuple[ca.SX, ca.SX]:
    """(q, P): q an SX column of len(joint_order), P an SX (len(points) x 3) of world positions.

    `points` are (body name, offset in the body frame). Body poses are shared between points,
    so each joint transform appears once in the graph.
    """
    q = ca.SX.sym("q", len(joint_order))
    index = {n: i for i, n in enumerate(joint_order)}
    movable = {j.name for j in tree.joints.values() if j.kind != "weld"}
    unknown = [n for n in joint_order if n not in movable]
    if unknown:
        raise DexdrakeError(f"joints {unknown} are not revolute/prismatic joints of the model")
    cache: dict[str, tuple] = {WORLD: (ca.SX.eye(3), ca.SX.zeros(3))}

    def pose(body: str):
        if body in cache:
            return cache[body]
        if body not in tree.joints:
            raise DexdrakeError(f"body {body!r} is not in the model")
        j = tree.joints[body]
        R, p = pose(j.parent)
        R, p = _compose(R, p, ca.SX(j.X_PF[:3, :3]), ca.SX(j.X_PF[:3, 3]))
        val = q[index[j.name]] if j.name in index else j.default
        if j.kind == "revolute":
            R = R @ _rot(j.axis, val)
        elif j.kind == "prismatic":
            p = p + R @ (ca.SX(j.axis) * val)
        else:
            R, p = _compose(R, p, ca.SX(j.X_FM[:3, :3]), ca.SX(j.X_FM[:3, 3]))
        X_MC = np.linalg.inv(j.X_CM)
        R, p = _compose(R, p, ca.SX(X_MC[:3, :3]), ca.SX(X_MC[:3, 3]))
        cache[body] = (R, p)
        return R, p

    rows = []
    for body, offset in points:
        R, p = pose(body)
        rows.append((p + R @ ca.SX(np.asarray(offset, float))).T)
    return q, ca.vertcat(*rows)


def fk_function(
    model_path: str | Path,
    joint_order: list[str] | tuple[str, ...],
    points: list[tuple[str, np.ndarray]],
) -> ca.Function:
    """A CasADi Function q -> (len(points) x 3) world positions of the body points."""
    q, P = symbolic_points(extract_tree(model_path), joint_order, points)
    return ca.Function("fk_points", [q], [P], ["q"], ["points"])
