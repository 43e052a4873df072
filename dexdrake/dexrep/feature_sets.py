"""Named observation sets (the paper's baselines and ablations) and the FeatureExtractor.

Each set is an ordered tuple of encoder groups; the learning code builds one encoder per
group. The hand state is always the first group. Group contents (n hand points, J joints):
  hand      f_h: joints, points rel. wrist, wrist position, wrist rotation (J + 3n + 9)
  hand2obj  world positions of the n hand points minus the object position (3n), as DAPG
  pglo      global 1024-d PointNet feature of the object + object pose (position 3,
            R[:,0], R[:,1]) = 1033, as ILAD
  local_geo f_l (64n)
  surf      f_s (4n)
  occ_surf  [f_o, f_s] (1000 + 4n)
  hand_vel  joint velocities (J): not in the paper; the grasp expert's labels depend on whether
            the arm has stopped and the fingers have settled, which positions alone cannot show
Adroit DexRep -> {"hand": 105, "occ_surf": 1088, "local_geo": 1408}.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from dexdrake.dexrep import features as F
from dexdrake.dexrep.geometry import ClosestPoints, ObjectGeometry
from dexdrake.dexrep.occupancy import OCCUPANCY_LEVELS, fast_occupancy
from dexdrake.dexrep.pointnet import GLOBAL_DIM, LOCAL_DIM
from dexdrake.dexrep.scenegraph import scenegraph_closest_points, scenegraph_occupancy
from dexdrake.errors import DexdrakeError, UnknownNameError
from dexdrake.hands.description import HandDescription

FEATURE_SETS: dict[str, tuple[str, ...]] = {
    "Hand2obj": ("hand", "hand2obj"),
    "pGlo": ("hand", "pglo"),
    "Loc-Geo": ("hand", "local_geo"),
    "Surf": ("hand", "surf"),
    "Occ+Surf": ("hand", "occ_surf"),
    "Occ+Surf+pGlo": ("hand", "occ_surf", "pglo"),
    "DexRep+pGlo": ("hand", "occ_surf", "local_geo", "pglo"),
    "DexRep": ("hand", "occ_surf", "local_geo"),
    "DexRep+Vel": ("hand", "occ_surf", "local_geo", "hand_vel"),
}
FeaturePath = Literal["fast", "scenegraph"]  # see FeatureExtractor
PATHS: tuple[str, ...] = get_args(FeaturePath)


def feature_set_names() -> list[str]:
    return list(FEATURE_SETS)


def observation_blocks(hand: HandDescription, feature_set: str = "DexRep") -> dict[str, int]:
    """Ordered {group: size} of `feature_set` for `hand`."""
    if feature_set not in FEATURE_SETS:
        raise UnknownNameError("feature set", feature_set, FEATURE_SETS)
    n = len(hand.dexrep_points)
    voxels = hand.occupancy.resolution ** 3
    sizes = {
        "hand": F.hand_state_size(len(hand.policy_joints), n),
        "hand2obj": 3 * n,
        "pglo": GLOBAL_DIM + 9,
        "local_geo": LOCAL_DIM * n,
        "surf": 4 * n,
        "occ_surf": voxels + 4 * n,
        "hand_vel": len(hand.policy_joints),
    }
    return {g: sizes[g] for g in FEATURE_SETS[feature_set]}


@dataclass(frozen=True)
class DexRepSnapshot:
    """World-frame hand points (n, 3), grid pose X_WG (4x4), occupancy (r^3,) and closest
    object points (signed distances, points, outward normals)."""

    hand_points: np.ndarray
    X_WG: np.ndarray
    occupancy: np.ndarray
    closest: ClosestPoints


class FeatureExtractor:
    """Computes one feature set from a plant context and the object pose.

    path "fast" uses the object's cached structures; "scenegraph" uses
    QueryObject.ComputeSignedDistanceToPoint on the object's distance geometry (closest
    points and occupancy; local-geo still reads the cached per-point features).
    Per step it reads each needed body pose once (hand points, wrist, grid anchor) and
    runs every feature as a few vectorised calls.
    """

    def __init__(self, hand: HandDescription, plant, hand_instance, geometry: ObjectGeometry,
                 feature_set: str = "DexRep", path: FeaturePath = "fast", distance_geometry_id=None,
                 surface_clip: float = F.SURFACE_CLIP):
        if path not in PATHS:
            raise UnknownNameError("feature path", path, PATHS)
        if path == "scenegraph" and distance_geometry_id is None:
            raise DexdrakeError("the scenegraph path needs the object's distance_geometry_id")
        self.hand, self.plant, self.geometry = hand, plant, geometry
        self.feature_set, self.path = feature_set, path
        self.distance_geometry_id = distance_geometry_id
        self.surface_clip = surface_clip
        self.observation_blocks = observation_blocks(hand, feature_set)
        self.size = sum(self.observation_blocks.values())
        self._groups = FEATURE_SETS[feature_set]
        self._needs_closest = bool({"surf", "occ_surf", "local_geo"} & set(self._groups))
        if path == "fast" and self._needs_closest:
            geometry.prepare_queries()  # built once per geometry, here rather than in the first step
        names = list(dict.fromkeys([p.body for p in hand.dexrep_points] + [hand.wrist_body, hand.occupancy.body]))
        self._bodies = [plant.GetBodyByName(name, hand_instance) for name in names]
        self._point_body = np.array([names.index(p.body) for p in hand.dexrep_points])
        self._point_offset = np.array([[*p.offset, 1.0] for p in hand.dexrep_points], dtype=float)
        self._wrist = names.index(hand.wrist_body)
        self._anchor = names.index(hand.occupancy.body)
        self._anchor_offset = np.array([*hand.occupancy.offset, 1.0], dtype=float)
        occ = hand.occupancy
        self._occupancy = fast_occupancy(occ.size, occ.resolution, OCCUPANCY_LEVELS)
        joints = [plant.GetJointByName(j, hand_instance) for j in hand.policy_joints]
        self._q_index = np.array([j.position_start() for j in joints])
        self._v_index = np.array([j.velocity_start() for j in joints])

    def _body_poses(self, plant_context) -> np.ndarray:
        """(B, 3, 4) world poses [R | p] of the bodies the features read."""
        return np.array([self.plant.EvalBodyPoseInWorld(plant_context, b).GetAsMatrix34() for b in self._bodies])

    def hand_points(self, plant_context) -> np.ndarray:
        """World positions (n, 3) of the hand's DexRep points."""
        return self._points_from(self._body_poses(plant_context))

    def _points_from(self, poses: np.ndarray) -> np.ndarray:
        return np.einsum("pij,pj->pi", poses[self._point_body], self._point_offset)

    def grid_pose(self, plant_context) -> np.ndarray:
        """X_WG: the anchor body's axes, origin at body pose * offset."""
        return self._grid_from(self._body_poses(plant_context))

    def _grid_from(self, poses: np.ndarray) -> np.ndarray:
        X = F.EYE4.copy()
        X[:3, :3] = poses[self._anchor, :, :3]
        X[:3, 3] = poses[self._anchor] @ self._anchor_offset
        return X

    def snapshot(self, plant_context, X_WO, query_object=None) -> DexRepSnapshot:
        """The geometric parts of DexRep in the world frame, for viewers and debugging."""
        X_WO = F.as_matrix(X_WO)
        poses = self._body_poses(plant_context)
        p_W = self._points_from(poses)
        cp = self._closest_points(p_W, X_WO, query_object)
        R, t = X_WO[:3, :3], X_WO[:3, 3]
        return DexRepSnapshot(p_W, self._grid_from(poses), self._occupancy_of(poses, X_WO, query_object),
                              ClosestPoints(cp.distance, cp.points @ R.T + t, cp.normals @ R.T))

    def __call__(self, plant_context, X_WO, query_object=None) -> np.ndarray:
        """The feature vector (blocks concatenated in `observation_blocks` order)."""
        return self.with_closest(plant_context, X_WO, query_object)[0]

    def with_closest(self, plant_context, X_WO, query_object=None) -> tuple[np.ndarray, ClosestPoints | None]:
        """(the feature vector, the closest object points of the hand's DexRep points in the
        object frame, or None when the feature set needs none): one query serves the features
        and any caller that wants distances of those points (the reward's fingertips)."""
        if self.path == "scenegraph" and query_object is None:
            raise DexdrakeError("the scenegraph path needs a query_object")
        X_WO = F.as_matrix(X_WO)
        poses = self._body_poses(plant_context)
        p_W = self._points_from(poses)
        cp_O = self._closest_points(p_W, X_WO, query_object) if self._needs_closest else None
        parts = []
        for g in self._groups:
            if g == "hand":
                q = self.plant.GetPositions(plant_context)[self._q_index]
                X_WH = poses[self._wrist]
                parts.append(F.hand_state_unchecked(q, p_W, X_WH[:, :3], X_WH[:, 3]))
            elif g == "hand_vel":
                parts.append(self.plant.GetVelocities(plant_context)[self._v_index])
            elif g == "hand2obj":
                parts.append((p_W - X_WO[:3, 3]).ravel())
            elif g == "pglo":
                parts.append(self.geometry.global_feature)
                parts.append(F.pose_6d(X_WO))
            elif g == "local_geo":
                parts.append(self.geometry.local_features[self.geometry.nearest_samples(cp_O.points)].ravel())
            elif g == "surf":
                parts.append(self._surface(cp_O, X_WO))
            elif g == "occ_surf":
                parts.append(self._occupancy_of(poses, X_WO, query_object))
                parts.append(self._surface(cp_O, X_WO))
        out = np.concatenate(parts, dtype=np.float64)
        if not np.isfinite(out.sum()):
            raise DexdrakeError("feature vector has NaN/Inf (check the object pose and hand state)")
        return out, cp_O

    def _closest_points(self, p_W: np.ndarray, X_WO: np.ndarray, query_object) -> ClosestPoints:
        """Closest object points in the object frame (normals too)."""
        R, t = X_WO[:3, :3], X_WO[:3, 3]
        if self.path == "fast":
            return self.geometry.closest_points((p_W - t) @ R)
        cp = scenegraph_closest_points(query_object, self.distance_geometry_id, p_W)
        return ClosestPoints(cp.distance, (cp.points - t) @ R, cp.normals @ R)

    def _surface(self, cp_O: ClosestPoints, X_WO: np.ndarray) -> np.ndarray:
        d = np.minimum(np.maximum(cp_O.distance, 0.0), self.surface_clip)
        return np.column_stack([d, cp_O.normals @ X_WO[:3, :3].T]).ravel()

    def _occupancy_of(self, poses: np.ndarray, X_WO: np.ndarray, query_object) -> np.ndarray:
        occ = self.hand.occupancy
        X_WG = self._grid_from(poses)
        if self.path == "fast":
            return self._occupancy(F.rigid_inverse(X_WO) @ X_WG, self.geometry)
        return scenegraph_occupancy(query_object, self.distance_geometry_id, X_WG, occ.size, occ.resolution)
