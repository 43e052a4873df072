"""The real hand captures made from spoken-to-signed's fingerspelling lexicon by
scripts/pose_to_keypoints.py: the depth scale and metric size it recovers, and that the
captures it writes into the cache load as plausible right hands."""

from __future__ import annotations

import numpy as np
import pytest

from dexdrake.demos.captures import grasp_trajectory
from dexdrake.demos.hand_frame import canonical
from dexdrake.demos.human_hand import open_hand_keypoints
from dexdrake.demos.loaders import load_keypoint_array
from dexdrake.paths import cache_dir

TIPS = [8, 12, 16, 20]
# the bench's real captures: (signed language, hand, frames with the hand tracked)
CAPTURES = [("ase", "right", 669), ("gsg", "right", 891), ("cse", "left", 657)]


def _as_pose_file(kp: np.ndarray, width: float, px_per_m: float, offset: float) -> np.ndarray:
    """Metric keypoints as a normalised .pose file stores them: x, y in pixels, z relative to
    the wrist in image widths, all shifted by `offset`."""
    out = kp * px_per_m
    out[..., 2] = (out[..., 2] - out[:, :1, 2]) / width
    return out + offset


def test_depth_scale_and_size_are_recovered(load_script):
    conv = load_script("pose_to_keypoints")
    hand = grasp_trajectory(120, 3)
    clips = [_as_pose_file(hand[:60], 640.0, 3000.0, 250.0),
             _as_pose_file(hand[60:], 640.0, 3000.0, -40.0)]
    scale = conv.depth_scale(clips)
    assert scale == pytest.approx(640.0, rel=0.03)
    kp = conv.to_metres(clips, scale)
    adult = open_hand_keypoints()

    def bones(k: np.ndarray) -> np.ndarray:
        return np.linalg.norm(k[..., 1:, :] - k[..., conv.PARENT, :], axis=-1)

    assert np.median(bones(kp).sum(axis=1)) == pytest.approx(bones(adult).sum(), rel=1e-6)
    truth = (hand - hand[:, :1]) * (bones(adult).sum() / np.median(bones(hand).sum(axis=1)))
    assert np.abs((kp - kp[:, :1]) - truth).max() < 0.002  # m


@pytest.mark.parametrize("language, hand, frames", CAPTURES, ids=lambda v: str(v))
def test_lexicon_capture_is_a_right_hand(load_script, tmp_path, monkeypatch,
                                         language, hand, frames):
    monkeypatch.setenv("DEXDRAKE_CACHE", str(tmp_path))
    path = load_script("pose_to_keypoints").lexicon_capture(language, hand)
    assert path == cache_dir() / "captures" / f"fingerspelling_{language}_{hand}.npy"
    demo = load_keypoint_array(path)
    assert len(demo.keypoints) == frames
    kp = canonical(demo.keypoints, per_frame=True)
    # fingers flex out of the palm's side (+x in the hand frame) as in the synthetic right hand
    assert np.mean(kp[:, TIPS, 0]) > 0.01
    assert np.mean(canonical(grasp_trajectory(120, 0), per_frame=True)[:, TIPS, 0]) > 0.01


def test_unknown_lexicon_is_one_line(load_script):
    with pytest.raises(SystemExit, match="no fingerspelling lexicon for 'xyz'; known: .*ase"):
        load_script("pose_to_keypoints").lexicon_files("xyz")
