"""Rollout backends on the real grasp env: Ray (a two-node cluster on this machine) against
local processes, for DAPG sampling and DAgger collection, and workers that die mid-run.

Ray start-up is slow, so the module shares one cluster and one sampler per backend; each
test runs a few episodes of a few control steps.
"""

from __future__ import annotations

import os
import sys
from functools import partial

import numpy as np
import pytest
import ray
import torch
from ray.cluster_utils import Cluster

from dexdrake.cli import main
from dexdrake.errors import DexdrakeError
from dexdrake.learn.dagger import collect
from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig
from dexdrake.learn.samplers import ProcessSampler, RaySampler, rollout
from dexdrake.systems.env_factory import GraspEnvFactory
from dexdrake.systems.reactive_grasp import ReactiveGrasp

OBJECT = "sphere_medium"
FACTORY = GraspEnvFactory("adroit", "DexRep", (OBJECT,), horizon=6)
MiB = 2**20

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def ray_sampler():
    """Two workers joining, by its address, a cluster of two Ray nodes of one CPU each: the
    one-CPU workers must land on different nodes."""
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "object_store_memory": 100 * MiB})
    cluster.add_node(num_cpus=1, object_store_memory=100 * MiB)
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # this module's episode functions
    try:
        with RaySampler(FACTORY, num_workers=2, address=cluster.address) as sampler:
            yield sampler
        assert not ray.is_initialized()  # the sampler that connected disconnects
    finally:
        ray.cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
        cluster.shutdown()


@pytest.fixture(scope="module")
def process_sampler():
    with ProcessSampler(FACTORY, num_workers=1) as sampler:  # two processes: tests/test_learn.py
        yield sampler


@pytest.fixture(scope="module")
def policy():
    env = FACTORY()
    torch.manual_seed(0)
    return DexRepNetPolicy(PolicyConfig.from_blocks(env.observation_blocks, env.action_dim, feature_set="DexRep",
                                                    hand="adroit"))


def _assert_same_trajectories(a, b) -> None:
    assert [t.seed for t in a] == [t.seed for t in b] and [t.success for t in a] == [t.success for t in b]
    for x, y in zip(a, b, strict=True):
        for field in ("observations", "actions", "rewards", "log_probs"):
            np.testing.assert_allclose(getattr(x, field), getattr(y, field), rtol=1e-6, atol=1e-6, err_msg=field)


def test_dapg_sampling_on_ray_matches_processes(ray_sampler, process_sampler, policy):
    seeds = [0, 1, 2]
    on_ray = ray_sampler.sample(policy, seeds)
    _assert_same_trajectories(on_ray, process_sampler.sample(policy, seeds))
    assert all(len(t) == FACTORY.horizon for t in on_ray)
    with torch.no_grad():
        policy.mlp[-1].bias.add_(0.5)  # the workers must pick up new weights
    changed = ray_sampler.sample(policy, seeds[:1])
    _assert_same_trajectories(changed, process_sampler.sample(policy, seeds[:1]))
    assert not np.allclose(changed[0].actions, on_ray[0].actions)


def test_dagger_collection_on_ray_matches_processes(ray_sampler, process_sampler, policy):
    for driver, jobs, noise in ((None, [(OBJECT, 10), (OBJECT, 11)], 0.3), (policy, [(OBJECT, 12)], 0.0)):
        a = collect(ray_sampler, driver, jobs, noise, "ray", ReactiveGrasp)
        b = collect(process_sampler, driver, jobs, noise, "processes", ReactiveGrasp)
        assert a.objects == b.objects and a.seeds.tolist() == [s for _, s in jobs]
        assert np.array_equal(a.success, b.success) and np.array_equal(a.episode_starts, b.episode_starts)
        for field in ("states", "observations", "labels"):
            np.testing.assert_allclose(getattr(a, field), getattr(b, field), rtol=1e-6, atol=1e-6, err_msg=field)
    assert len(a.labels) == FACTORY.horizon


def _node_and_rollout(env, policy, seed):
    return ray.get_runtime_context().get_node_id(), rollout(env, policy, seed)


def test_work_lands_on_both_nodes(ray_sampler, policy):
    nodes = [node for node, _ in ray_sampler.map(_node_and_rollout, policy, [0, 1, 2, 3])]
    assert set(nodes) == {n["NodeID"] for n in ray.nodes() if n["Alive"]} and len(set(nodes)) == 2
    assert ray_sampler.describe() == "RaySampler with 2 worker(s) x 1 env(s) on 2 node(s)"


def _exit_on_seed(doomed: int, env, policy, seed: int):
    """A rollout whose worker dies without clean-up (like a crash) on seed `doomed`."""
    if seed == doomed:
        os._exit(3)
    return rollout(env, policy, seed)


@pytest.mark.parametrize("backend", ["process", "ray"])
def test_a_dead_worker_loses_only_its_episode_and_is_replaced(backend, request, policy):
    sampler = request.getfixturevalue(f"{backend}_sampler")
    expected = sampler.sample(policy, [20, 22, 23])
    with pytest.warns(RuntimeWarning, match=r"died \(.*\) while running job 21: that episode is lost"):
        got = sampler.map(partial(_exit_on_seed, 21), policy, [20, 21, 22, 23])
    _assert_same_trajectories(got, expected)
    _assert_same_trajectories(sampler.sample(policy, [20, 22, 23]), expected)  # the replacement works
    if backend == "process":  # the same scheduling code on both backends: one check suffices
        with pytest.warns(RuntimeWarning), pytest.raises(DexdrakeError, match="every job's worker died"):
            sampler.map(partial(_exit_on_seed, 24), policy, [24])


def test_cli_address_needs_the_ray_backend(tmp_path, capsys):
    out = tmp_path / "d"
    assert main(["train", "dagger", "--out", str(out), "--objects", OBJECT, "--address", "auto"]) == 2
    assert "a cluster address needs the 'ray' backend, not 'process'" in capsys.readouterr().err
    assert not out.exists()
