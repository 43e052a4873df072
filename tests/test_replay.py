"""Tests of the demo replay (systems/demo_replay.py) and `dexdrake demos replay`."""

from __future__ import annotations

import numpy as np
import pytest

from dexdrake.demos.format import DemoMeta, HumanDemo
from dexdrake.demos.trim import quat_wxyz_to_matrix
from dexdrake.errors import DexdrakeError
from dexdrake.hands.description import load_hand
from dexdrake.systems.demo_replay import (
    ReplayConfig,
    closure_ramp,
    correlated_noise,
    grasp_onset_step,
    place_demo,
    resample_trajectory,
)
from dexdrake.systems.scene import ObjectPlacement
from dexdrake.task import TaskSpec


def test_resample_is_linear_interpolation_at_the_control_period():
    time = np.arange(31) / 60.0  # 0.5 s at 60 fps
    q = np.stack([2.0 * time + 1.0, -time, np.sin(time)], axis=1)
    out = resample_trajectory(q, time, 0.02)
    assert out.shape == (26, 3)  # 0, 0.02, ..., 0.5
    t = 0.02 * np.arange(26)
    np.testing.assert_allclose(out[:, 0], 2.0 * t + 1.0, atol=1e-12)
    np.testing.assert_allclose(out[:, 1], -t, atol=1e-12)
    np.testing.assert_allclose(out[-1], q[-1])
    # a duration that is not a multiple of the period still ends on the last frame
    out = resample_trajectory(q[:29], time[:29], 0.02)
    assert out.shape == (25, 3)
    np.testing.assert_allclose(out[-1], q[28])
    np.testing.assert_allclose(out[-2, 0], 2.0 * 0.46 + 1.0)


def test_resample_rejects_bad_input():
    with pytest.raises(DexdrakeError, match="do not match"):
        resample_trajectory(np.zeros((5, 2)), np.arange(4.0), 0.02)
    with pytest.raises(DexdrakeError, match="increasing"):
        resample_trajectory(np.zeros((3, 2)), np.array([0.0, 0.1, 0.1]), 0.02)
    with pytest.raises(DexdrakeError, match="positive"):
        resample_trajectory(np.zeros((3, 2)), np.arange(3.0), 0.0)


def _random_demo(rng: np.random.Generator, T: int = 6) -> HumanDemo:
    kp = rng.normal(scale=0.1, size=(T, 21, 3))
    pos = np.cumsum(rng.normal(scale=0.01, size=(T, 3)), axis=0) + [0.0, 0.0, 0.04]
    quat = rng.normal(size=(T, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    return HumanDemo(kp, np.arange(T) / 30.0, "sphere_small", pos, quat, DemoMeta(fps=30.0))


def test_place_demo_keeps_keypoints_fixed_relative_to_the_object():
    rng = np.random.default_rng(3)
    demo = _random_demo(rng)
    placement = ObjectPlacement(0.03, -0.02, 2.5)
    placed = place_demo(demo, placement, rest_height=0.07)
    placed.validate()

    def in_object_frame(d):
        R = quat_wxyz_to_matrix(d.object_quat)
        return np.einsum("tkj,tji->tki", d.keypoints - d.object_pos[:, None], R)

    np.testing.assert_allclose(in_object_frame(placed), in_object_frame(demo), atol=1e-9)
    np.testing.assert_allclose(placed.object_pos[0], [0.03, -0.02, 0.07], atol=1e-12)
    c, s = np.cos(2.5), np.sin(2.5)
    np.testing.assert_allclose(quat_wxyz_to_matrix(placed.object_quat[0]), [[c, -s, 0], [s, c, 0], [0, 0, 1]], atol=1e-9)
    # the object's motion is carried along: displacements keep their length
    np.testing.assert_allclose(np.linalg.norm(np.diff(placed.object_pos, axis=0), axis=1),
                               np.linalg.norm(np.diff(demo.object_pos, axis=0), axis=1), atol=1e-12)


def test_episode_placement_is_seeded_and_in_the_papers_ranges():
    p = [ObjectPlacement.from_seed(s) for s in range(200)]
    assert ObjectPlacement.from_seed(7) == ObjectPlacement.from_seed(7)
    assert len({q.yaw for q in p}) == 200
    assert all(-0.05 <= q.x <= 0.05 and -0.05 <= q.y <= 0.0 and -np.pi <= q.yaw <= np.pi for q in p)


def test_correlated_noise_statistics():
    tau = 10.0
    x = correlated_noise(np.random.default_rng(0), 4000, 40, tau)
    np.testing.assert_array_equal(x, correlated_noise(np.random.default_rng(0), 4000, 40, tau))
    assert not np.allclose(x, correlated_noise(np.random.default_rng(1), 4000, 40, tau))
    np.testing.assert_array_equal(x[0], 0.0)
    tail = x[100:]  # past the start-up transient
    assert abs(tail.std() - 1.0) < 0.05
    lag1 = np.mean([np.corrcoef(tail[:-1, j], tail[1:, j])[0, 1] for j in range(40)])
    assert abs(lag1 - np.exp(-1 / tau)) < 0.02
    lag30 = np.mean([np.corrcoef(tail[:-30, j], tail[30:, j])[0, 1] for j in range(40)])
    assert abs(lag30 - np.exp(-30 / tau)) < 0.05
    cross = np.corrcoef(tail.T)[np.triu_indices(40, 1)]
    assert np.abs(cross).mean() < 0.1  # joints are perturbed independently
    with pytest.raises(DexdrakeError):
        correlated_noise(np.random.default_rng(0), 0, 3, tau)


def test_closure_ramp_follows_the_hands_closing_directions():
    hand = load_hand("adroit")
    lo, hi = hand.joint_limits()
    ramp = closure_ramp(hand, 30, start=10, ramp_steps=5, amount=0.2)
    assert ramp.shape == (30, hand.num_actuators)
    np.testing.assert_array_equal(ramp[:10], 0.0)
    sign = np.array([hand.closing.get(j, 0.0) for j in hand.policy_joints])
    np.testing.assert_allclose(ramp[14:], np.tile(0.2 * sign * (hi - lo) / 2, (16, 1)))
    assert np.all(np.diff(ramp[:, sign > 0], axis=0) >= 0)
    np.testing.assert_array_equal(ramp[:, : len(hand.arm_joints)], 0.0)


def test_grasp_onset_is_where_the_fingers_start_closing():
    hand = load_hand("adroit")
    sign = np.array([hand.closing.get(j, 0.0) for j in hand.policy_joints])
    s = np.clip((np.arange(50) - 20) / 20, 0, 1)
    q = hand.pregrasp_vector() + s[:, None] * 0.5 * sign
    assert grasp_onset_step(hand, q, 0.2) == 24  # first s >= 0.2
    assert grasp_onset_step(hand, np.tile(q[0], (10, 1)), 0.2) == 5  # never closes: middle


def test_replay_config_validation():
    with pytest.raises(DexdrakeError, match="horizon"):
        ReplayConfig(horizon=1)
    with pytest.raises(DexdrakeError, match="closure"):
        ReplayConfig(closure=(0.3, 0.1))
    with pytest.raises(DexdrakeError, match="squeeze"):
        ReplayConfig(squeeze=-0.1)


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    from dexdrake.demos.format import save_demo
    from dexdrake.demos.synthetic import synthesize_object_demos

    folder = tmp_path_factory.mktemp("demos")
    (demo,) = synthesize_object_demos("sphere_small", 1, seed=0,
                                      placement_yaw=lambda s: ObjectPlacement.from_seed(s).yaw)
    save_demo(demo, folder / "sphere_small_00_top.npz")
    np.savez(folder / "sphere_small_00_top.adroit.npz", q=np.zeros((3, 30)))  # not a demo: skipped
    return folder


def test_short_replay_writes_a_dataset_the_bc_loader_reads(demo_dir, tmp_path):
    from dexdrake.cli.replay import run_replay
    from dexdrake.learn.demo_dataset import load_demo_dataset

    # a lenient task so a 12-step episode can succeed: the test is about the pipeline
    config = ReplayConfig(horizon=12, attempts=1, task=TaskSpec(success_radius=0.5, success_steps=5))
    out = tmp_path / "replay.npz"
    meta = run_replay(demo_dir, out, "adroit", config, seed=4, command="test", progress=False)
    data = load_demo_dataset(out, obs_dim=60, action_dim=30)
    assert len(data) == 12 and data.episode_starts.sum() == 1
    assert np.all(np.abs(data.actions) <= 1.0 + 1e-6)
    assert data.metadata["command"] == "test" and data.metadata["seed"] == 4
    assert data.metadata["config"]["horizon"] == 12 and data.metadata["feature_set"] is None
    assert data.metadata["demos"][0]["placement"] == meta["demos"][0]["placement"]
    assert data.metadata["hand"] == "adroit" and data.metadata["observation_blocks"] == {"hand": 60}
    (rec,) = data.metadata["demos"]
    assert rec["object"] == "sphere_small" and rec["kind"] == "raw" and rec["kept_attempt"] == 0
    assert rec["file"].endswith("sphere_small_00_top.npz")
    rates = data.metadata["success_rates"]
    assert rates["per_category"]["sphere"]["raw_rate"] == 1.0
    assert data.metadata["counts"] == {"demos": 1, "episodes": 1, "samples": 12, "raw_episodes": 1,
                                       "sampled_episodes": 0, "attempts_run": 1}
    assert np.std(data.actions[:, :6], axis=0).max() > 1e-3  # the arm moves along the demo


def test_replayer_tracks_the_demo_and_samples_after_a_failure(demo_dir):
    from dexdrake.demos.format import load_demo
    from dexdrake.systems.demo_replay import DemoReplayer

    demo = load_demo(demo_dir / "sphere_small_00_top.npz")
    # success is impossible within 10 steps: the raw replay and both sampled attempts fail
    replayer = DemoReplayer("adroit", config=ReplayConfig(horizon=10, attempts=2))
    result = replayer.replay(demo, seed=11)
    assert [k for k, _, _ in result.outcomes] == [0, 1, 2]
    assert not result.success and not result.raw_success and result.episode is None
    env = replayer.env("sphere_small")
    plan = replayer.plan(demo, 11)
    raw = replayer.run(env, plan)
    np.testing.assert_allclose(raw.actions[0], env.normalise(plan.q_demo[1]), atol=1e-6)
    q_measured = raw.observations[1:, :30]  # hand positions follow the set-points closely
    assert np.abs(q_measured[:, :6] - plan.q_demo[1:10, :6]).max() < 0.05
    sampled = replayer.run(env, plan, replayer.perturbation(env, plan, np.random.default_rng([11, 1])), attempt=1)
    assert sampled.sampled and not np.allclose(sampled.actions, raw.actions)
    # the episode starts at the planned placement
    X = env.scene.object_pose(env.plant_context).translation()
    assert abs(X[0] - plan.placement.x) < 0.01 and abs(X[1] - plan.placement.y) < 0.01


def test_run_replay_errors_clearly(tmp_path, demo_dir):
    from dexdrake.cli.replay import find_demos, run_replay

    with pytest.raises(DexdrakeError, match="does not exist"):
        find_demos(tmp_path / "missing", None)
    with pytest.raises(DexdrakeError, match="no demo-format"):
        find_demos(tmp_path, None)
    with pytest.raises(DexdrakeError, match="no demos of"):
        find_demos(demo_dir, ["mug"])
    with pytest.raises(DexdrakeError, match="unknown feature set"):
        run_replay(demo_dir, tmp_path / "x.npz", "adroit", ReplayConfig(horizon=5), feature_set="Nope", progress=False)


def test_cli_registers_demos_replay():
    from dexdrake.cli import build_parser

    args = build_parser().parse_args(["demos", "replay", "--hand", "adroit", "--demos", "d", "--out", "o.npz",
                                      "--attempts", "3", "--workers", "2"])
    from dexdrake.cli.replay import cmd_replay, command_line

    assert args.func is cmd_replay
    assert command_line(args) == ("dexdrake demos replay --hand adroit --demos d --out o.npz --attempts 3 "
                                  "--seed 0 --horizon 200 --workers 2")


def test_parallel_workers_match_serial(demo_dir, tmp_path):
    from dexdrake.cli.replay import run_replay
    from dexdrake.learn.demo_dataset import load_demo_dataset

    config = ReplayConfig(horizon=8, attempts=0, task=TaskSpec(success_radius=0.5, success_steps=3))
    run_replay(demo_dir, tmp_path / "a.npz", "adroit", config, seed=2, workers=1, progress=False)
    run_replay(demo_dir, tmp_path / "b.npz", "adroit", config, seed=2, workers=2, progress=False)
    a, b = load_demo_dataset(tmp_path / "a.npz"), load_demo_dataset(tmp_path / "b.npz")
    np.testing.assert_allclose(a.observations, b.observations, atol=1e-6)
    np.testing.assert_allclose(a.actions, b.actions, atol=1e-6)


def test_demos_made_for_an_episode_are_replayed_at_its_placement(demo_dir):
    from dexdrake.demos.format import load_demo
    from dexdrake.cli.replay import find_demos
    from dexdrake.systems.demo_replay import DemoReplayer

    ((path, name, made_for),) = find_demos(demo_dir, None)
    demo = load_demo(path)
    assert name == "sphere_small" and made_for == demo.meta.extra["episode_seed"]
    plan = DemoReplayer("adroit", config=ReplayConfig(attempts=0)).plan(demo, made_for)
    assert abs(plan.placement.yaw - demo.meta.extra["placement_yaw"]) < 1e-6
    # the squeeze adds closure only in the closing directions, after the grasp onset
    assert np.all(plan.squeeze[0] == 0) and plan.squeeze[-1].max() > 0 and plan.squeeze.min() >= 0
