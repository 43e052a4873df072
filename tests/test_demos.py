"""Human demo format, loaders and the synthetic grasp source."""

import pickle

import numpy as np
import pytest
import trimesh

from dexdrake.demos import human_hand as hh
from dexdrake.demos.format import (FORMAT_VERSION, DemoFormatError, DemoMeta, HumanDemo,
                                   load_demo, save_demo)
from dexdrake.demos.loaders import MANO_TO_MEDIAPIPE, load_keypoint_array, reorder_keypoints
from dexdrake.demos.synthetic import grasp_types_for, synthesize_demo
from dexdrake.demos.trim import SignedDistance, hand_object_distance


def _demo(T=5, seed=0) -> HumanDemo:
    rng = np.random.default_rng(seed)
    return HumanDemo(
        keypoints=rng.normal(size=(T, 21, 3)) * 0.05, time=np.arange(T) / 30.0,
        object_name="mug", object_pos=rng.normal(size=(T, 3)),
        object_quat=np.tile([1.0, 0, 0, 0], (T, 1)),
        meta=DemoMeta(subject="s1", fps=30.0, source="test", extra={"k": 1}),
        mano_pose=rng.normal(size=(T, 48)), mano_trans=rng.normal(size=(T, 3)),
        mano_betas=np.zeros(10))


def test_round_trip(tmp_path):
    d = _demo()
    path = save_demo(d, tmp_path / "d.npz")
    e = load_demo(path)
    np.testing.assert_array_equal(e.keypoints, d.keypoints)
    np.testing.assert_array_equal(e.time, d.time)
    np.testing.assert_array_equal(e.mano_pose, d.mano_pose)
    assert e.object_name == "mug" and e.meta.subject == "s1" and e.meta.extra == {"k": 1}


def _write(tmp_path, **changes):
    d = _demo()
    path = save_demo(d, tmp_path / "ok.npz")
    with np.load(path) as z:
        arrays = dict(z)
    for k, v in changes.items():
        if v is None:
            del arrays[k]
        else:
            arrays[k] = v
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    return bad


@pytest.mark.parametrize("changes, message", [
    ({"keypoints": np.zeros((5, 20, 3))}, "keypoints"),
    ({"time": np.zeros(4)}, "time"),
    ({"keypoints": np.full((5, 21, 3), np.nan)}, "NaN"),
    ({"object_pos": np.array([[0, 0, np.inf]] * 5)}, "object_pos"),
    ({"time": np.array([0.0, 0.1, 0.1, 0.2, 0.3])}, "not strictly increasing"),
    ({"format_version": np.int64(FORMAT_VERSION + 1)}, "unknown format_version"),
    ({"object_quat": None}, "missing keys"),
    ({"object_quat": np.tile([2.0, 0, 0, 0], (5, 1))}, "unit quaternions"),
    ({"mano_betas": None}, "together"),
])
def test_load_refuses_malformed(tmp_path, changes, message):
    with pytest.raises(DemoFormatError, match=message):
        load_demo(_write(tmp_path, **changes))


def test_load_refuses_non_npz(tmp_path):
    p = tmp_path / "x.npz"
    p.write_text("not a zip")
    with pytest.raises(DemoFormatError, match="not a readable"):
        load_demo(p)


def test_mano_order_permutation(tmp_path):
    mp = hh.open_hand_keypoints()
    mano = np.empty_like(mp)
    mano[MANO_TO_MEDIAPIPE] = mp  # write the hand in MANO order
    assert np.allclose(mano[13], mp[1]) and np.allclose(mano[16], mp[4])  # thumb CMC, tip
    assert np.allclose(mano[7], mp[17]) and np.allclose(mano[19], mp[16])  # little, ring tip
    np.testing.assert_allclose(reorder_keypoints(mano, "mano"), mp)
    seq = np.stack([mano, mano + 0.01])
    np.save(tmp_path / "k.npy", seq)
    with open(tmp_path / "k.pkl", "wb") as f:
        pickle.dump({"keypoints": seq}, f)
    for name in ("k.npy", "k.pkl"):
        d = load_keypoint_array(tmp_path / name, order="mano", fps=60.0)
        np.testing.assert_allclose(d.keypoints[1], mp + 0.01)
        assert d.meta.fps == 60.0
    with pytest.raises(Exception, match="unknown keypoint order"):
        load_keypoint_array(tmp_path / "k.npy", order="openpose25")


def test_human_hand_bone_lengths():
    pose = np.random.default_rng(1).uniform(0, 1, (5, 4))
    kp = hh.hand_keypoints(pose)
    for f in range(5):
        chain = kp[1 + 4 * f: 5 + 4 * f]
        np.testing.assert_allclose(np.linalg.norm(np.diff(chain, axis=0), axis=1), hh.BONES[f])
    np.testing.assert_allclose(np.linalg.norm(kp[[5, 9, 13, 17]], axis=1),
                               [0.095, 0.095, 0.090, 0.084])


@pytest.mark.parametrize("mesh, grasp", [
    (trimesh.creation.box((0.06, 0.06, 0.12)), "top"),
    (trimesh.creation.cylinder(0.035, 0.15), "side"),
    (trimesh.creation.icosphere(3, 0.025), "pinch"),
])
def test_synthetic_demo_plausible(mesh, grasp):
    assert grasp in grasp_types_for(mesh)
    d = synthesize_demo(mesh, "prim", grasp, seed=3)
    d.validate()
    # bones keep their lengths in every frame
    for f in range(5):
        chain = d.keypoints[:, 1 + 4 * f: 5 + 4 * f]
        np.testing.assert_allclose(np.linalg.norm(np.diff(chain, axis=1), axis=2),
                                   np.broadcast_to(hh.BONES[f], (d.num_frames, 3)), atol=1e-9)
    dist = hand_object_distance(d, SignedDistance(mesh.vertices, mesh.faces))
    assert dist.min() >= -0.003  # penetration at most 3 mm
    assert dist.min() <= 0.015  # the hand actually reaches the object
    assert 0.09 <= dist[0] <= 0.10  # trimmed where the hand is 10 cm away
    rise = d.object_pos[:, 2] - d.object_pos[0, 2]
    assert 0.04 <= rise[-1] <= 0.045 and rise[-2] < 0.04  # ends when lifted ~4 cm
    # canonical frame: object starts unrotated above the origin, resting on the table
    np.testing.assert_allclose(d.object_pos[0], [0, 0, -mesh.bounds[0, 2]], atol=1e-9)
    np.testing.assert_allclose(d.object_quat, np.tile([1.0, 0, 0, 0], (d.num_frames, 1)))
    assert sum(d.meta.extra["contacts"]) >= 2
    assert d.keypoints[..., 2].min() >= -1e-6  # never below the table


def test_synthetic_grasps_are_seeded_and_distinct():
    mesh = trimesh.creation.box((0.05, 0.05, 0.10))
    a = synthesize_demo(mesh, "box", "top", seed=7)
    b = synthesize_demo(mesh, "box", "top", seed=7)
    c = synthesize_demo(mesh, "box", "side", seed=7)
    np.testing.assert_array_equal(a.keypoints, b.keypoints)
    assert np.abs(a.keypoints[-1] - c.keypoints[-1]).max() > 0.02


def test_object_demos_head_where_the_arm_reaches_after_placement():
    from dexdrake.demos.synthetic import ADROIT_HEADING, HEADING_SPREAD, synthesize_object_demos
    from dexdrake.systems.demo_replay import episode_placement

    for demo in synthesize_object_demos("sphere_small", 2, seed=3):
        extra = demo.meta.extra
        assert extra["grasp"] != "side" and extra["episode_seed"] == extra["seed"]
        psi = episode_placement(extra["episode_seed"]).yaw
        assert abs(extra["placement_yaw"] - psi) < 1e-6
        fingers = demo.keypoints[-1, 9] - demo.keypoints[-1, 0]  # wrist -> middle MCP, object frame
        world_yaw = np.arctan2(fingers[1], fingers[0]) + psi
        assert abs(np.angle(np.exp(1j * (world_yaw - ADROIT_HEADING)))) < HEADING_SPREAD + 0.3


def test_palm_centre_is_in_front_of_the_palm():
    kp = hh.open_hand_keypoints()
    np.testing.assert_allclose(hh.palm_centre(kp, out=0.05, along=0.5),
                               0.5 * kp[9] + [0.05, 0, 0], atol=1e-12)
