"""Seeded policy rollouts: in-process, in local worker processes, or on Ray actors.

Every worker builds its env once from the picklable EnvFactory and keeps it (Drake
diagrams do not pickle). The policy travels as serialised bytes (config + state dict) with
each batch of seeds; rollout i is fully determined by seeds[i] (env reset and action
noise), so all backends return identical trajectories for the same seeds and policy.

The process backend uses the 'forkserver' (default on Linux) or 'spawn' start method, so
a script that uses it must guard its entry point with `if __name__ == "__main__":`.
"""

from __future__ import annotations

import io
import math
import multiprocessing as mp
import uuid
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Protocol

import numpy as np
import torch

from dexdrake.errors import DexdrakeError
from dexdrake.learn.env_protocol import Env, EnvFactory, observation_dim
from dexdrake.learn.policy import DexRepNetPolicy, policy_from_payload, policy_payload
from dexdrake.learn.trajectory import Trajectory

BACKENDS = ("sequential", "process", "ray")


def check_env_matches(env: Env, policy: DexRepNetPolicy) -> None:
    """Raise if the env's observation blocks or action size differ from the policy's."""
    blocks = dict(env.observation_blocks)
    observation_dim(blocks)
    if list(blocks.items()) != [tuple(b) for b in policy.config.blocks] or env.action_dim != policy.config.action_dim:
        raise DexdrakeError(
            f"env (blocks {blocks}, action_dim {env.action_dim}) does not match the policy "
            f"(blocks {dict(policy.config.blocks)}, action_dim {policy.config.action_dim})"
        )


def rollout(env: Env, policy: DexRepNetPolicy, seed: int, deterministic: bool = False) -> Trajectory:
    """Run one episode of at most env.horizon steps; seed drives env.reset and action noise."""
    rng = None if deterministic else np.random.default_rng(seed)
    obs = np.asarray(env.reset(int(seed)), dtype=np.float32)
    d = policy.config.obs_dim
    observations, actions, rewards, log_probs = [], [], [], []
    success = terminated = False
    for t in range(env.horizon):
        if obs.shape != (d,) or not np.all(np.isfinite(obs)):
            raise DexdrakeError(
                f"env returned a bad observation at step {t} of seed {seed}: shape {obs.shape} "
                f"(expected ({d},)) or non-finite values"
            )
        action, logp = policy.act(obs, rng)
        next_obs, reward, done, info = env.step(action)
        if not math.isfinite(reward):
            raise DexdrakeError(f"env returned a non-finite reward {reward} at step {t} of seed {seed}")
        observations.append(obs)
        actions.append(action)
        rewards.append(float(reward))
        log_probs.append(logp)
        success = success or bool(info.get("success", False))
        obs = np.asarray(next_obs, dtype=np.float32)
        if done:
            terminated = t + 1 < env.horizon
            break
    return Trajectory(
        seed=int(seed),
        observations=np.asarray(observations, dtype=np.float32),
        actions=np.asarray(actions, dtype=np.float32),
        rewards=np.asarray(rewards, dtype=np.float64),
        log_probs=np.asarray(log_probs, dtype=np.float64),
        success=success,
        terminated=terminated,
    )


def policy_to_bytes(policy: DexRepNetPolicy) -> bytes:
    """The policy as checkpoint bytes (what workers receive)."""
    buf = io.BytesIO()
    torch.save(policy_payload(policy), buf)
    return buf.getvalue()


class RolloutWorker:
    """Holds one env (built once) and the most recent policy; runs seeded rollouts."""

    def __init__(self, env_factory: EnvFactory, single_thread: bool = True):
        if single_thread:  # one torch thread per worker; the workers are the parallelism
            torch.set_num_threads(1)
        self.env = env_factory()
        self._policy_key: str | None = None
        self._policy: DexRepNetPolicy | None = None

    def run(self, policy_key: str, policy_bytes: bytes, seeds: Sequence[int], deterministic: bool) -> list[Trajectory]:
        if policy_key != self._policy_key:
            payload = torch.load(io.BytesIO(policy_bytes), map_location="cpu", weights_only=True)
            self._policy = policy_from_payload(payload).eval()
            check_env_matches(self.env, self._policy)
            self._policy_key = policy_key
        assert self._policy is not None
        return [rollout(self.env, self._policy, s, deterministic) for s in seeds]


@contextmanager
def single_torch_thread() -> Iterator[None]:
    """Batch-1 inference is fastest on one thread (and avoids oversubscribed cores)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


class Sampler(Protocol):
    def sample(self, policy: DexRepNetPolicy, seeds: Sequence[int], deterministic: bool = False) -> list[Trajectory]: ...

    def close(self) -> None: ...


def _chunks(seeds: Sequence[int], n: int) -> list[list[int]]:
    size = max(1, math.ceil(len(seeds) / n))
    return [list(seeds[i : i + size]) for i in range(0, len(seeds), size)]


class SequentialSampler:
    """Rollouts one after another in this process (debugging, CI)."""

    def __init__(self, env_factory: EnvFactory):
        self._factory = env_factory
        self._worker: RolloutWorker | None = None

    def sample(self, policy: DexRepNetPolicy, seeds: Sequence[int], deterministic: bool = False) -> list[Trajectory]:
        if self._worker is None:
            self._worker = RolloutWorker(self._factory, single_thread=False)
        check_env_matches(self._worker.env, policy)
        with single_torch_thread():
            return [rollout(self._worker.env, policy, s, deterministic) for s in seeds]

    def close(self) -> None:
        self._worker = None

    def __enter__(self) -> SequentialSampler:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


_WORKER: RolloutWorker | None = None


def _init_process_worker(env_factory: EnvFactory) -> None:
    global _WORKER
    _WORKER = RolloutWorker(env_factory)


def _run_in_process_worker(key: str, policy_bytes: bytes, seeds: list[int], deterministic: bool) -> list[Trajectory]:
    if _WORKER is None:
        raise DexdrakeError("rollout worker process was not initialised")
    return _WORKER.run(key, policy_bytes, seeds, deterministic)


class ProcessSampler:
    """Rollouts in `num_workers` local processes, each holding its own env."""

    def __init__(self, env_factory: EnvFactory, num_workers: int = 2, start_method: str | None = None):
        if num_workers < 1:
            raise DexdrakeError(f"num_workers must be >= 1, got {num_workers}")
        method = start_method or ("forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn")
        if method not in ("forkserver", "spawn"):
            raise DexdrakeError(f"start_method must be 'forkserver' or 'spawn' (Drake and torch are not fork-safe), got {method!r}")
        self.num_workers = num_workers
        self._pool = ProcessPoolExecutor(
            max_workers=num_workers,
            mp_context=mp.get_context(method),
            initializer=_init_process_worker,
            initargs=(env_factory,),
        )

    def sample(self, policy: DexRepNetPolicy, seeds: Sequence[int], deterministic: bool = False) -> list[Trajectory]:
        key, blob = uuid.uuid4().hex, policy_to_bytes(policy)
        futures = [
            self._pool.submit(_run_in_process_worker, key, blob, chunk, deterministic)
            for chunk in _chunks(seeds, self.num_workers)
        ]
        try:
            return [traj for f in futures for traj in f.result()]
        except BrokenProcessPool as exc:
            raise DexdrakeError(
                "a rollout worker process died (crash or out of memory in the env factory or env); "
                "run with backend='sequential' to see the error in-process"
            ) from exc

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> ProcessSampler:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class RaySampler:
    """Rollouts on `num_workers` Ray actors (needs the optional `ray` extra)."""

    def __init__(self, env_factory: EnvFactory, num_workers: int = 2, **ray_init: Any):
        try:
            import ray
        except ImportError as exc:
            raise DexdrakeError("the Ray backend needs `pip install dexdrake[ray]`") from exc
        self._ray = ray
        if not ray.is_initialized():
            ray.init(**ray_init)
        actor_cls = ray.remote(num_cpus=1)(RolloutWorker)
        self._actors = [actor_cls.remote(env_factory) for _ in range(num_workers)]

    def sample(self, policy: DexRepNetPolicy, seeds: Sequence[int], deterministic: bool = False) -> list[Trajectory]:
        key = uuid.uuid4().hex
        blob = self._ray.put(policy_to_bytes(policy))
        refs = [
            actor.run.remote(key, blob, chunk, deterministic)
            for actor, chunk in zip(self._actors, _chunks(seeds, len(self._actors)))
        ]
        return [traj for part in self._ray.get(refs) for traj in part]

    def close(self) -> None:
        for actor in self._actors:
            self._ray.kill(actor)
        self._actors = []

    def __enter__(self) -> RaySampler:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def make_sampler(env_factory: EnvFactory, backend: str = "process", num_workers: int = 2) -> Sampler:
    """A sampler for `backend` in ("sequential", "process", "ray")."""
    if backend == "sequential":
        return SequentialSampler(env_factory)
    if backend == "process":
        return ProcessSampler(env_factory, num_workers)
    if backend == "ray":
        return RaySampler(env_factory, num_workers)
    raise DexdrakeError(f"unknown sampler backend {backend!r}; valid: {', '.join(BACKENDS)}")
