"""Batched work gives the bits of unbatched work: the policy's batch act, K envs in lockstep,
the reward's fingertip distances read from the features' closest-point query, the SDF grid's
float32 gather."""

from __future__ import annotations

import numpy as np
import pytest
from test_learn import PointMassReach, make_toy_env, toy_policy

from dexdrake.dexrep.geometry import SdfGrid
from dexdrake.learn.samplers import SequentialSampler, rollout, rollout_lockstep

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _same_trajectories(a, b, rtol: float = 0.0) -> None:
    """Equal bits (rtol 0), or equal within `rtol` for the float32 network's outputs."""
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert x.seed == y.seed and x.success == y.success and x.terminated == y.terminated
        for field in ("observations", "actions", "rewards", "log_probs"):
            np.testing.assert_allclose(getattr(x, field), getattr(y, field), rtol=rtol, atol=0, err_msg=field)


def test_batch_act_gives_each_row_the_bits_of_a_single_act():
    """The shipped policy: a row's action and log-probability do not depend on the batch."""
    from dexdrake.cli.demo import default_policy_path
    from dexdrake.learn.policy import load_policy

    policy = load_policy(default_policy_path())[0]
    rng = np.random.default_rng(0)
    obs = (rng.normal(size=(19, policy.config.obs_dim)) * policy.obs_std.numpy() + policy.obs_mean.numpy())
    for k in (1, 2, 5, 8, 9, 19):
        rngs = [np.random.default_rng(100 + i) if i % 2 else None for i in range(k)]
        actions, log_probs = policy.act_batch(obs[:k], rngs)
        for i in range(k):
            action, log_prob = policy.act(obs[i], np.random.default_rng(100 + i) if i % 2 else None)
            np.testing.assert_array_equal(actions[i], action)
            assert log_probs[i] == log_prob


class StopsEarly(PointMassReach):
    """The toy env ending at a seed-dependent step, so envs in lockstep finish apart."""

    def reset(self, seed: int) -> np.ndarray:
        self._left = 3 + seed % 11
        return super().reset(seed)

    def step(self, action):
        obs, reward, _, info = super().step(action)
        self._left -= 1
        return obs, reward, self._left == 0, info


def make_stops_early() -> StopsEarly:
    return StopsEarly()


@pytest.mark.parametrize("deterministic", [True, False])
def test_lockstep_rollouts_equal_one_env_at_a_time(deterministic):
    policy = toy_policy(seed=1).eval()
    seeds = [4, 9, 10, 2, 7]
    one = [rollout(make_stops_early(), policy, s, deterministic) for s in seeds]
    assert len({len(t.rewards) for t in one}) > 1  # the episodes end at different steps
    # the toy's 2-wide output layer rounds by a row's place in the batch (the shipped policy's
    # layers do not: the tests above and below), hence the tolerance
    _same_trajectories(rollout_lockstep([make_stops_early() for _ in seeds], policy, seeds, deterministic), one,
                       rtol=1e-5)


def test_sampler_envs_per_worker_changes_no_trajectory():
    policy = toy_policy(seed=2).eval()
    seeds = list(range(11))
    expected = SequentialSampler(make_toy_env).sample(policy, seeds)
    for k in (4, 8):
        with SequentialSampler(make_toy_env, envs_per_worker=k) as sampler:
            _same_trajectories(sampler.sample(policy, seeds), expected, rtol=1e-5)


@pytest.mark.slow
def test_grasp_env_episodes_are_the_same_at_k_1_and_4():
    """The shipped DexRep policy on the Drake grasp env: four seeds one after another on one
    env, and the same four on four envs in lockstep, agree step by step."""
    from dexdrake.cli.demo import default_policy_path
    from dexdrake.learn.policy import load_policy
    from dexdrake.systems.env_factory import env_factory_for_policy

    policy = load_policy(default_policy_path())[0]
    factory = env_factory_for_policy(policy.config, ["mug", "can_soda"], 25, object_from_seed=True)
    seeds = [11, 12, 13, 14]
    env = factory()
    one = [rollout(env, policy, s) for s in seeds]
    _same_trajectories(rollout_lockstep([factory() for _ in seeds], policy, seeds), one)


@pytest.mark.slow
def test_reward_fingertip_distances_equal_their_own_closest_point_query():
    """The env reads the fingertips' distances from the features' closest-point query; a
    query of the fingertips alone (the path without features) gives the same distances."""
    from dexdrake.systems.env_factory import GraspEnvFactory

    env = GraspEnvFactory("adroit", "DexRep+Vel", ("mug",), 40)()
    env.reset(5)
    rng, shared, own = np.random.default_rng(0), [], []
    for _ in range(40):
        env.step(np.clip(env.normalise(env.scene.hand.pregrasp_vector()) + 0.3 * rng.standard_normal(env.action_dim),
                         -1, 1))
        shared.append(env.fingertip_distances())
        env._tips_at = None  # forget the shared result: the query of its own
        own.append(env.fingertip_distances())
    np.testing.assert_allclose(shared, own, rtol=0, atol=1e-12)
    assert np.ptp(np.array(own)) > 1e-3  # the fingertips moved


def test_sdf_grid_float32_gather_equals_float64_values():
    rng = np.random.default_rng(0)
    values = rng.normal(size=(7, 8, 9)).astype(np.float32)
    u = rng.uniform(-1, 9, size=(500, 3))
    f32 = SdfGrid(np.zeros(3), 0.01, values)
    f64 = SdfGrid(np.zeros(3), 0.01, values.astype(np.float64))
    for a, b in zip(f32.trilinear_index(u, with_gradient=True), f64.trilinear_index(u, with_gradient=True)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(f32.nearest_node_index_value(u), f64.nearest_node_index_value(u))


def test_evaluation_episodes_do_not_depend_on_envs_per_worker():
    from dexdrake.cli.demo import default_policy_path
    from dexdrake.eval.evaluate import evaluate_policy
    from dexdrake.systems.env_factory import env_factory_for_policy

    def episodes(k: int) -> list[tuple]:
        report = evaluate_policy(default_policy_path(), env_factory_for_policy, ["mug", "can_soda", "box_cube"],
                                 episodes=2, seed=5, horizon=12, progress=False, envs_per_worker=k)
        assert report.envs_per_worker == k
        return [(e.object, e.seed, e.success, e.max_lift, e.steps, e.total_reward) for e in report.episodes]

    one = episodes(1)
    assert [(o, s) for o, s, *_ in one] == [(o, s) for o in ("mug", "can_soda", "box_cube") for s in (5, 6)]
    assert episodes(3) == one


def test_dagger_lockstep_labels_equal_one_episode_at_a_time():
    from dexdrake.cli.demo import default_policy_path
    from dexdrake.learn.dagger import labelled_episode, labelled_lockstep
    from dexdrake.learn.policy import load_policy
    from dexdrake.systems.env_factory import GraspEnvFactory
    from dexdrake.systems.reactive_grasp import ReactiveGrasp

    policy = load_policy(default_policy_path())[0]
    factory = GraspEnvFactory("adroit", policy.config.feature_set, ("mug", "can_soda"), 15)
    jobs = [("mug", 1), ("can_soda", 2), ("mug", 3)]
    env = factory()
    one = [labelled_episode(env, name, seed, policy, 0.0, ReactiveGrasp) for name, seed in jobs]
    together = labelled_lockstep([factory() for _ in jobs], jobs, policy, 0.0, ReactiveGrasp)
    for a, b in zip(one, together, strict=True):
        assert a.objects == b.objects and a.seeds == b.seeds and a.success == b.success
        for field in ("episode_starts", "states", "observations", "labels"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
