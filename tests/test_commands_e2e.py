"""Every user-facing command once, end to end, on small inputs, through `dexdrake.cli.main`."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest
import torch
import trimesh

from dexdrake.cli import main
from dexdrake.demos.format import load_demo
from dexdrake.dexrep.pointnet import PointNetEncoder, load_encoder
from dexdrake.eval.seeds import EVALUATION_SEEDS
from dexdrake.hands.description import load_hand
from dexdrake.learn.demo_dataset import load_demo_dataset
from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig, load_policy, save_policy
from dexdrake.systems.env_factory import GraspEnvFactory
from dexdrake.task import TaskSpec
from rrd_content import logged_rows

pytestmark = pytest.mark.usefixtures("one_torch_thread")
SEED = 1_000_000_007  # evaluation seeds lie in the range reserved for evaluation


def _summary(out: str) -> dict[str, str]:
    """The `key=value` pairs of a command's one-line summary."""
    return dict(re.findall(r"(\w+)=(\S+)", out))


def test_default_demo_grasps_with_the_shipped_dexrep_policy(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the default recording, demo.rrd, lands here
    assert main(["demo"]) == 0
    out = capsys.readouterr().out
    line = _summary(out)
    # The shipped manifest's best unseen object on the first evaluation seed the manifest records
    # as a success there: the demo replays that evaluation episode, a grasp in 100 steps.
    manifest = json.loads(_shipped("adroit").with_suffix(".json").read_text())
    unseen = manifest["metrics"]["unseen"]
    best = max(o["success_pct"] for o in unseen["per_object"].values())
    name = line["object"]
    assert unseen["per_object"][name]["success_pct"] == best > 0
    seed = min(unseen["successful_seeds"][name])
    assert seed in EVALUATION_SEEDS and f"seed {seed} replays an evaluation episode" in out
    assert (line["seed"], line["success"], line["steps"]) == (str(seed), "True", "100")
    spec = TaskSpec()  # a success holds the object within success_radius of target_height above its start
    assert float(line["max_lift"].rstrip("m")) > spec.target_height - spec.success_radius
    policy, _ = load_policy(_shipped("adroit"))
    assert policy.config.feature_set == manifest["feature_set"] and policy.config.feature_set.startswith("DexRep")
    assert logged_rows(tmp_path / "demo.rrd")["/task/success"] == 100


def _shipped(hand: str):
    from dexdrake.paths import models_dir

    return models_dir() / "weights" / f"{hand}_dexrep_policy.pt"


def test_eval_with_two_workers_matches_one(tmp_path, capsys):
    common = ["eval", "--policy", str(_shipped("adroit")), "--objects", "apple", "--episodes-per-object", "3",
              "--seed", str(SEED), "--horizon", "4"]
    assert main([*common, "--workers", "1", "--out", str(tmp_path / "one")]) == 0
    assert main([*common, "--workers", "2", "--out", str(tmp_path / "two")]) == 0
    assert '"episodes": 3' in capsys.readouterr().out
    one, two = (json.loads((tmp_path / d / "eval_selected.json").read_text()) for d in ("one", "two"))
    assert [(e["object"], e["seed"], e["steps"]) for e in two["episodes"]] == [("apple", SEED + i, 4) for i in range(3)]
    for a, b in zip(one["episodes"], two["episodes"]):
        assert (a["object"], a["seed"], a["success"]) == (b["object"], b["seed"], b["success"])
        assert a["total_reward"] == pytest.approx(b["total_reward"], rel=1e-9)
        assert a["max_lift"] == pytest.approx(b["max_lift"], abs=1e-12)
    assert (one["workers"], two["workers"]) == (1, 2)
    for d in ("one", "two"):  # one object row, and apple's category row (its category is "apple" too)
        with open(tmp_path / d / "eval_selected.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        assert [(r["object"], r["category"]) for r in rows if "apple" in (r["object"], r["category"])] == [
            ("apple", ""), ("", "apple")]


def test_eval_sees_the_object_pose_as_the_policy_was_trained_to(tmp_path, capsys):
    """The shipped Allegro-on-Z1 policy records its training perception model: eval applies it,
    and --pose-noise replaces its sigmas (the frames' period and latency stay)."""
    trained = load_policy(_shipped("allegro_z1"))[1]["scenario"]["perception"]
    common = ["eval", "--policy", str(_shipped("allegro_z1")), "--objects", "can_soda", "--episodes-per-object", "1",
              "--seed", str(SEED), "--horizon", "6"]
    assert main([*common, "--out", str(tmp_path / "trained")]) == 0
    assert f"pose_noise_position_m {trained['pose_noise_position_m']:g}" in capsys.readouterr().out
    assert main([*common, "--pose-noise", "0,0", "--out", str(tmp_path / "exact")]) == 0
    out = capsys.readouterr().out
    assert "pose_noise_position_m 0, pose_noise_rotation_rad 0, " in out and "(--pose-noise)" in out
    rewards = [json.loads((tmp_path / d / "eval_selected.json").read_text())["episodes"][0]["total_reward"]
               for d in ("trained", "exact")]
    assert rewards[0] != rewards[1]


def test_sim_with_allegro_on_z1_lifts_the_sphere(tmp_path, capsys):
    rrd = tmp_path / "sim.rrd"
    assert main(["sim", "--hand", "allegro_z1", "--object", "sphere_medium", "--horizon", "150", "--rrd", str(rrd)]) == 0
    line = _summary(capsys.readouterr().out)
    assert line["success"] == "True" and float(line["max_lift"].rstrip("m")) > 0.1
    rows = logged_rows(rrd)
    assert len([e for e in rows if e.startswith("/joints/arm/") and e.endswith("/q")]) == 6  # the Z1 arm
    for finger in ("index", "middle", "ring", "thumb"):  # the Allegro hand, one group per finger
        assert len([e for e in rows if e.startswith(f"/joints/{finger}/") and e.endswith("/q")]) == 4


def test_train_dagger_on_allegro_z1(tmp_path):
    out = tmp_path / "dagger"
    assert main(["train", "dagger", "--out", str(out), "--hand", "allegro_z1", "--objects", "sphere_small",
                 "--iterations", "1", "--episodes-per-object", "1", "--horizon", "5", "--epochs", "1", "--workers", "1",
                 "--threads", "1"]) == 0
    policy, meta = load_policy(out / "dagger_policy.pt")
    assert policy.config.hand == "allegro_z1" and policy.config.feature_set == "DexRep"
    assert policy.config.action_dim == 6 + 16
    assert meta["command"].startswith("dexdrake train dagger")


def test_demos_synth_writes_loadable_demos(tmp_path, capsys):
    out = tmp_path / "demos"
    assert main(["demos", "synth", "--objects", "sphere_small,box_cube", "--out", str(out), "--demos-per-object", "1"]) == 0
    assert "wrote 2 demos" in capsys.readouterr().out
    files = sorted(out.glob("*.npz"))
    assert [f.name.split("_00_")[0] for f in files] == ["box_cube", "sphere_small"]
    for f in files:
        demo = load_demo(f)
        assert demo.num_frames > 10 and np.all(np.isfinite(demo.time))


def test_retarget_and_replay_a_synthetic_demo(tmp_path, capsys):
    demos = tmp_path / "demos"
    assert main(["demos", "synth", "--objects", "sphere_small", "--out", str(demos), "--demos-per-object", "1"]) == 0
    (demo,) = demos.glob("*.npz")
    out = tmp_path / "allegro.npz"
    capsys.readouterr()
    assert main(["retarget", str(demo), "--hand", "allegro", "--out", str(out)]) == 0
    frames, mean = re.search(r"(\d+) frames -> .*; key-vector residual ([\d.]+) mm mean", capsys.readouterr().out).groups()
    hand = load_hand("allegro")
    with np.load(out) as q:
        assert q["q"].shape == (int(frames), len(hand.policy_joints)) == (load_demo(demo).num_frames, 6 + 16)  # wrist and fingers
        assert list(q["joint_names"]) == list(hand.policy_joints) and str(q["hand"]) == "allegro"
        lower, upper = hand.joint_limits()
        assert np.all((q["q"] >= lower - 1e-9) & (q["q"] <= upper + 1e-9)) and np.ptp(q["q"], axis=0).max() > 0.1
        assert f"{float(q['residual_mm_mean']):.1f}" == mean and float(mean) < 50  # spec reference: 44 mm
    # the demo replayed in Drake by the Adroit hand: one successful episode, written as a BC dataset
    data = tmp_path / "replay.npz"
    assert main(["demos", "replay", "--hand", "adroit", "--demos", str(demos), "--out", str(data),
                 "--attempts", "0"]) == 0
    assert "overall: 1 demos, raw 100.0 %" in capsys.readouterr().out
    dataset = load_demo_dataset(data)
    assert dataset.observations.shape == (200, 60) and dataset.actions.shape == (200, 30)
    assert dataset.metadata["command"].startswith("dexdrake demos replay --hand adroit")


def test_encoder_train_for_one_step(tmp_path, capsys):
    meshes, out = tmp_path / "meshes", tmp_path / "enc.pt"
    meshes.mkdir()
    trimesh.creation.box((0.05, 0.03, 0.02)).export(meshes / "box.stl")
    trimesh.creation.icosphere(2, 0.03).export(meshes / "ball.obj")
    assert main(["encoder", "train", "--meshes", str(meshes), "--epochs", "1", "--steps-per-epoch", "1",
                 "--batch-size", "2", "--threads", "1", "--out", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    assert isinstance(load_encoder(out), PointNetEncoder)
    manifest = json.loads(out.with_suffix(".json").read_text())
    # The manifest names the command as given (also when called in-process, not from sys.argv).
    assert manifest["command"].startswith(f"dexdrake encoder train --meshes {meshes} --epochs 1 --steps-per-epoch 1")
    assert manifest["command"].endswith(f"--out {out}") and manifest["chamfer_train"] > 0


def test_imported_object_in_sim_and_eval(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("DEXDRAKE_DATA", str(tmp_path / "data"))  # keep the user object to this test
    monkeypatch.setenv("DEXDRAKE_CACHE", str(tmp_path / "cache"))
    mesh = tmp_path / "mug_like.stl"
    trimesh.creation.cylinder(radius=0.03, height=0.09, sections=24).export(mesh)
    assert main(["objects", "import", str(mesh), "--name", "test_cylinder"]) == 0
    assert "imported test_cylinder" in capsys.readouterr().out
    assert main(["sim", "--object", "test_cylinder", "--horizon", "5"]) == 0
    assert _summary(capsys.readouterr().out)["object"] == "test_cylinder"

    env = GraspEnvFactory("adroit", "Hand2obj", ("test_cylinder",), horizon=3)()
    torch.manual_seed(0)
    config = PolicyConfig.from_blocks(dict(env.observation_blocks), env.action_dim, feature_set="Hand2obj",
                                      hand="adroit")
    policy = save_policy(tmp_path / "p.pt", DexRepNetPolicy(config))
    assert main(["eval", "--policy", str(policy), "--objects", "test_cylinder", "--episodes-per-object", "1", "--horizon", "3",
                 "--seed", str(SEED), "--out", str(tmp_path / "eval")]) == 0
    report = json.loads((tmp_path / "eval" / "eval_selected.json").read_text())
    assert [(e["object"], e["steps"]) for e in report["episodes"]] == [("test_cylinder", 3)]
