"""Synthetic hand captures without an object, for measuring retargeters: the kinematic hand of
`human_hand` moving between grasp poses, and a seeded model of a monocular MediaPipe
capture's errors to put on any keypoint trajectory.

Both return (T, 21, 3) keypoints in metres, MediaPipe order, in an arbitrary capture frame.
"""

from __future__ import annotations

import numpy as np

from dexdrake.demos import human_hand as hh

# parent of each of the 21 keypoints (MediaPipe order; the wrist is its own parent)
PARENT = np.array([0, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19])
_POWER = np.array([[-0.45, 0.95, 0.6, 0.7]] + [[0.0, 1.5, 1.7, 1.2]] * 4)
_PINCH = np.array([[-0.45, 0.45, 0.45, 0.5], [0.0, 1.0, 1.0, 0.6], [0.0, 1.1, 1.1, 0.6],
                   [0.0, 1.5, 1.7, 1.2], [0.0, 1.5, 1.7, 1.2]])


def grasp_trajectory(frames: int, seed: int, noise: float = 0.0, fps: float = 30.0
                     ) -> np.ndarray:
    """The hand moving between random key poses one second apart (power grasp, pinch or
    open, each finger 30-100 % of the way there from the open pose, eased in and out) while
    the wrist turns (+-0.3 rad) and moves (+-5 cm), in a random capture frame; plus white
    noise of std `noise` (m) on every coordinate."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    keys = [hh.OPEN_POSE]
    while len(keys) * fps < frames + fps:
        base = [hh.OPEN_POSE, _POWER, _PINCH][rng.integers(3)]
        keys.append(hh.OPEN_POSE + rng.uniform(0.3, 1.0, (5, 1)) * (base - hh.OPEN_POSE))
    s = np.arange(frames) / fps
    i = np.minimum(s.astype(int), len(keys) - 2)
    a = 0.5 - 0.5 * np.cos(np.pi * (s - i))
    R0 = Rotation.random(random_state=seed).as_matrix()
    out = []
    for t in range(frames):
        pose = keys[i[t]] + a[t] * (keys[i[t] + 1] - keys[i[t]])
        turn = Rotation.from_rotvec(0.3 * np.sin([0.7 * s[t], 0.5 * s[t], 0.9 * s[t]]))
        out.append(hh.hand_keypoints(pose) @ (R0 @ turn.as_matrix()).T + [0.4, -1.1, 0.8]
                   + 0.05 * np.sin(s[t]))
    return np.array(out) + rng.normal(0.0, noise, (frames, 21, 3))


def mediapipe_like(keypoints: np.ndarray, seed: int) -> np.ndarray:
    """`keypoints` (T, 21, 3) with the errors of a monocular hand tracker, seeded:
    another person's hand (hand size x U(0.9, 1.1), each bone x N(1, 0.06), bones re-chained
    from the wrist); slow, temporally correlated errors (AR(1), 0.9 per frame) of 3 mm std
    across and 8 mm along a random camera depth axis; 1.5 mm white jitter; and tracker
    glitches (1 % of frames: one finger's 4 keypoints off by 10-20 mm for 1-3 frames)."""
    kp = np.asarray(keypoints, float)
    rng = np.random.default_rng(seed)
    T = len(kp)
    bones = kp[:, 1:] - kp[:, PARENT[1:]]
    scale = rng.uniform(0.9, 1.1) * rng.normal(1.0, 0.06, 20)
    out = np.zeros_like(kp)
    out[:, 0] = kp[:, 0]
    for j in range(1, 21):
        out[:, j] = out[:, PARENT[j]] + scale[j - 1] * bones[:, j - 1]
    depth = rng.normal(size=3)
    depth /= np.linalg.norm(depth)
    sigma = 0.003 * np.eye(3) + (0.008 - 0.003) * np.outer(depth, depth)
    drive = rng.normal(size=(T, 21, 3)) @ sigma.T * np.sqrt(1 - 0.9 ** 2)
    slow = np.zeros_like(kp)
    slow[0] = rng.normal(size=(21, 3)) @ sigma.T
    for t in range(1, T):
        slow[t] = 0.9 * slow[t - 1] + drive[t]
    out += slow + rng.normal(0.0, 0.0015, kp.shape)
    for t in np.flatnonzero(rng.random(T) < 0.01):
        f = rng.integers(5)
        off = rng.normal(size=3)
        out[t:t + rng.integers(1, 4), 1 + 4 * f:5 + 4 * f] += \
            rng.uniform(0.010, 0.020) * off / np.linalg.norm(off)
    return out
