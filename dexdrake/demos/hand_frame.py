"""The canonical hand frame: where every keypoint input is put before retargeting.

Canonical hand frame of 21 keypoints (MediaPipe order) of a RIGHT hand, the operator frame
of `human_hand` and of many retargeters:

    origin  the wrist keypoint (0)
    z       wrist -> middle-finger MCP (9): the finger direction
    y       little-finger MCP (17) -> index MCP (5), made orthogonal to z: towards the thumb
    x       y x z: the palm normal, pointing out of the palm

A left hand is made a right hand by mirroring it first (`mirror`). A sequence is put into
one frame for all its frames (`sequence_frame`: the mean wrist position and the mean palm
orientation), so the hand's own motion is kept; a fixed-wrist retarget instead puts each
frame into its own hand frame (`to_hand_frame` per frame), keeping the fingers only.
The retargeter then places the canonical frame on the robot hand's own frame at its
reference pose (`Retargeter.home`), so retargeting starts inside the arm's reach whatever
frame the capture used.
"""

from __future__ import annotations

import numpy as np

WRIST, INDEX_MCP, MIDDLE_MCP, LITTLE_MCP = 0, 5, 9, 17


def hand_frames(keypoints: np.ndarray, little: int = LITTLE_MCP
                ) -> tuple[np.ndarray, np.ndarray]:
    """(R (..., 3, 3) with columns x, y, z of the hand frame, origin (..., 3)) of
    (..., 21, 3) keypoints. `little`: the keypoint that stands for the little-finger MCP
    (e.g. the ring MCP, 13, for a four-fingered robot hand)."""
    kp = np.asarray(keypoints, float)
    z = _unit(kp[..., MIDDLE_MCP, :] - kp[..., WRIST, :])
    y = kp[..., INDEX_MCP, :] - kp[..., little, :]
    y = _unit(y - z * np.sum(y * z, axis=-1, keepdims=True))
    return np.stack([np.cross(y, z), y, z], axis=-1), kp[..., WRIST, :]


def to_hand_frame(keypoints: np.ndarray, R: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Keypoints (..., 21, 3) expressed in the frame (R, origin) (broadcast over frames)."""
    kp = np.asarray(keypoints, float)
    return (kp - np.asarray(origin)[..., None, :]) @ R


def sequence_frame(keypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One frame for a (T, 21, 3) sequence: the chordal mean of its hand orientations and
    the mean wrist position."""
    R, origin = hand_frames(keypoints)
    u, _, vt = np.linalg.svd(R.sum(axis=0))
    mean = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return mean, origin.mean(axis=0)


def canonical(keypoints: np.ndarray, per_frame: bool = False) -> np.ndarray:
    """A (T, 21, 3) right-hand sequence in the canonical hand frame: one frame for the whole
    sequence (`sequence_frame`), or each frame in its own (`per_frame`, wrist fixed)."""
    kp = np.asarray(keypoints, float)
    R, origin = hand_frames(kp) if per_frame else sequence_frame(kp)
    return to_hand_frame(kp, R, origin)


def mirror(keypoints: np.ndarray) -> np.ndarray:
    """A left hand as a right hand: the keypoints reflected through their x = 0 plane."""
    return np.asarray(keypoints, float) * np.array([-1.0, 1.0, 1.0])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
