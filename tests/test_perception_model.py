"""Training sees the object pose as deployed: the paper's pose noise and the perception
pipeline's frame period and latency on the features' input, seeded per episode; the reward
and success keep the true pose; the model is recorded in checkpoints and recipe manifests."""

from __future__ import annotations

import numpy as np
import pytest

from dexdrake.errors import DexdrakeError
from dexdrake.perceived_pose import PerceivedPose, PerceptionModel

PAPER = PerceptionModel(pose_noise_position_m=0.02, pose_noise_rotation_rad=0.1, period_s=0.04, latency_s=0.04)


def _rotation_vector(R: np.ndarray) -> np.ndarray:
    """log(R) as a rotation vector (angles below pi)."""
    angle = np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2 * np.sin(angle))
    return angle * axis


def test_noise_has_the_papers_sigmas_about_the_true_pose():
    seen = PerceivedPose(PerceptionModel(0.02, 0.1), control_period=0.02)
    p, R = np.array([0.1, -0.2, 0.05]), np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    seen.reset(7)
    errors, turns = [], []
    for k in range(4000):  # a frame at every control step (period 0), used at once (latency 0)
        p_seen, R_seen = seen(0.02 * k, p, R)
        errors.append(p_seen - p)
        turns.append(_rotation_vector(R_seen @ R.T))
        np.testing.assert_allclose(R_seen @ R_seen.T, np.eye(3), atol=1e-12)
    errors, turns = np.array(errors), np.array(turns)
    np.testing.assert_allclose(errors.std(axis=0), 0.02, rtol=0.06)
    np.testing.assert_allclose(turns.std(axis=0), 0.1, rtol=0.06)
    assert np.all(np.abs(errors.mean(axis=0)) < 0.002) and np.all(np.abs(turns.mean(axis=0)) < 0.01)
    assert np.all(np.abs(np.corrcoef(errors.T) - np.eye(3)) < 0.06)  # independent axes


def test_each_step_sees_the_newest_frame_one_latency_old():
    """Frames every 40 ms used 40 ms later at a 20 ms control period: the pose of step t is the
    true pose at the newest frame time <= t - 40 ms (the first frame's until then)."""
    seen = PerceivedPose(PerceptionModel(period_s=0.04, latency_s=0.04), control_period=0.02)
    seen.reset(0)
    for k in range(12):
        t = 0.02 * k
        p_seen, _ = seen(t, np.array([t, 0.0, 0.0]), np.eye(3))
        frame = max(0.0, 0.04 * np.floor(round((t - 0.04) / 0.02) / 2))
        assert p_seen[0] == pytest.approx(frame, abs=1e-12), (t, p_seen[0])


def test_the_noise_is_the_episode_seeds_alone():
    model, p, R = PerceptionModel(0.02, 0.1, 0.04, 0.04), np.zeros(3), np.eye(3)

    def poses(seed: int, busy: bool = False) -> np.ndarray:
        seen = PerceivedPose(model, 0.02)
        if busy:  # another episode before this one on the same object (as in a worker)
            seen.reset(seed + 1)
            [seen(0.02 * k, p, R) for k in range(7)]
        seen.reset(seed)
        return np.array([np.concatenate([a, b.ravel()]) for a, b in (seen(0.02 * k, p, R) for k in range(10))])

    np.testing.assert_array_equal(poses(3), poses(3, busy=True))
    assert not np.allclose(poses(3), poses(4))


@pytest.mark.parametrize("field,value", [("period_s", 0.03), ("latency_s", -0.04), ("pose_noise_position_m", float("nan"))])
def test_a_perception_entry_the_loop_cannot_run_is_refused(field, value):
    from dexdrake.systems.scenario import ScenarioError, parse_scenario

    with pytest.raises(ScenarioError, match=f"perception.{field}"):
        parse_scenario(f"perception: {{{field}: {value}}}\n")


def _episode(perception: PerceptionModel, seed: int, steps: int = 8):
    from dexdrake.systems.env_factory import GraspEnvFactory

    env = GraspEnvFactory("allegro_z1", "DexRep", ("box_cube",), steps, perception=perception)()
    observations, rewards, tips = [env.reset(seed)], [], []
    target = env.normalise(env.scene.hand.pregrasp_vector())
    rng = np.random.default_rng(0)
    for _ in range(steps):
        obs, reward, _, info = env.step(np.clip(target + 0.3 * rng.standard_normal(env.action_dim), -1, 1))
        observations.append(obs)
        rewards.append((reward, info["success"], info["lift"]))
        tips.append(env.fingertip_distances())
    return env, np.array(observations), np.array(rewards), np.array(tips)


def test_training_env_features_see_the_perceived_pose_and_the_reward_the_true_one():
    _, exact_obs, exact_rewards, exact_tips = _episode(PerceptionModel(), seed=2)
    env, noisy_obs, noisy_rewards, noisy_tips = _episode(PAPER, seed=2)
    assert env.scenario.perception == PAPER
    assert not np.allclose(exact_obs, noisy_obs)  # the features moved with the seen pose
    np.testing.assert_allclose(noisy_rewards, exact_rewards, rtol=0, atol=1e-9)  # the true pose scores
    np.testing.assert_allclose(noisy_tips, exact_tips, rtol=0, atol=1e-9)
    # the features are those of the seen pose: the frame taken 40 ms before the last step
    X_seen = env.seen_object_pose()
    features, _ = env._features.with_closest(env.plant_context, X_seen)
    np.testing.assert_array_equal(features, noisy_obs[-1])
    assert np.linalg.norm(X_seen.translation() - env.object_position()) > 1e-4
    _, again, _, _ = _episode(PAPER, seed=2)
    np.testing.assert_array_equal(again, noisy_obs)  # reproducible per seed


def test_the_sim_station_delivers_the_perceived_pose_of_the_training_env():
    from dexdrake.systems.diagram import build_diagram, run_station_episode
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.scenario import load_scenario, simulated
    from dexdrake.systems.station import pose_from_vector, sim_station

    env = _episode(PAPER, seed=2)[0]  # the training env's "object_pose" port is what its features saw
    X_port = pose_from_vector(env.diagram.GetOutputPort("object_pose").Eval(env.context))
    X_seen = env.seen_object_pose()
    np.testing.assert_allclose(X_port.translation(), X_seen.translation(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(X_port.rotation().matrix(), X_seen.rotation().matrix(), rtol=0, atol=1e-9)
    assert sim_station(training_scenario("allegro_z1")).perceived is None  # exact: the plant's pose itself

    class Seen:  # a station-episode logger: the pose the controller saw beside the true one
        def __init__(self):
            self.errors: list[float] = []

        def log_station_step(self, t, hand_state, command, object_pose, stats, true_pose):
            self.errors.append(float(np.linalg.norm(object_pose[:3] - true_pose.translation())))

    scenario = simulated(load_scenario("hil"))  # the deployed scenario's sim twin: its perception model
    assert not scenario.perception.is_exact
    hold = lambda t, hand_state, object_pose: hand_state[: len(hand_state) // 2]  # noqa: E731
    run_station_episode(sim_station(scenario), hold, 6, logger=(seen := Seen()))
    assert len(seen.errors) == 6 and 0 < np.median(seen.errors) < 5 * 3**0.5 * scenario.perception.pose_noise_position_m
    with pytest.raises(DexdrakeError, match="perception model .* needs 'fast'"):
        build_diagram(sim_station(scenario), None, "DexRep", "scenegraph")


def test_checkpoints_record_the_perception_model_and_a_mismatch_is_warned():
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.scenario import load_scenario
    from dexdrake.systems.scenario_record import check_policy_scenario, scenario_record

    trained = scenario_record(training_scenario("allegro_z1", perception=PAPER))
    assert trained["perception"] == {"pose_noise_position_m": 0.02, "pose_noise_rotation_rad": 0.1,
                                     "period_s": 0.04, "latency_s": 0.04}
    deployed = scenario_record(load_scenario("hil"))
    for name in ("hil", "real"):  # the deployed scenarios name one model
        assert load_scenario(name).perception == load_scenario("hil").perception != PAPER
        assert not any("perception" in w for w in check_policy_scenario(deployed, load_scenario(name), "p.pt"))
    for other in (trained, scenario_record(training_scenario("allegro_z1"))):  # the paper's noise, the true pose
        (warning,) = [w for w in check_policy_scenario(other, load_scenario("hil"), "p.pt") if "perception" in w]
        assert warning.startswith("warning: p.pt was trained under another perception model")


def test_the_allegro_recipe_trains_as_deployed_and_the_adroit_one_on_the_true_pose():
    from pathlib import Path

    from dexdrake.learn.recipe import load_recipe, recipe_dict, stage_plan
    from dexdrake.systems.scenario import load_scenario

    recipes = Path(__file__).resolve().parents[1] / "configs" / "recipes"
    allegro = load_recipe(recipes / "allegro_z1.yaml")
    assert allegro.perception == load_scenario("hil").perception  # the model the station deploys
    assert recipe_dict(allegro)["perception"]["latency_s"] == 0.04
    assert load_recipe(recipes / "adroit.yaml").perception.is_exact
    dapg = [f"dapg{k + 1}" for k in range(len(allegro.dapg))]
    assert [s.name for s in stage_plan(allegro) if "perception" in s.reads] == ["dagger", *dapg, "choose", "test"]


def test_noisy_evaluation_episodes_do_not_depend_on_envs_per_worker():
    from functools import partial

    from dexdrake.cli.demo import default_policy_path
    from dexdrake.eval.evaluate import evaluate_policy
    from dexdrake.systems.env_factory import env_factory_for_policy

    def episodes(k: int) -> list[tuple]:
        report = evaluate_policy(default_policy_path(), partial(env_factory_for_policy, perception=PAPER),
                                 ["mug", "can_soda"], episodes=2, seed=5, horizon=12, progress=False, envs_per_worker=k)
        return [(e.object, e.seed, e.success, e.max_lift, e.steps, e.total_reward) for e in report.episodes]

    assert episodes(2) == episodes(1)
