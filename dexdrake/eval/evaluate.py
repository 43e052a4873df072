"""Per-object success of a policy checkpoint, in the layout of the paper's Table I.

The protocol: every object of the split (seen = every training object, unseen = all unseen
objects), N >= 10 episodes each with seeds S..S+N-1 taken from one part of the range
reserved for evaluation (`eval.seeds`: validation for choices, test for a shipped policy's
tables, custom for older blocks; the report names it, or says the seeds are not reserved),
deterministic mean actions and the paper's evaluation length of
100 control steps. The hand and feature set come from the policy. Rates carry 95 % Wilson
intervals, per object and per object category (the library's; UNKNOWN_CATEGORY for an object
it does not hold). Episodes run in worker processes (spawn/forkserver: a script calling
`evaluate_policy` with workers > 1 needs a `if __name__ == "__main__":` guard), each stepping
the episodes of up to `envs_per_worker` objects in lockstep with one policy call per step
(one env per object, as with one episode at a time).
"""

from __future__ import annotations

import multiprocessing as mp
import signal
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from dexdrake.episode import EpisodeResult, run_episode, run_lockstep
from dexdrake.errors import DexdrakeError, UnknownNameError
from dexdrake.eval.paper import PAPER_AVERAGE
from dexdrake.eval.seeds import seed_range
from dexdrake.learn.env_protocol import PolicyEnvFactory

EVAL_HORIZON = 100  # control steps per evaluation episode (paper)
Z_95 = 1.959963984540054  # standard normal quantile for a two-sided 95 % interval
UNKNOWN_CATEGORY = "unknown"  # the category of an object the object library does not hold


def wilson_interval(successes: int, trials: int, z: float = Z_95) -> tuple[float, float]:
    """The Wilson score interval (low, high) for a binomial proportion, as fractions in [0, 1]."""
    if trials < 1 or not 0 <= successes <= trials:
        raise DexdrakeError(f"need 0 <= successes <= trials and trials >= 1, got {successes}/{trials}")
    p = successes / trials
    denom = 1 + z * z / trials
    centre = (p + z * z / (2 * trials)) / denom
    half = z * ((p * (1 - p) / trials + z * z / (4 * trials * trials)) ** 0.5) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def pool_by_category(counts: Iterable[tuple[str, str, int, int]]) -> dict[str, tuple[list[str], int, int]]:
    """Per category, sorted by name: (its objects, successes, episodes), summed over the
    (object, category, successes, episodes) of each object."""
    pooled: dict[str, tuple[list[str], int, int]] = {}
    for name, category, wins, runs in counts:
        objects, w, n = pooled.get(category, ([], 0, 0))
        pooled[category] = ([*objects, name], w + wins, n + runs)
    return dict(sorted(pooled.items()))


def object_categories(objects: Iterable[str]) -> dict[str, str]:
    """Object -> its category in the object library, UNKNOWN_CATEGORY where it holds no such object."""
    from dexdrake.objects.library import get_object

    def category(name: str) -> str:
        try:
            return get_object(name).category
        except UnknownNameError:
            return UNKNOWN_CATEGORY

    return {name: category(name) for name in objects}


@dataclass
class EvalReport:
    """All episodes of one evaluation and what made them."""

    policy: str
    label: str  # "seen" | "unseen" | "selected"
    objects: list[str]
    episodes_per_object: int
    seed: int
    horizon: int
    command: str = ""
    wall_s: float = 0.0
    workers: int = 1
    envs_per_worker: int = 1
    hand: str = ""  # from the policy
    feature_set: str = ""  # from the policy
    episodes: list[EpisodeResult] = field(default_factory=list)
    categories: dict[str, str] = field(default_factory=dict)  # object -> category; absent: UNKNOWN_CATEGORY

    def per_object(self) -> dict[str, dict[str, float]]:
        """{object: {"successes", "episodes", "success_pct", "ci95_pct", "mean_max_lift"}} in object order."""
        out: dict[str, dict[str, float]] = {}
        for name in self.objects:
            eps = [e for e in self.episodes if e.object == name]
            if not eps:
                raise DexdrakeError(f"evaluation has no episode of object {name!r}")
            wins = sum(e.success for e in eps)
            out[name] = {
                "successes": wins,
                "episodes": len(eps),
                "success_pct": 100.0 * wins / len(eps),
                "ci95_pct": [100.0 * x for x in wilson_interval(wins, len(eps))],
                "mean_max_lift": float(np.mean([e.max_lift for e in eps])),
            }
        return out

    def per_category(self) -> dict[str, dict[str, Any]]:
        """{category: {"objects", "successes", "episodes", "success_pct", "ci95_pct"}}, sorted by
        category: the episodes of its objects pooled."""
        pooled = pool_by_category((name, self.categories.get(name, UNKNOWN_CATEGORY), int(r["successes"]),
                                   int(r["episodes"])) for name, r in self.per_object().items())
        return {category: {"objects": objects, "successes": wins, "episodes": runs,
                           "success_pct": 100.0 * wins / runs,
                           "ci95_pct": [100.0 * x for x in wilson_interval(wins, runs)]}
                for category, (objects, wins, runs) in pooled.items()}

    def average_pct(self) -> float:
        """Mean over objects of the per-object success rate (%), as in the paper's tables."""
        return float(np.mean([row["success_pct"] for row in self.per_object().values()]))

    def average_ci95_pct(self) -> tuple[float, float]:
        """95 % Wilson interval (%) of the average: all episodes pooled (equal episodes per object)."""
        low, high = wilson_interval(sum(e.success for e in self.episodes), len(self.episodes))
        return 100.0 * low, 100.0 * high

    def placement_ci95_pct(self, draws: int = 2000) -> tuple[float, float] | None:
        """95 % interval (%) of the average when the placements are resampled too: every object
        runs the same seeds, so the same N placements (a seed fixes the placement), and the
        pooled episodes are not independent. A percentile bootstrap over the N seeds (each draw
        averages N seeds drawn with replacement; fixed generator). None with one seed."""
        seeds = sorted({e.seed for e in self.episodes})
        if len(seeds) < 2:
            return None
        rate = np.array([np.mean([e.success for e in self.episodes if e.seed == s]) for s in seeds])
        means = rate[np.random.default_rng(0).integers(len(seeds), size=(draws, len(seeds)))].mean(axis=1)
        return 100.0 * float(np.quantile(means, 0.025)), 100.0 * float(np.quantile(means, 0.975))

    def seeds_text(self) -> str:
        return f"{self.seed}..{self.seed + self.episodes_per_object - 1}"

    def seed_range(self) -> str | None:
        """'validation', 'test' or 'custom' (eval.seeds); None: not seeds reserved for evaluation."""
        return seed_range(self.seed, self.episodes_per_object)

    def seeds_reserved(self) -> bool:
        """The seeds lie in the range reserved for evaluation (disjoint from training seeds)."""
        return self.seed_range() is not None

    def paper_average(self) -> float | None:
        return PAPER_AVERAGE.get(self.label)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["per_object"] = self.per_object()
        d["per_category"] = self.per_category()
        d["average_pct"] = self.average_pct()
        d["average_ci95_pct"] = list(self.average_ci95_pct())
        d["seeds_reserved_for_evaluation"] = self.seeds_reserved()
        d["seed_range"] = self.seed_range()
        return d


def mean_actor(policy) -> Callable[[np.ndarray], np.ndarray]:
    """The policy's deterministic (mean) action for an observation, as `run_episode`'s `act`."""
    return lambda observation: policy.act(np.asarray(observation, dtype=np.float32))[0]


class _EpisodeRunner:
    """Holds the policy and one single-object env per object name (built on first use)."""

    def __init__(self, policy_path: str, horizon: int, env_factory_for: PolicyEnvFactory,
                 record: Callable[[Any], dict[str, Callable]] | None = None):
        import torch

        from dexdrake.learn.policy import load_policy

        torch.set_num_threads(1)
        self.policy, _ = load_policy(policy_path)
        self.horizon = horizon
        self.env_factory_for = env_factory_for
        self.record = record
        self._envs: dict[str, Any] = {}

    def env(self, name: str) -> Any:
        if name not in self._envs:
            from dexdrake.learn.samplers import check_env_matches

            env = self.env_factory_for(self.policy.config, [name], self.horizon)()
            check_env_matches(env, self.policy)
            self._envs[name] = env
        return self._envs[name]

    def __call__(self, group: tuple[tuple[str, int], ...]) -> list[EpisodeResult]:
        """The episodes of `group` ((object, seed) pairs of distinct objects), in lockstep."""
        if self.record is not None:
            return [run_episode(self.env(name), mean_actor(self.policy), seed, self.horizon,
                                **self.record(self.env(name))) for name, seed in group]

        def act(observations: list[np.ndarray], live: list[int]) -> np.ndarray:
            return self.policy.act_batch(np.asarray(observations, dtype=np.float32), [None] * len(live))[0]

        return run_lockstep([self.env(name) for name, _ in group], act, [seed for _, seed in group], self.horizon)


_RUNNER: _EpisodeRunner | None = None


def _init_worker(policy_path: str, horizon: int, env_factory_for: PolicyEnvFactory) -> None:
    global _RUNNER
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    _RUNNER = _EpisodeRunner(policy_path, horizon, env_factory_for)


def _run_in_worker(group: tuple[tuple[str, int], ...]) -> list[EpisodeResult]:
    if _RUNNER is None:
        raise DexdrakeError("evaluation worker was not initialised")
    return _RUNNER(group)


def evaluate_policy(
    policy_path: str | Path,
    env_factory_for: PolicyEnvFactory,
    objects: list[str],
    episodes: int,
    seed: int = 0,
    workers: int = 1,
    horizon: int = EVAL_HORIZON,
    label: str = "selected",
    command: str = "",
    progress: bool = True,
    record: Callable[[Any], dict[str, Callable]] | None = None,
    envs_per_worker: int = 1,
) -> EvalReport:
    """Run `episodes` seeded episodes per object (seeds seed..seed+episodes-1) of a checkpoint,
    in envs from `env_factory_for` (picklable: worker processes call it too), the same seed's
    episodes of up to `envs_per_worker` objects in lockstep (results do not depend on it).
    `record(env)` returns the `on_reset`/`on_step` hooks of `run_episode` that log the env's
    episodes (e.g. RerunLogger.hooks; one worker, one episode at a time)."""
    from dexdrake.learn.policy import load_policy

    if episodes < 1 or workers < 1 or horizon < 1:
        raise DexdrakeError(f"episodes, workers and horizon must be >= 1 (got {episodes}, {workers}, {horizon})")
    if not objects:
        raise DexdrakeError("no objects to evaluate")
    if envs_per_worker < 1:
        raise DexdrakeError(f"envs_per_worker must be >= 1 (got {envs_per_worker})")
    if record is not None and workers > 1:
        raise DexdrakeError("a recorded evaluation runs in one process: use --workers 1 with --rrd")
    policy, _ = load_policy(policy_path)  # fail early, in this process, on a bad checkpoint
    env_factory_for(policy.config, objects, horizon)
    jobs = [(name, seed + i) for name in objects for i in range(episodes)]
    k = 1 if record is not None else min(envs_per_worker, len(objects))
    by_seed = [(name, seed + i) for i in range(episodes) for name in objects]  # k in a row: distinct objects
    groups = [tuple(by_seed[i:i + k]) for i in range(0, len(by_seed), k)]
    report = EvalReport(str(policy_path), label, list(objects), episodes, seed, horizon, command, workers=workers,
                        envs_per_worker=k, hand=policy.config.hand, feature_set=policy.config.feature_set,
                        categories=object_categories(objects))
    bar = tqdm(total=len(jobs), desc=f"eval {label}", unit="episode", disable=not progress)
    start = time.perf_counter()
    try:  # the bar's line ends before any message that follows (an error, Ctrl-C)
        if workers == 1:
            runner = _EpisodeRunner(str(policy_path), horizon, env_factory_for, record)
            for group in groups:
                report.episodes.extend(runner(group))
                bar.update(len(group))
        else:
            method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
            previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # the workers inherit it: Ctrl-C is ours
            try:
                pool = ProcessPoolExecutor(workers, mp.get_context(method), initializer=_init_worker,
                                           initargs=(str(policy_path), horizon, env_factory_for))
                futures = [pool.submit(_run_in_worker, group) for group in groups]
            finally:
                signal.signal(signal.SIGINT, previous)
            try:
                for fut in as_completed(futures):
                    results = fut.result()
                    report.episodes.extend(results)
                    bar.update(len(results))
            except BaseException as exc:  # Ctrl-C or an error: drop the queued jobs, end the running ones
                running = list(pool._processes.values())
                pool.shutdown(wait=False, cancel_futures=True)
                for process in running:
                    process.terminate()
                if isinstance(exc, BrokenProcessPool):
                    raise DexdrakeError("an evaluation worker died; rerun with --workers 1 to see the error") from exc
                raise
            pool.shutdown()
    finally:
        bar.close()
    report.wall_s = time.perf_counter() - start
    order = {job: k for k, job in enumerate(jobs)}
    report.episodes.sort(key=lambda e: order[(e.object, e.seed)])
    return report
