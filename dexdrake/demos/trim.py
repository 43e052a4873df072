"""Object-relative processing shared by every demo source: distances, trimming, canonical frame.

The paper keeps each sequence from the frame where the hand is 10 cm from the object until
the object is lifted about 4 cm, and moves the object to a frame with no rotation, the hand
moving with it (specs/retargeting.md).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dexdrake.demos.format import DemoFormatError, HumanDemo, TrimInfo

APPROACH_DISTANCE = 0.10  # m, hand-to-object distance where a demo starts
LIFT_HEIGHT = 0.04  # m, object rise where a demo ends


def quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) w, x, y, z quaternions -> (..., 3, 3) rotation matrices."""
    q = np.asarray(q, float)
    return Rotation.from_quat(q[..., [1, 2, 3, 0]].reshape(-1, 4)).as_matrix().reshape(
        q.shape[:-1] + (3, 3))


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) w, x, y, z quaternions with w >= 0."""
    R = np.asarray(R, float)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()[:, [3, 0, 1, 2]]
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(R.shape[:-2] + (4,))


class SignedDistance:
    """Signed distance (m, negative inside) to a watertight mesh given in its object frame.

    Uses open3d's RaycastingScene (Embree), thousands of points in well under a millisecond.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        import open3d as o3d

        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                                 o3d.core.Tensor(np.asarray(faces, np.uint32)))

    def __call__(self, points_object: np.ndarray) -> np.ndarray:
        p = np.asarray(points_object, np.float32).reshape(-1, 3)
        d = self.scene.compute_signed_distance(self._o3d.core.Tensor(p)).numpy()
        return d.astype(float).reshape(np.shape(points_object)[:-1])

    def closest_points(self, points_object: np.ndarray) -> np.ndarray:
        """The closest surface point to each query point (object frame)."""
        p = np.asarray(points_object, np.float32).reshape(-1, 3)
        ans = self.scene.compute_closest_points(self._o3d.core.Tensor(p))
        return ans["points"].numpy().astype(float).reshape(np.shape(points_object))

    def closest_points_normals(self, points_object: np.ndarray
                               ) -> tuple[np.ndarray, np.ndarray]:
        """(closest surface points, outward unit normals of their triangles), object frame."""
        p = np.asarray(points_object, np.float32).reshape(-1, 3)
        ans = self.scene.compute_closest_points(self._o3d.core.Tensor(p))
        shape = np.shape(points_object)
        n = ans["primitive_normals"].numpy().astype(float)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        return ans["points"].numpy().astype(float).reshape(shape), n.reshape(shape)

    def world(self, points_world: np.ndarray, pos: np.ndarray, quat_wxyz: np.ndarray):
        """Signed distance of world points for the object at pose (pos, quat)."""
        R = quat_wxyz_to_matrix(quat_wxyz)
        return self((np.asarray(points_world) - pos) @ R)


def hand_object_distance(demo: HumanDemo, sdf: SignedDistance) -> np.ndarray:
    """(T,) smallest signed distance from any hand keypoint to the object, per frame."""
    R = quat_wxyz_to_matrix(demo.object_quat)  # (T, 3, 3)
    local = np.einsum("tkj,tji->tki", demo.keypoints - demo.object_pos[:, None], R)
    return sdf(local).min(axis=1)


def trim_demo(demo: HumanDemo, sdf: SignedDistance, approach: float = APPROACH_DISTANCE,
              lift: float = LIFT_HEIGHT) -> HumanDemo:
    """Keep frames from the first with the hand within `approach` of the object until the
    first with the object `lift` above its start height (both inclusive)."""
    d = hand_object_distance(demo, sdf)
    near = np.flatnonzero(d <= approach)
    if near.size == 0:
        raise DemoFormatError(f"hand never comes within {approach} m of the object "
                              f"(closest {d.min():.3f} m)")
    start = int(near[0])
    rise = demo.object_pos[:, 2] - demo.object_pos[start, 2]
    up = np.flatnonzero((rise >= lift) & (np.arange(demo.num_frames) > start))
    if up.size == 0:
        raise DemoFormatError(f"object is never lifted {lift} m (max {rise.max():.3f} m)")
    end = int(up[0])
    s = slice(start, end + 1)
    mano = {}
    if demo.mano_pose is not None:
        mano = dict(mano_pose=demo.mano_pose[s], mano_trans=demo.mano_trans[s],
                    mano_betas=demo.mano_betas)
    meta = demo.meta
    offset = max(meta.trim.start_frame, 0)
    meta.trim = TrimInfo(offset + start, offset + end,
                         meta.trim.source_frames or demo.num_frames,
                         f"hand {approach:.2f} m from object .. object lifted {lift:.2f} m")
    return HumanDemo(demo.keypoints[s], demo.time[s], demo.object_name, demo.object_pos[s],
                     demo.object_quat[s], meta, **mano)


def canonicalize(demo: HumanDemo, rest_height: float | None = None) -> HumanDemo:
    """Move everything rigidly so the object's first pose has no rotation and sits at
    (0, 0, rest_height) (default: its first height). MANO params are dropped if rotated,
    since they would no longer match the keypoints."""
    R0 = quat_wxyz_to_matrix(demo.object_quat[0])
    p0 = demo.object_pos[0]
    z = p0[2] if rest_height is None else rest_height
    # x_new = R0^T (x - p0) + (0, 0, z)
    shift = np.array([0.0, 0.0, z])
    kp = (demo.keypoints - p0) @ R0 + shift
    pos = (demo.object_pos - p0) @ R0 + shift
    quat = matrix_to_quat_wxyz(np.einsum("ji,tjk->tik", R0, quat_wxyz_to_matrix(
        demo.object_quat)))
    identity = np.allclose(R0, np.eye(3), atol=1e-9) and np.allclose(shift, p0)
    mano = {}
    if demo.mano_pose is not None and identity:
        mano = dict(mano_pose=demo.mano_pose, mano_trans=demo.mano_trans,
                    mano_betas=demo.mano_betas)
    return HumanDemo(kp, demo.time, demo.object_name, pos, quat, demo.meta, **mano)
