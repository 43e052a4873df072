"""DexRep features as pure numpy functions of hand points, grid pose, object pose and geometry.

Poses are 4x4 homogeneous matrices or pydrake RigidTransforms: X_WG (occupancy grid
frame G in world W), X_WO (object frame O), X_WH (hand root / wrist frame H). Hand points
are world positions, shape (n, 3).

Occupancy f_o (resolution^3, default 1000): see dexdrake.dexrep.occupancy.

Surface f_s (4n): per point [d, nx, ny, nz] with d = min(distance to the surface, clip)
(0 for points inside or on the object) and n the outward unit normal at the closest
surface point, in the world frame (or in the hand frame H when R_WH is given). The paper's
definition is the default: no scaling (the public code multiplies d by 10; `scale` does).

Local-Geo f_l (64n): per point, the cached PointNet per-point feature of the sampled surface
point nearest to its closest surface point.

Hand state f_h: [q (joints, policy order), positions of the n hand points relative to the
wrist expressed in the wrist frame (3n, point-major), wrist position in world (3), first two
columns of R_WH (6: R[:,0] then R[:,1])]. Adroit: 30 + 66 + 3 + 6 = 105; Allegro on the Z1:
22 + 60 + 3 + 6 = 91.
"""

from __future__ import annotations

import numpy as np

from dexdrake.dexrep.geometry import ClosestPoints, ObjectGeometry
from dexdrake.dexrep.occupancy import OCCUPANCY_LEVELS, fast_occupancy
from dexdrake.errors import DexdrakeError

SURFACE_CLIP = 0.20  # m
EYE4 = np.eye(4)  # copied where a pose is built (cheaper than np.eye); never written to


def as_matrix(X) -> np.ndarray:
    """A 4x4 float array from a 4x4 array-like or anything with GetAsMatrix4()."""
    M = X.GetAsMatrix4() if hasattr(X, "GetAsMatrix4") else np.asarray(X, dtype=np.float64)
    if M.shape != (4, 4) or not np.isfinite(M).all():
        raise DexdrakeError(f"expected a finite 4x4 pose, got shape {M.shape}")
    return M


def _points(p: np.ndarray, label: str = "points") -> np.ndarray:
    p = np.asarray(p, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
        raise DexdrakeError(f"{label} must be a finite (n, 3) array, got shape {p.shape}")
    return p


def rigid_inverse(X: np.ndarray) -> np.ndarray:
    """The inverse of a 4x4 rigid transform."""
    out = EYE4.copy()
    out[:3, :3] = X[:3, :3].T
    out[:3, 3] = -(X[:3, 3] @ X[:3, :3])
    return out


def occupancy(X_WG, X_WO, geometry: ObjectGeometry, size: float = 0.2, resolution: int = 10,
              levels: int = OCCUPANCY_LEVELS) -> np.ndarray:
    """Fast-path occupancy f_o (resolution^3,) from the object's cached signed-distance grid."""
    X_OG = rigid_inverse(as_matrix(X_WO)) @ as_matrix(X_WG)
    return fast_occupancy(size, resolution, levels)(X_OG, geometry)


def closest_points(p_W: np.ndarray, X_WO, geometry: ObjectGeometry) -> ClosestPoints:
    """Fast-path closest object points to world points, returned in the world frame."""
    p_W = _points(p_W, "hand points")
    X = as_matrix(X_WO)
    R, t = X[:3, :3], X[:3, 3]
    cp = geometry.closest_points((p_W - t) @ R)
    return ClosestPoints(cp.distance, cp.points @ R.T + t, cp.normals @ R.T)


def surface_from_closest(cp: ClosestPoints, clip: float = SURFACE_CLIP, R_WH: np.ndarray | None = None,
                         scale: float = 1.0) -> np.ndarray:
    """f_s (4n,) from world-frame closest points; normals in the hand frame if R_WH is given."""
    d = np.minimum(np.maximum(cp.distance, 0.0), clip) * scale
    n = cp.normals if R_WH is None else cp.normals @ np.asarray(R_WH)
    return np.column_stack([d, n]).ravel()


def local_geo_from_closest(cp: ClosestPoints, X_WO, geometry: ObjectGeometry) -> np.ndarray:
    """f_l (64n,): cached per-point features of the samples nearest to the closest points."""
    X = as_matrix(X_WO)
    c_O = (cp.points - X[:3, 3]) @ X[:3, :3]
    return geometry.local_features[geometry.nearest_samples(c_O)].astype(np.float64).ravel()


def hand_state(q: np.ndarray, p_W: np.ndarray, X_WH) -> np.ndarray:
    """f_h = [q, R_WH^T (p_j - p_WH) for each point, p_WH, R_WH[:,0], R_WH[:,1]]."""
    q = np.asarray(q, dtype=np.float64).ravel()
    if not np.all(np.isfinite(q)):
        raise DexdrakeError("hand_state: joint positions contain NaN or Inf")
    X = as_matrix(X_WH)
    return hand_state_unchecked(q, _points(p_W, "hand points"), X[:3, :3], X[:3, 3])


def hand_state_unchecked(q: np.ndarray, p_W: np.ndarray, R_WH: np.ndarray, p_WH: np.ndarray) -> np.ndarray:
    """`hand_state` without input checks, for per-step callers that check their output."""
    return np.concatenate([q, ((p_W - p_WH) @ R_WH).ravel(), p_WH, R_WH[:, :2].T.ravel()])


def hand_state_size(num_joints: int, num_points: int) -> int:
    return num_joints + 3 * num_points + 9


def pose_6d(X) -> np.ndarray:
    """[position (3), R[:,0], R[:,1]] of a pose (9,)."""
    X = as_matrix(X)
    return np.concatenate([X[:3, 3], X[:3, 0], X[:3, 1]])
