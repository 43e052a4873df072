"""Seeded episodes on a pool of workers: in-process, in local worker processes, or on Ray actors.

One abstraction serves DAPG sampling (`Sampler.sample`: policy rollouts) and DAgger
collection (`Sampler.map` with DAgger's episode function). `map` hands the jobs out one at
a time to whichever worker is free. Every worker builds its env once from the picklable
EnvFactory and keeps it (Drake diagrams do not pickle); it receives the policy as bytes
(config + state dict) only when the policy changed. A job's result depends only on the job
and the policy (env reset and noise are seeded by it), so every backend returns the same
results, in job order.

A worker that dies (a crash, out of memory, a lost Ray node) loses only the job it was
running: a RuntimeWarning names the job, a fresh worker replaces the dead one and `map`
returns the other jobs' results. An exception raised by an episode is a bug and propagates.

The process backend uses the 'forkserver' (default on Linux) or 'spawn' start method, so
a script that uses it must guard its entry point with `if __name__ == "__main__":`.
"""

from __future__ import annotations

import io
import math
import multiprocessing as mp
import os
import signal
import time
import traceback
import uuid
import warnings
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from multiprocessing.connection import Connection, wait
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from dexdrake.episode import run_lockstep
from dexdrake.errors import DexdrakeError
from dexdrake.learn.env_protocol import Env, EnvFactory, observation_dim
from dexdrake.learn.policy import DexRepNetPolicy, policy_from_payload, policy_payload
from dexdrake.learn.trajectory import Trajectory

BACKENDS = ("sequential", "process", "ray")
# envs a worker steps in lockstep by default (scripts/bench_rollout.py measures K = 1 and 8)
ENVS_PER_WORKER = 8

Episode = Callable[[Env, DexRepNetPolicy | None, Any], Any]
"""episode(env, policy, job) -> result; must be picklable (a top-level function or a partial of one)."""


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
    """Run one episode of at most env.horizon steps (the one episode loop, dexdrake/episode.py);
    seed drives env.reset and action noise."""
    return rollout_lockstep([env], policy, [seed], deterministic)[0]


def rollout_lockstep(envs: Sequence[Env], policy: DexRepNetPolicy, seeds: Sequence[int],
                     deterministic: bool = False) -> list[Trajectory]:
    """One episode per (env, seed), all stepped in lockstep with one policy call per step for
    the envs still running; each trajectory is the one `rollout(env, policy, seed)` gives."""
    rngs = [None if deterministic else np.random.default_rng(seed) for seed in seeds]
    d = policy.config.obs_dim
    runs = [_Recording(int(seed)) for seed in seeds]

    def act(observations: list[np.ndarray], live: list[int]) -> np.ndarray:
        obs = np.asarray(observations, dtype=np.float32)
        for k, o in zip(live, obs):
            if o.shape != (d,) or not np.all(np.isfinite(o)):
                raise DexdrakeError(
                    f"env returned a bad observation at step {len(runs[k].actions)} of seed {runs[k].seed}: shape "
                    f"{o.shape} (expected ({d},)) or non-finite values"
                )
        actions, log_probs = policy.act_batch(obs, [rngs[k] for k in live])
        for k, o, a, lp in zip(live, obs, actions, log_probs):
            runs[k].observations.append(o)
            runs[k].actions.append(a)
            runs[k].log_probs.append(float(lp))
        return actions

    def record(k: int, reward: float, info: dict) -> None:
        if not math.isfinite(reward):
            raise DexdrakeError(f"env returned a non-finite reward {reward} at step {len(runs[k].rewards)} of seed "
                                f"{runs[k].seed}")
        runs[k].rewards.append(float(reward))

    results = run_lockstep(envs, act, seeds, on_step=record)
    return [run.trajectory(result.success, result.steps < env.horizon)
            for run, result, env in zip(runs, results, envs)]


@dataclass
class _Recording:
    """What `rollout_lockstep` records of one episode, step by step."""

    seed: int
    observations: list = field(default_factory=list)
    actions: list = field(default_factory=list)
    rewards: list = field(default_factory=list)
    log_probs: list = field(default_factory=list)

    def trajectory(self, success: bool, terminated: bool) -> Trajectory:
        return Trajectory(
            seed=self.seed,
            observations=np.asarray(self.observations, dtype=np.float32),
            actions=np.asarray(self.actions, dtype=np.float32),
            rewards=np.asarray(self.rewards, dtype=np.float64),
            log_probs=np.asarray(self.log_probs, dtype=np.float64),
            success=success,
            terminated=terminated,
        )


def rollout_job(deterministic: bool, envs: list[Env], policy: DexRepNetPolicy | None,
                seeds: tuple[int, ...]) -> list[Trajectory]:
    """`rollout_lockstep` as a Lockstep episode (jobs = seeds), with `deterministic` bound first."""
    if policy is None:
        raise DexdrakeError("a policy rollout needs a policy")
    return rollout_lockstep(envs, policy, seeds, deterministic)


@dataclass(frozen=True)
class Lockstep:
    """A job of jobs: a worker runs them together on its first len(jobs) envs with one call
    episode(envs, policy, jobs) -> one result per job (e.g. `rollout_job`)."""

    jobs: tuple


def policy_to_bytes(policy: DexRepNetPolicy) -> bytes:
    """The policy as checkpoint bytes (what workers receive)."""
    buf = io.BytesIO()
    torch.save(policy_payload(policy), buf)
    return buf.getvalue()


class RolloutWorker:
    """Holds one env (built on first use, then kept) and the most recent policy; runs episode jobs."""

    def __init__(self, env_factory: EnvFactory, single_thread: bool = True):
        if single_thread:  # one torch thread per worker; the workers are the parallelism
            torch.set_num_threads(1)
        self._factory = env_factory
        self._envs: list[Env] = []
        self._policy_key: str | None = None
        self._policy: DexRepNetPolicy | None = None

    @property
    def env(self) -> Env:
        return self.envs(1)[0]

    def envs(self, k: int) -> list[Env]:
        """The worker's first k envs (built on first use, then kept)."""
        while len(self._envs) < k:
            self._envs.append(self._factory())
        return self._envs[:k]

    def run(self, episode: Episode, job: Any, policy_key: str, policy_bytes: bytes | None) -> tuple[Any, float]:
        """(episode(env, policy, job), CPU seconds this process spent on it); the policy is
        (re)loaded from `policy_bytes` when `policy_key` changed."""
        start = time.process_time()
        if policy_key != self._policy_key:
            self._policy = None
            if policy_bytes is not None:
                payload = torch.load(io.BytesIO(policy_bytes), map_location="cpu", weights_only=True)
                self._policy = policy_from_payload(payload).eval()
                check_env_matches(self.env, self._policy)
            self._policy_key = policy_key
        if isinstance(job, Lockstep):
            result = episode(self.envs(len(job.jobs)), self._policy, job.jobs)
        else:
            result = episode(self.env, self._policy, job)
        return result, time.process_time() - start


@contextmanager
def single_torch_thread() -> Iterator[None]:
    """Batch-1 inference is fastest on one thread (and avoids oversubscribed cores)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


class Sampler(ABC):
    """Runs episode jobs on `num_workers` workers, each holding its own env.

    `episode_cpu_s` adds up the CPU seconds the workers spent on finished jobs (env builds
    and policy loads included), for rates per CPU-second.
    """

    num_workers: int
    envs_per_worker: int = 1
    episode_cpu_s: float = 0.0

    @abstractmethod
    def map(self, episode: Episode, policy: DexRepNetPolicy | None, jobs: Sequence[Any],
            desc: str | None = None) -> list[Any]:
        """episode(env, policy, job) for every job, results in job order; a job whose worker died
        is left out (with a warning). `desc` labels a progress bar (none when None)."""

    def map_lockstep(self, episode: Episode, policy: DexRepNetPolicy | None, jobs: Sequence[Any],
                     desc: str | None = None) -> list[Any]:
        """`map` for a Lockstep episode: the jobs in groups of at most `envs_per_worker`, each
        group run together on one worker; as many groups as a multiple of the workers, of equal
        sizes (within one), so the workers finish together; results flattened in job order (a
        dead worker's group is lost). A job's result does not depend on its group."""
        if not jobs:
            return []
        count = -(-len(jobs) // self.envs_per_worker)
        count = -(-count // self.num_workers) * self.num_workers
        bounds = np.linspace(0, len(jobs), min(count, len(jobs)) + 1).round().astype(int)
        groups = [Lockstep(tuple(jobs[a:b])) for a, b in zip(bounds[:-1], bounds[1:])]
        return [r for results in self.map(episode, policy, groups, desc) for r in results]

    def sample(self, policy: DexRepNetPolicy, seeds: Sequence[int], deterministic: bool = False) -> list[Trajectory]:
        """One rollout of `policy` per seed (`envs_per_worker` of them in lockstep per worker)."""
        return self.map_lockstep(partial(rollout_job, deterministic), policy, list(seeds))

    def describe(self) -> str:
        """One line for logs: the backend and its workers."""
        return f"{type(self).__name__} with {self.num_workers} worker(s) x {self.envs_per_worker} env(s)"

    def _set_envs_per_worker(self, k: int) -> None:
        if k < 1:
            raise DexdrakeError(f"envs_per_worker must be >= 1, got {k}")
        self.envs_per_worker = k

    def close(self) -> None:
        """Stop the workers."""

    def __enter__(self) -> Sampler:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class SequentialSampler(Sampler):
    """Episodes one after another in this process (debugging, CI)."""

    num_workers = 1

    def __init__(self, env_factory: EnvFactory, envs_per_worker: int = 1):
        self._set_envs_per_worker(envs_per_worker)
        self._factory = env_factory
        self._worker: RolloutWorker | None = None

    def map(self, episode: Episode, policy: DexRepNetPolicy | None, jobs: Sequence[Any],
            desc: str | None = None) -> list[Any]:
        if self._worker is None:
            self._worker = RolloutWorker(self._factory, single_thread=False)
        start = time.process_time()
        worker = self._worker
        if policy is not None:
            check_env_matches(worker.env, policy)
        with single_torch_thread():
            results = [episode(worker.envs(len(job.jobs)), policy, job.jobs) if isinstance(job, Lockstep)
                       else episode(worker.env, policy, job)
                       for job in tqdm(jobs, desc=desc, unit="episode", disable=desc is None)]
        self.episode_cpu_s += time.process_time() - start
        return results

    def close(self) -> None:
        self._worker = None


class WorkerDied(Exception):
    """A worker process or actor ended while it ran a job."""


@dataclass(eq=False)
class _Worker:
    handle: Any  # backend-specific: a (process, connection) pair or a Ray actor
    location: str  # where it runs, for messages: a pid, or a Ray node id
    policy_key: str | None = None  # the policy it holds


class _WorkerPool(Sampler):
    """The scheduling shared by the process and Ray backends: one job per free worker, dead
    workers replaced. Subclasses start, stop and talk to workers."""

    def __init__(self, num_workers: int, envs_per_worker: int = 1):
        if num_workers < 1:
            raise DexdrakeError(f"num_workers must be >= 1, got {num_workers}")
        self._set_envs_per_worker(envs_per_worker)
        self.num_workers = num_workers
        self._workers = self._start(num_workers)

    @abstractmethod
    def _start(self, n: int) -> list[_Worker]: ...

    @abstractmethod
    def _stop(self, worker: _Worker) -> None: ...

    @abstractmethod
    def _share(self, blob: bytes) -> Any:
        """The policy bytes in the form _submit passes on (sent once per map call where possible)."""

    @abstractmethod
    def _submit(self, worker: _Worker, episode: Episode, job: Any, key: str, blob: Any) -> Any:
        """Start `job` on the idle `worker`; returns a hashable token for _wait and _result."""

    @abstractmethod
    def _wait(self, tokens: list[Any]) -> list[Any]:
        """Blocks until at least one token is done; returns the done ones."""

    @abstractmethod
    def _result(self, token: Any) -> Any:
        """(the job's result, the worker's CPU seconds on it); raises WorkerDied if the worker
        died, or the episode's exception."""

    def map(self, episode: Episode, policy: DexRepNetPolicy | None, jobs: Sequence[Any],
            desc: str | None = None) -> list[Any]:
        key, blob = ("none", None) if policy is None else (uuid.uuid4().hex, self._share(policy_to_bytes(policy)))
        results: dict[int, Any] = {}
        todo, running, idle = deque(range(len(jobs))), {}, list(self._workers)
        with tqdm(total=len(jobs), desc=desc, unit="episode", disable=desc is None) as bar:
            while todo or running:
                while idle and todo:
                    worker, i = idle.pop(), todo.popleft()
                    running[self._submit(worker, episode, jobs[i], key, blob if worker.policy_key != key else None)] = (worker, i)
                    worker.policy_key = key
                for token in self._wait(list(running)):
                    worker, i = running.pop(token)
                    try:
                        results[i], cpu_s = self._result(token)
                        self.episode_cpu_s += cpu_s
                    except WorkerDied as exc:
                        idle.append(self._replace(worker, exc, jobs[i]))
                    except Exception:
                        self._drain(running, jobs)
                        raise
                    else:
                        idle.append(worker)
                    bar.update()
        if jobs and not results:
            raise DexdrakeError(f"every job's worker died ({len(jobs)} jobs); see the warnings above")
        return [results[i] for i in sorted(results)]

    def _replace(self, dead: _Worker, exc: WorkerDied, job: Any) -> _Worker:
        warnings.warn(f"rollout worker {dead.location} died ({exc}) while running job {job!r}: that episode is "
                      "lost, a new worker replaces it and the run continues", RuntimeWarning, stacklevel=2)
        self._stop(dead)
        fresh = self._start(1)[0]
        self._workers[self._workers.index(dead)] = fresh
        return fresh

    def _drain(self, running: dict[Any, tuple[_Worker, int]], jobs: Sequence[Any]) -> None:
        """Wait out the jobs still running (results dropped) so no stale reply is left behind."""
        while running:
            for token in self._wait(list(running)):
                worker, i = running.pop(token)
                try:
                    self._result(token)
                except WorkerDied as exc:
                    self._replace(worker, exc, jobs[i])
                except Exception:
                    pass  # the first error is the one raised

    def close(self) -> None:
        for worker in self._workers:
            self._stop(worker)
        self._workers: list[_Worker] = []


def _process_worker_main(conn: Connection, env_factory: EnvFactory) -> None:
    """A worker process: run (episode, job, key, blob) messages until None or a closed pipe."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    worker = RolloutWorker(env_factory)
    while True:
        try:
            message = conn.recv()
        except EOFError:
            return
        if message is None:
            return
        try:
            reply = (True, worker.run(*message))
        except Exception as exc:
            exc.add_note(f"(in rollout worker process {os.getpid()})\n{traceback.format_exc()}")
            reply = (False, exc)
        try:
            conn.send(reply)
        except Exception:  # an exception that does not pickle
            conn.send((False, DexdrakeError(f"rollout worker process {os.getpid()}:\n{traceback.format_exc()}")))


# Imported once by the forkserver (with the module of the env factory's class), before any
# thread starts, so each worker starts in a fraction of a second instead of importing torch,
# Drake, Open3D and the mesh stack the object geometry loads with itself (~3 CPU-s).
PRELOAD = ("torch", "pydrake.all", "open3d", "trimesh", "scipy.spatial")


class ProcessSampler(_WorkerPool):
    """Episodes in `num_workers` local processes, each holding its own env."""

    def __init__(self, env_factory: EnvFactory, num_workers: int = 2, start_method: str | None = None,
                 envs_per_worker: int = 1):
        method = start_method or ("forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn")
        if method not in ("forkserver", "spawn"):
            raise DexdrakeError(f"start_method must be 'forkserver' or 'spawn' (Drake and torch are not fork-safe), got {method!r}")
        self._ctx = mp.get_context(method)
        if method == "forkserver":  # workers fork from a server that has imported the stack once
            self._ctx.set_forkserver_preload([*PRELOAD, type(env_factory).__module__])
        self._factory = env_factory
        super().__init__(num_workers, envs_per_worker)

    def _start(self, n: int) -> list[_Worker]:
        workers = []
        for _ in range(n):
            conn, child = self._ctx.Pipe()
            process = self._ctx.Process(target=_process_worker_main, args=(child, self._factory), daemon=True)
            process.start()
            child.close()
            workers.append(_Worker((process, conn), f"pid {process.pid}"))
        return workers

    def _stop(self, worker: _Worker) -> None:
        process, conn = worker.handle
        try:
            conn.send(None)
        except OSError:
            pass  # already gone
        process.join(timeout=5)
        if process.is_alive():
            process.terminate()
            process.join()
        conn.close()

    def _share(self, blob: bytes) -> bytes:
        return blob

    def _submit(self, worker: _Worker, episode: Episode, job: Any, key: str, blob: Any) -> _Worker:
        worker.handle[1].send((episode, job, key, blob))
        return worker

    def _wait(self, tokens: list[_Worker]) -> list[_Worker]:
        by_conn = {w.handle[1]: w for w in tokens}
        return [by_conn[c] for c in wait(list(by_conn))]

    def _result(self, token: _Worker) -> Any:
        process, conn = token.handle
        try:
            ok, value = conn.recv()
        except (EOFError, OSError):
            process.join(timeout=5)
            raise WorkerDied(f"exit code {process.exitcode}") from None
        if not ok:
            raise value
        return value


class _RayRolloutWorker(RolloutWorker):
    def node_id(self) -> str:
        import ray

        return ray.get_runtime_context().get_node_id()


class RaySampler(_WorkerPool):
    """Episodes on `num_workers` Ray actors of one CPU each (needs the optional `ray` extra).

    Joins the running Ray instance, else the cluster at `address` (e.g. "auto" or
    "HEAD_IP:6379"), else starts a local one.
    """

    def __init__(self, env_factory: EnvFactory, num_workers: int = 2, address: str | None = None,
                 envs_per_worker: int = 1):
        try:
            import ray
        except ImportError as exc:
            raise DexdrakeError("the Ray backend needs `pip install dexdrake[ray]`") from exc
        self._ray, self._factory, self._owns_ray = ray, env_factory, not ray.is_initialized()
        self._workers: list[_Worker] = []
        if self._owns_ray:
            local = {} if address else {"num_cpus": max(num_workers, os.cpu_count() or 1), "include_dashboard": False}
            try:
                ray.init(address=address, **local)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                raise DexdrakeError(f"cannot join the Ray cluster at {address!r}: {exc}") from exc
        cpus = ray.cluster_resources().get("CPU", 0)
        if cpus < num_workers:
            self.close()
            raise DexdrakeError(f"the Ray cluster has {cpus:g} CPUs; {num_workers} workers need one each")
        self._actor_cls = ray.remote(num_cpus=1)(_RayRolloutWorker)
        super().__init__(num_workers, envs_per_worker)

    def _start(self, n: int) -> list[_Worker]:
        actors = [self._actor_cls.remote(self._factory) for _ in range(n)]
        nodes = self._ray.get([a.node_id.remote() for a in actors])
        return [_Worker(actor, f"on Ray node {node}") for actor, node in zip(actors, nodes)]

    def _stop(self, worker: _Worker) -> None:
        self._ray.kill(worker.handle)

    def _share(self, blob: bytes) -> Any:
        return self._ray.put(blob)

    def _submit(self, worker: _Worker, episode: Episode, job: Any, key: str, blob: Any) -> Any:
        return worker.handle.run.remote(episode, job, key, blob)

    def _wait(self, tokens: list[Any]) -> list[Any]:
        return self._ray.wait(tokens, num_returns=1)[0]

    def _result(self, token: Any) -> Any:
        try:
            return self._ray.get(token)
        except self._ray.exceptions.RayActorError as exc:
            raise WorkerDied(type(exc).__name__) from None
        except self._ray.exceptions.RayTaskError as exc:  # a user's mistake: its own one line
            if isinstance(exc.cause, DexdrakeError):
                raise exc.cause from None
            raise

    def describe(self) -> str:
        return (f"RaySampler with {self.num_workers} worker(s) x {self.envs_per_worker} env(s) on "
                f"{len({w.location for w in self._workers})} node(s)")

    def close(self) -> None:
        super().close()
        if self._owns_ray and self._ray.is_initialized():
            self._ray.shutdown()


def check_backend(backend: str, address: str | None = None) -> None:
    """Raise unless `backend` is one of BACKENDS and `address` is None or used with Ray."""
    if backend not in BACKENDS:
        raise DexdrakeError(f"unknown sampler backend {backend!r}; valid: {', '.join(BACKENDS)}")
    if address is not None and backend != "ray":
        raise DexdrakeError(f"a cluster address needs the 'ray' backend, not {backend!r}")


def make_sampler(env_factory: EnvFactory, backend: str = "process", num_workers: int = 2,
                 address: str | None = None, envs_per_worker: int = ENVS_PER_WORKER) -> Sampler:
    """A sampler for `backend` in BACKENDS; `address` (Ray only) joins an existing Ray cluster;
    each worker steps `envs_per_worker` envs in lockstep for Lockstep episodes."""
    check_backend(backend, address)
    if backend == "sequential":
        return SequentialSampler(env_factory, envs_per_worker)
    if backend == "process":
        return ProcessSampler(env_factory, num_workers, envs_per_worker=envs_per_worker)
    return RaySampler(env_factory, num_workers, address, envs_per_worker)
