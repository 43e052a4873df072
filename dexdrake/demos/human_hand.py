"""A kinematic adult right hand that produces the 21 MediaPipe keypoints.

Hand frame (the operator frame of many retargeters): origin at the wrist keypoint, x the
palm normal (out of the palm), y from the little finger to the thumb, z from the wrist to
the fingertips. Bone lengths are adult skeletal means (specs/retargeting.md); the soft tip
is added to the distal bone so keypoints 4, 8, 12, 16, 20 lie on the skin at the tip.

Pose: a (5, 4) array of angles (rad), rows thumb, index, middle, ring, little.
    fingers: [abduction (about x, + towards the thumb), MCP flexion, PIP flexion, DIP flexion]
    thumb:   [CMC abduction (+ away from the palm plane), CMC flexion, MCP flexion, IP flexion]
Flexion is positive towards the palm (+x).
"""

from __future__ import annotations

import numpy as np

FINGERS = ("thumb", "index", "middle", "ring", "little")
# bone lengths (m) from the finger's first keypoint outwards: thumb CMC->MCP->IP->tip,
# fingers MCP->PIP->DIP->tip (distal + soft tip)
BONES = np.array([
    [0.0462, 0.0316, 0.0217 + 0.0057],
    [0.0398, 0.0224, 0.0158 + 0.0038],
    [0.0446, 0.0263, 0.0174 + 0.0040],
    [0.0414, 0.0257, 0.0173 + 0.0040],
    [0.0326, 0.0181, 0.0160 + 0.0037],
])
_WRIST_TO_MCP = np.array([0.095, 0.095, 0.090, 0.084])  # index, middle, ring, little
_MCP_Y = np.array([0.024, 0.002, -0.017, -0.034])
MCP = np.stack([np.zeros(4), _MCP_Y, np.sqrt(_WRIST_TO_MCP**2 - _MCP_Y**2)], axis=1)
THUMB_CMC = np.array([0.010, 0.022, 0.028])
# thumb base frame: z along the resting metacarpal, x the direction it flexes towards
_tz = np.array([0.25, 0.55, 0.80]) / np.linalg.norm([0.25, 0.55, 0.80])
_tx = np.array([1.0, -0.6, 0.0]) - np.dot([1.0, -0.6, 0.0], _tz) * _tz
_tx /= np.linalg.norm(_tx)
THUMB_BASE = np.stack([_tx, np.cross(_tz, _tx), _tz], axis=1)
# radius of the finger around its bone axis (m): for contact with the object
BONE_RADIUS = np.array([0.010, 0.008, 0.007])
PALM_RADIUS = 0.012  # half the palm thickness around the wrist-MCP plane

OPEN_POSE = np.array([
    [0.0, 0.15, 0.10, 0.10],
    [0.05, 0.10, 0.15, 0.10],
    [0.0, 0.10, 0.15, 0.10],
    [-0.05, 0.10, 0.15, 0.10],
    [-0.10, 0.10, 0.15, 0.10],
])


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def finger_keypoints(finger: int, angles: np.ndarray) -> np.ndarray:
    """The 4 keypoints (hand frame) of one finger: thumb CMC..tip or finger MCP..tip."""
    a = np.asarray(angles, float)
    if finger == 0:
        R = THUMB_BASE @ _rx(-a[0]) @ _ry(a[1])
        p = THUMB_CMC.copy()
        flex = (a[2], a[3])
    else:
        R = _rx(a[0]) @ _ry(a[1])
        p = MCP[finger - 1].copy()
        flex = (a[2], a[3])
    out = [p]
    for k, length in enumerate(BONES[finger]):
        p = p + R[:, 2] * length
        out.append(p)
        if k < 2:
            R = R @ _ry(flex[k])
    return np.array(out)


def hand_keypoints(pose: np.ndarray) -> np.ndarray:
    """All 21 keypoints (MediaPipe order) in the hand frame for a (5, 4) pose."""
    pose = np.asarray(pose, float)
    if pose.shape != (5, 4):
        raise ValueError(f"hand pose must have shape (5, 4), got {pose.shape}")
    kp = np.zeros((21, 3))
    for f in range(5):
        kp[1 + 4 * f: 5 + 4 * f] = finger_keypoints(f, pose[f])
    return kp


def open_hand_keypoints() -> np.ndarray:
    """Keypoints of the relaxed open hand (hand frame); used e.g. for retargeting scales."""
    return hand_keypoints(OPEN_POSE)


def finger_samples(keypoints4: np.ndarray, per_bone: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Points along a finger's 3 bones and the finger radius at each (for contact checks).

    The tip keypoint itself is included with radius 0 (it lies on the skin).
    """
    pts, rad = [], []
    for b in range(3):
        for t in np.linspace(0, 1, per_bone, endpoint=False):
            pts.append(keypoints4[b] + t * (keypoints4[b + 1] - keypoints4[b]))
            rad.append(BONE_RADIUS[b])
    pts.append(keypoints4[3] - 0.004 * _unit(keypoints4[3] - keypoints4[2]))
    rad.append(BONE_RADIUS[2] * 0.7)
    pts.append(keypoints4[3])
    rad.append(0.0)
    return np.array(pts), np.array(rad)


def palm_samples(keypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points spanning the palm (wrist, thumb CMC, the 4 MCPs) with the palm half-thickness."""
    corners = keypoints[[0, 1, 5, 9, 13, 17]]
    pts = [corners]
    for m in keypoints[[5, 9, 13, 17]]:
        pts.append(keypoints[0] + np.outer(np.linspace(0.25, 0.75, 3), m - keypoints[0]))
    pts = np.concatenate(pts)
    return pts, np.full(len(pts), PALM_RADIUS)


def palm_centre(keypoints: np.ndarray, out: float = 0.051, along: float = 0.72) -> np.ndarray:
    """The grasp centre in front of the palm for 21 keypoints in any frame, (..., 21, 3) ->
    (..., 3): `along` of the way from the wrist to the middle MCP, moved `out` along the
    palm normal (x of `hand_frame.hand_frames`)."""
    from dexdrake.demos.hand_frame import hand_frames

    kp = np.asarray(keypoints, float)
    R, wrist = hand_frames(kp)
    return wrist + along * (kp[..., 9, :] - wrist) + out * R[..., :, 0]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / (np.linalg.norm(v) or 1.0)
