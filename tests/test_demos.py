"""Human demo format, loaders and the synthetic grasp source."""

import pickle

import numpy as np
import pytest
import trimesh

from dexdrake.demos import human_hand as hh
from dexdrake.demos.format import (FORMAT_VERSION, DemoFormatError, DemoMeta, HumanDemo,
                                   load_demo, save_demo)
from dexdrake.demos.hand_frame import canonical
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
        np.testing.assert_allclose(d.keypoints, canonical(np.stack([mp, mp + 0.01])), atol=1e-12)
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
    from dexdrake.systems.scene import ObjectPlacement

    for demo in synthesize_object_demos("sphere_small", 2, seed=3,
                                        placement_yaw=lambda s: ObjectPlacement.from_seed(s).yaw):
        extra = demo.meta.extra
        assert extra["grasp"] != "side" and extra["episode_seed"] == extra["seed"]
        psi = ObjectPlacement.from_seed(extra["episode_seed"]).yaw
        assert abs(extra["placement_yaw"] - psi) < 1e-6
        fingers = demo.keypoints[-1, 9] - demo.keypoints[-1, 0]  # wrist -> middle MCP, object frame
        world_yaw = np.arctan2(fingers[1], fingers[0]) + psi
        assert abs(np.angle(np.exp(1j * (world_yaw - ADROIT_HEADING)))) < HEADING_SPREAD + 0.3


def test_palm_centre_is_in_front_of_the_palm():
    kp = hh.open_hand_keypoints()
    np.testing.assert_allclose(hh.palm_centre(kp, out=0.05, along=0.5),
                               0.5 * kp[9] + [0.05, 0, 0], atol=1e-12)


def _moving_hand(T: int = 20, seed: int = 0) -> np.ndarray:
    """A closing right hand in an arbitrary frame (rotated, far from the origin), metres."""
    from scipy.spatial.transform import Rotation

    closed = np.array([[-0.45, 0.95, 0.6, 0.7]] + [[0.0, 1.5, 1.7, 1.2]] * 4)
    R = Rotation.random(random_state=seed).as_matrix()
    return np.array([hh.hand_keypoints(hh.OPEN_POSE + a * (closed - hh.OPEN_POSE)) @ R.T
                     + [0.4, -1.2, 0.7] for a in np.linspace(0, 0.8, T)])


def test_canonical_frame_is_frame_free():
    from scipy.spatial.transform import Rotation

    from dexdrake.demos.hand_frame import hand_frames

    kp = _moving_hand()
    R = Rotation.random(random_state=5).as_matrix()
    np.testing.assert_allclose(canonical(kp @ R.T + [1, 2, 3]), canonical(kp), atol=1e-12)
    fixed = canonical(kp, per_frame=True)  # every frame in its own hand frame
    np.testing.assert_allclose(fixed[:, 0], 0, atol=1e-12)
    Rf, _ = hand_frames(fixed)
    np.testing.assert_allclose(Rf, np.broadcast_to(np.eye(3), Rf.shape), atol=1e-12)
    # the human_hand model's frame is the canonical one: open hand x = palm normal
    Ro, _ = hand_frames(hh.open_hand_keypoints())
    assert Ro[0, 0] > 0.999 and Ro[2, 2] > 0.999


def _save(tmp_path, name, kp):
    import json

    path = tmp_path / name
    if name.endswith(".npy"):
        np.save(path, kp)
    elif name.endswith(".npz"):
        np.savez(path, keypoints=kp, time=np.arange(len(kp)) / 50.0)
    elif name.endswith(".pkl"):
        path.write_bytes(pickle.dumps({"keypoints": kp}))
    elif name.endswith(".json"):
        path.write_text(json.dumps([[{"x": x, "y": y, "z": z} for x, y, z in f] for f in kp]))
    else:
        np.savetxt(path, kp.reshape(len(kp), 63), delimiter=",", header="k" * 63)
    return path


@pytest.mark.parametrize("name", ["k.npy", "k.npz", "k.pkl", "k.json", "k.csv"])
def test_keypoint_formats_and_units(tmp_path, name):
    kp = _moving_hand()
    ref = canonical(kp)
    for units, scale in (("auto", 1.0), ("mm", 1000.0), ("auto", 1000.0)):
        notes = []
        d = load_keypoint_array(_save(tmp_path, name, kp * scale), units=units, notes=notes)
        np.testing.assert_allclose(d.keypoints, ref, atol=1e-9)
        assert d.meta.extra["frame"] == "hand"
    assert d.time[1] == pytest.approx(0.02 if name == "k.npz" else 1 / 30)


def test_left_hand_is_mirrored(tmp_path):
    kp = _moving_hand()
    left = kp * [-1, 1, 1]  # a left hand: the mirror image of the right one
    d = load_keypoint_array(_save(tmp_path, "l.npy", left), hand="left")
    np.testing.assert_allclose(d.keypoints, canonical(kp * [-1, 1, 1] * [-1, 1, 1]), atol=1e-12)


def _with(kp, t, j, value):
    kp = kp.copy()
    kp[t, j] = value
    return kp


@pytest.mark.parametrize("change, message", [
    (lambda kp: kp * 0, "every frame is empty"),
    (lambda kp: _with(kp, 3, 4, np.nan), "NaN/Inf keypoints .first: frame 3, keypoint 4"),
    (lambda kp: kp * 7, "cannot tell the units"),
    (lambda kp: _with(kp, slice(2, 4), slice(None), kp[2, 0] + 1e-4), "collapsed hand"),
    (lambda kp: kp[:, MANO_TO_MEDIAPIPE], "impossible bone lengths.*--order"),
    (lambda kp: kp[:0], "empty .0 frames"),
    (lambda kp: kp[:, :20], "expected keypoints of shape"),
])
def test_degenerate_keypoints_are_refused(tmp_path, change, message):
    with pytest.raises(DemoFormatError, match=message):
        load_keypoint_array(_save(tmp_path, "k.npy", change(_moving_hand())))


def test_missing_frames_are_dropped(tmp_path):
    kp = _with(_moving_hand(), 5, slice(None), 0.0)
    notes = []
    d = load_keypoint_array(_save(tmp_path, "k.npy", kp), notes=notes)
    assert d.num_frames == 19 and d.time[5] == pytest.approx(6 / 30)
    assert any("dropped 1 of 20" in n for n in notes)


def test_unit_flag_must_fit(tmp_path):
    with pytest.raises(DemoFormatError, match="pass --units mm"):
        load_keypoint_array(_save(tmp_path, "k.npy", _moving_hand() * 1000), units="m")


def test_bad_files_are_refused(tmp_path):
    (tmp_path / "t.npz").write_bytes(b"PK\x03\x04 truncated")
    np.savez(tmp_path / "e.npz")
    np.savez(tmp_path / "o.npz", keypoints=np.array([None, 1], dtype=object))

    class Evil:
        def __reduce__(self):
            return (print, ("ran code",))

    (tmp_path / "evil.pkl").write_bytes(pickle.dumps({"keypoints": Evil()}))
    (tmp_path / "k.txt").write_text("1 2 3")
    for name, message in (("t.npz", "cannot read keypoints"), ("e.npz", "holds no arrays"),
                          ("o.npz", "Python objects"), ("evil.pkl", "refused to load builtins"),
                          ("k.txt", "unsupported keypoint file type"),
                          ("none.npy", "no such file")):
        with pytest.raises(DemoFormatError, match=message):
            load_keypoint_array(tmp_path / name)


def test_object_pose_parsing(tmp_path):
    from dexdrake.demos.loaders import parse_pose

    np.testing.assert_allclose(parse_pose("0.1,0.2,0.3"), [0.1, 0.2, 0.3, 1, 0, 0, 0])
    np.save(tmp_path / "p.npy", np.tile([0, 0, 0.05, 1, 0, 0, 0], (4, 1)))
    assert parse_pose(str(tmp_path / "p.npy")).shape == (4, 7)
    for bad in ("1,2", "a,b,c", "0,0,0,2,0,0,0"):
        with pytest.raises(DemoFormatError, match="--object-pose"):
            parse_pose(bad)


def test_demos_import_command(tmp_path, capsys):
    from dexdrake.cli import main

    src = _save(tmp_path, "k.npy", _moving_hand() * 1000)
    assert main(["demos", "import", str(src), "--out", str(tmp_path / "d.npz"),
                 "--hand", "left", "--fps", "60"]) == 0
    out = capsys.readouterr().out
    assert "millimetres (detected)" in out and "mirrored the left hand" in out
    d = load_demo(tmp_path / "d.npz")
    assert d.meta.fps == 60 and d.meta.extra["hand"] == "left"
    assert main(["demos", "import", str(src), "--out", str(tmp_path / "o.npz"),
                 "--object", "no_such_object"]) == 2
    assert "unknown object 'no_such_object'" in capsys.readouterr().err
