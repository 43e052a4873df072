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
Adroit DexRep -> {"hand": 105, "occ_surf": 1088, "local_geo": 1408}.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dexdrake.dexrep import features as F
from dexdrake.dexrep.geometry import ClosestPoints, ObjectGeometry
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
}
PATHS = ("fast", "scenegraph")


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
    }
    return {g: sizes[g] for g in FEATURE_SETS[feature_set]}


@dataclass
class _BodyPoints:
    bodies: list
    offsets: np.ndarray  # (n, 3)


class FeatureExtractor:
    """Computes one feature set from a plant context and the object pose.

    path "fast" uses the object's cached structures; "scenegraph" uses
    QueryObject.ComputeSignedDistanceToPoint on the object's distance geometry (closest
    points and occupancy; local-geo still reads the cached per-point features).
    """

    def __init__(self, hand: HandDescription, plant, hand_instance, geometry: ObjectGeometry,
                 feature_set: str = "DexRep", path: str = "fast", distance_geometry_id=None,
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
        body = lambda name: plant.GetBodyByName(name, hand_instance)  # noqa: E731
        self._points = _BodyPoints([body(p.body) for p in hand.dexrep_points],
                                   np.array([p.offset for p in hand.dexrep_points], dtype=float))
        self._wrist = body(hand.wrist_body)
        self._anchor = body(hand.occupancy.body)
        self._anchor_offset = np.array(hand.occupancy.offset, dtype=float)
        joints = [plant.GetJointByName(j, hand_instance) for j in hand.policy_joints]
        self._q_index = np.array([j.position_start() for j in joints])

    def hand_points(self, plant_context) -> np.ndarray:
        """World positions (n, 3) of the hand's DexRep points."""
        out = np.empty((len(self._points.bodies), 3))
        for i, (b, off) in enumerate(zip(self._points.bodies, self._points.offsets)):
            out[i] = self.plant.EvalBodyPoseInWorld(plant_context, b).multiply(off)
        return out

    def grid_pose(self, plant_context) -> np.ndarray:
        """X_WG: the anchor body's axes, origin at body pose * offset."""
        X = self.plant.EvalBodyPoseInWorld(plant_context, self._anchor).GetAsMatrix4()
        X[:3, 3] = X[:3, :3] @ self._anchor_offset + X[:3, 3]
        return X

    def __call__(self, plant_context, X_WO, query_object=None) -> np.ndarray:
        """The feature vector (blocks concatenated in `observation_blocks` order)."""
        if self.path == "scenegraph" and query_object is None:
            raise DexdrakeError("the scenegraph path needs a query_object")
        X_WO = F.as_matrix(X_WO)
        p_W = self.hand_points(plant_context)
        groups = FEATURE_SETS[self.feature_set]
        cp: ClosestPoints | None = None
        if {"surf", "occ_surf", "local_geo"} & set(groups):
            cp = (F.closest_points(p_W, X_WO, self.geometry) if self.path == "fast" else
                  scenegraph_closest_points(query_object, self.distance_geometry_id, p_W))
        parts = []
        for g in groups:
            if g == "hand":
                q = self.plant.GetPositions(plant_context)[self._q_index]
                X_WH = self.plant.EvalBodyPoseInWorld(plant_context, self._wrist)
                parts.append(F.hand_state(q, p_W, X_WH))
            elif g == "hand2obj":
                parts.append((p_W - X_WO[:3, 3]).ravel())
            elif g == "pglo":
                parts.append(np.concatenate([self.geometry.global_feature, F.pose_6d(X_WO)]))
            elif g == "local_geo":
                parts.append(F.local_geo_from_closest(cp, X_WO, self.geometry))
            elif g == "surf":
                parts.append(F.surface_from_closest(cp, self.surface_clip))
            elif g == "occ_surf":
                parts.append(self._occupancy(plant_context, X_WO, query_object))
                parts.append(F.surface_from_closest(cp, self.surface_clip))
        out = np.concatenate(parts)
        if not np.all(np.isfinite(out)):
            raise DexdrakeError("feature vector has NaN/Inf (check the object pose and hand state)")
        return out

    def _occupancy(self, plant_context, X_WO, query_object) -> np.ndarray:
        occ = self.hand.occupancy
        X_WG = self.grid_pose(plant_context)
        if self.path == "fast":
            return F.occupancy(X_WG, X_WO, self.geometry, occ.size, occ.resolution)
        return scenegraph_occupancy(query_object, self.distance_geometry_id, X_WG, occ.size, occ.resolution)
