"""DexRep features as pure numpy functions of hand points, grid pose, object pose and geometry.

Poses are 4x4 homogeneous matrices or pydrake RigidTransforms: X_WG (occupancy grid
frame G in world W), X_WO (object frame O), X_WH (hand root / wrist frame H). Hand points
are world positions, shape (n, 3).

Occupancy f_o (resolution^3, default 1000): voxel i = 100*ix + 10*iy + iz (x-major in the
grid frame; voxel centres at (i + 0.5) * size/res - size/2 along each grid axis) is 1 when
the voxel cube intersects the solid object, else 0. Rule, given a signed distance sd
(negative inside) at a cube centre with half-diagonal r: sd <= 0 -> occupied; sd > r ->
empty; otherwise the cube is split into 8 children and the rule repeats (`levels` times);
at the last level a cube is occupied iff sd <= (edge/2) * |n|_1 with n the unit sd
gradient, which is exact when the surface is planar across the cube.

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

from collections.abc import Callable

import numpy as np

from dexdrake.dexrep.geometry import ClosestPoints, ObjectGeometry
from dexdrake.errors import DexdrakeError

SURFACE_CLIP = 0.20  # m
OCCUPANCY_LEVELS = 1  # refinement levels before the planar rule

# sd_fn(points (m, 3) in frame F, with_gradient) -> sd (m,) or (sd, grad (m, 3))
SignedDistanceFn = Callable[..., object]

_CHILD_SIGNS = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)], dtype=float) - 0.5


def as_matrix(X) -> np.ndarray:
    """A 4x4 float array from a 4x4 array-like or anything with GetAsMatrix4()."""
    M = X.GetAsMatrix4() if hasattr(X, "GetAsMatrix4") else np.asarray(X, dtype=np.float64)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise DexdrakeError(f"expected a finite 4x4 pose, got shape {M.shape}")
    return M


def _points(p: np.ndarray, label: str = "points") -> np.ndarray:
    p = np.asarray(p, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
        raise DexdrakeError(f"{label} must be a finite (n, 3) array, got shape {p.shape}")
    return p


def voxel_centres(size: float = 0.2, resolution: int = 10) -> np.ndarray:
    """(resolution^3, 3) voxel centres in the grid frame, x-major (i = r*r*ix + r*iy + iz)."""
    if size <= 0 or resolution < 1:
        raise DexdrakeError(f"bad occupancy grid: size {size}, resolution {resolution}")
    h = size / resolution
    axis = (np.arange(resolution) + 0.5) * h - size / 2
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)


def occupancy_in_frame(sd_fn: SignedDistanceFn, X_FG: np.ndarray, size: float = 0.2,
                       resolution: int = 10, levels: int = OCCUPANCY_LEVELS,
                       coarse_fn: SignedDistanceFn | None = None) -> np.ndarray:
    """Occupancy of the grid at X_FG given a signed-distance function in frame F.

    `coarse_fn(points)` may return sd with an error bound already subtracted/added as a pair
    (lower, upper) to decide most voxels cheaply; undecided ones use `sd_fn`.
    """
    X_FG = as_matrix(X_FG)
    R, t = X_FG[:3, :3], X_FG[:3, 3]
    edge = size / resolution
    centres = voxel_centres(size, resolution) @ R.T + t
    occ = np.zeros(len(centres), dtype=bool)
    idx = np.arange(len(centres))
    half_diag = edge * np.sqrt(3) / 2
    if coarse_fn is not None:
        lower, upper = coarse_fn(centres)
        occ[upper <= 0.0] = True
        keep = (upper > 0.0) & (lower <= half_diag)
        idx, centres = idx[keep], centres[keep]
    owner = idx
    for level in range(levels + 1):
        if len(centres) == 0:
            break
        half_diag = edge * np.sqrt(3) / 2
        last = level == levels
        if last:
            sd, grad = sd_fn(centres, True)
            norm = np.linalg.norm(grad, axis=1)
            l1 = np.abs(grad).sum(axis=1) / np.where(norm > 0, norm, 1.0)
            hit = sd <= np.where(norm > 0, 0.5 * edge * l1, 0.0)
        else:
            sd = sd_fn(centres, False)
            hit = sd <= 0.0
        occ[owner[hit]] = True
        if last:
            break
        open_ = ~hit & (sd <= half_diag) & ~occ[owner]
        edge /= 2
        offsets = (_CHILD_SIGNS * edge) @ R.T
        centres = (centres[open_][:, None, :] + offsets).reshape(-1, 3)
        owner = np.repeat(owner[open_], 8)
    return occ.astype(np.float64)


def occupancy(X_WG, X_WO, geometry: ObjectGeometry, size: float = 0.2, resolution: int = 10,
              levels: int = OCCUPANCY_LEVELS) -> np.ndarray:
    """Fast-path occupancy f_o (resolution^3,) from the object's cached signed-distance grid."""
    X_OG = np.linalg.inv(as_matrix(X_WO)) @ as_matrix(X_WG)
    grid = geometry.sdf
    slack = grid.spacing * np.sqrt(3) / 2 + 1e-4  # nearest-node error bound

    def coarse(p):
        sd = grid.nearest_node_value(p)
        return sd - slack, sd + slack

    return occupancy_in_frame(grid.evaluate, X_OG, size, resolution, levels, coarse)


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


def surface(p_W: np.ndarray, X_WO, geometry: ObjectGeometry, clip: float = SURFACE_CLIP,
            R_WH: np.ndarray | None = None, scale: float = 1.0) -> np.ndarray:
    """Fast-path surface feature f_s (4n,), layout [d, nx, ny, nz] per point."""
    return surface_from_closest(closest_points(p_W, X_WO, geometry), clip, R_WH, scale)


def local_geo_from_closest(cp: ClosestPoints, X_WO, geometry: ObjectGeometry) -> np.ndarray:
    """f_l (64n,): cached per-point features of the samples nearest to the closest points."""
    X = as_matrix(X_WO)
    c_O = (cp.points - X[:3, 3]) @ X[:3, :3]
    return geometry.local_features[geometry.nearest_samples(c_O)].astype(np.float64).ravel()


def local_geo(p_W: np.ndarray, X_WO, geometry: ObjectGeometry) -> np.ndarray:
    """Fast-path local-geo feature f_l (64n,)."""
    return local_geo_from_closest(closest_points(p_W, X_WO, geometry), X_WO, geometry)


def hand_state(q: np.ndarray, p_W: np.ndarray, X_WH) -> np.ndarray:
    """f_h = [q, R_WH^T (p_j - p_WH) for each point, p_WH, R_WH[:,0], R_WH[:,1]]."""
    q = np.asarray(q, dtype=np.float64).ravel()
    if not np.all(np.isfinite(q)):
        raise DexdrakeError("hand_state: joint positions contain NaN or Inf")
    p_W = _points(p_W, "hand points")
    X = as_matrix(X_WH)
    R, t = X[:3, :3], X[:3, 3]
    rel = (p_W - t) @ R
    return np.concatenate([q, rel.ravel(), t, R[:, 0], R[:, 1]])


def hand_state_size(num_joints: int, num_points: int) -> int:
    return num_joints + 3 * num_points + 9


def pose_6d(X) -> np.ndarray:
    """[position (3), R[:,0], R[:,1]] of a pose (9,)."""
    X = as_matrix(X)
    return np.concatenate([X[:3, 3], X[:3, 0], X[:3, 1]])
