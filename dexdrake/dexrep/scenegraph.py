"""The SceneGraph path: DexRep's distance queries answered by QueryObject.

Closest points come from `ComputeSignedDistanceToPoint(p_WQ, inf)` filtered to the object's
distance geometry. Occupancy uses the same query at voxel centres (threshold = the voxel
half-diagonal: a farther object leaves the voxel empty) and at the refinement sub-cubes,
with the same rule as the fast path (see features.py). One query per point: slow, a
reference for the fast path.
"""

from __future__ import annotations

import numpy as np

from dexdrake.dexrep.occupancy import OCCUPANCY_LEVELS, occupancy_in_frame
from dexdrake.dexrep.geometry import FAR, ClosestPoints
from dexdrake.errors import DexdrakeError


def _object_result(query_object, geometry_id, p_W: np.ndarray, threshold: float):
    for r in query_object.ComputeSignedDistanceToPoint(p_W, threshold):
        if r.id_G == geometry_id:
            return r
    return None


def scenegraph_closest_points(query_object, geometry_id, p_W: np.ndarray) -> ClosestPoints:
    """World-frame closest points, signed distances and outward normals on the object."""
    p_W = np.asarray(p_W, dtype=np.float64).reshape(-1, 3)
    X_WG = query_object.GetPoseInWorld(geometry_id)
    dist, pts, normals = np.empty(len(p_W)), np.empty((len(p_W), 3)), np.empty((len(p_W), 3))
    for i, p in enumerate(p_W):
        r = _object_result(query_object, geometry_id, p, np.inf)
        if r is None:
            raise DexdrakeError(f"geometry {geometry_id} has no proximity role or is not in the scene")
        dist[i] = r.distance
        pts[i] = X_WG.multiply(np.asarray(r.p_GN).ravel())
        g = np.asarray(r.grad_W).ravel()
        normals[i] = g / max(np.linalg.norm(g), 1e-12)
    return ClosestPoints(dist, pts, normals)


def scenegraph_signed_distance(query_object, geometry_id, threshold: float):
    """sd_fn(points_W, with_gradient) for occupancy_in_frame; FAR beyond `threshold`."""

    def sd_fn(p_W: np.ndarray, with_gradient: bool = False):
        sd, grad = np.full(len(p_W), FAR), np.zeros((len(p_W), 3))
        for i, p in enumerate(p_W):
            r = _object_result(query_object, geometry_id, p, threshold)
            if r is not None:
                sd[i] = r.distance
                grad[i] = np.asarray(r.grad_W).ravel()
        return (sd, grad) if with_gradient else sd

    return sd_fn


def scenegraph_occupancy(query_object, geometry_id, X_WG, size: float = 0.2, resolution: int = 10,
                         levels: int = OCCUPANCY_LEVELS) -> np.ndarray:
    """Occupancy f_o from SceneGraph signed distances at voxel centres and sub-cubes."""
    threshold = size / resolution * np.sqrt(3) / 2 * 1.01
    return occupancy_in_frame(scenegraph_signed_distance(query_object, geometry_id, threshold),
                              X_WG, size, resolution, levels)
