"""CLI `dexdrake demos replay`: replay retargeted demos in Drake into a behaviour-cloning dataset.

The dataset is the BC format of `dexdrake.learn.demo_dataset` (load it with
`load_demo_dataset(path)`); its metadata records the hand, feature set, observation blocks,
every demo's file, seed, placement and attempts, raw and after-sampling success rates per
object and per category, counts and the command line that made it.
Heavy imports (pydrake) happen inside the functions so `--help` stays quick.
"""

from __future__ import annotations

import argparse
import signal
import warnings
import zipfile
from collections import defaultdict
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from dexdrake import argtypes
from dexdrake.cli import flags
from dexdrake.errors import DexdrakeError, DexdrakeWarning

DATASET_FORMAT = "dexdrake.replay/1"


def add_parser(subparsers) -> None:
    """Add the `replay` sub-command to the `demos` parser's subparsers object."""
    p = subparsers.add_parser("replay", help="replay retargeted demos in Drake into a BC dataset")
    p.add_argument("--hand", required=True, help="hand name, e.g. adroit")
    p.add_argument("--demos", required=True, type=Path, help="folder of demo .npz files (demo format)")
    p.add_argument("--out", required=True, type=argtypes.output_file(".npz"), help="dataset .npz to write")
    p.add_argument("--feature-set", default=None, help="observation feature set, e.g. DexRep "
                   "(default: hand state [q; v] only)")
    p.add_argument("--attempts", type=argtypes.int_at_least(0), default=8, help="K correlated-sampling attempts per failed demo")
    p.add_argument("--seed", type=argtypes.seed, default=0, help="base seed of the episode placements and sampling")
    p.add_argument("--objects", default=None, help="'train', 'unseen' or comma-separated names "
                   "(default: every demo in --demos)")
    flags.add_horizon(p, 200)
    p.add_argument("--workers", type=argtypes.count, default=1, help="worker processes (each builds its own envs)")
    p.set_defaults(func=cmd_replay, recorded_options=flags.option_names(p))


# -- inputs ------------------------------------------------------------------------------
def find_demos(folder: Path, objects: list[str] | None) -> list[tuple[Path, str, int | None]]:
    """(path, object name, the episode seed the demo was made for or None) per demo; a demo
    file that cannot be used (damaged, NaN keypoints, an unknown object) is named in a warning
    and skipped."""
    from dexdrake.demos.format import is_demo_file, load_demo
    from dexdrake.objects.library import get_object

    folder = Path(folder)
    if not folder.is_dir():
        raise DexdrakeError(f"demo folder {folder} {'is a file' if folder.exists() else 'does not exist'}; "
                            "give the folder of demo .npz files")
    found = []
    for path in sorted(folder.glob("*.npz")):
        try:
            demo = load_demo(path)
            get_object(demo.object_name)
            made_for = demo.meta.extra.get("episode_seed")
            found.append((path, demo.object_name, None if made_for is None else int(made_for)))
        except DexdrakeError as err:
            if is_demo_file(path) or not zipfile.is_zipfile(path):  # not other .npz files (e.g. trajectories)
                warnings.warn(f"skipping {path}: {err}", DexdrakeWarning, stacklevel=2)
    if not found:
        raise DexdrakeError(f"no demo-format .npz files in {folder} (make some with `dexdrake demos synth`)")
    if objects is None:
        return found
    missing = sorted(set(objects) - {name for _, name, _ in found})
    if missing and len(missing) == len(set(objects)):
        have = sorted({name for _, name, _ in found})
        raise DexdrakeError(f"no demos of {missing} in {folder}; it has demos of {have}")
    return [d for d in found if d[1] in set(objects)]


def demo_seed(base_seed: int, index: int) -> int:
    """The episode seed of the `index`-th demo (deterministic, 31-bit) when the demo was
    not made for an episode (demos with meta.extra["episode_seed"] are replayed at that
    episode's placement, which their approach was synthesised to reach)."""
    return int(np.random.SeedSequence([base_seed, index]).generate_state(1)[0] >> 1)


# -- workers -----------------------------------------------------------------------------
_REPLAYER = None


def _init_worker(hand: str, feature_set: str | None, config) -> None:
    global _REPLAYER
    from dexdrake.systems.demo_replay import DemoReplayer

    _REPLAYER = DemoReplayer(hand, feature_set, config)


def _replay_job(job: tuple[int, str, int]):
    from dexdrake.demos.format import load_demo

    index, path, seed = job
    return index, _REPLAYER.replay(load_demo(path), seed)


def replay_demos(jobs: list[tuple[int, str, int]], hand: str, feature_set: str | None, config,
                 workers: int = 1, progress: bool = True) -> list:
    """DemoReplayResult per job (index, demo path, episode seed), in job order; with
    `workers` > 1 in spawned processes, each building its own Drake envs."""
    from tqdm import tqdm

    if workers < 1:
        raise DexdrakeError(f"--workers must be at least 1, got {workers}")
    results: dict[int, Any] = {}
    with tqdm(total=len(jobs), desc=f"replay {hand}", unit="demo", disable=not progress) as bar:  # closed on Ctrl-C too
        if workers == 1:
            _init_worker(hand, feature_set, config)
            for job in jobs:
                i, res = _replay_job(job)
                results[i] = res
                bar.update()
                bar.set_postfix(ok=sum(r.success for r in results.values()))
        else:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor, as_completed

            # Drake objects don't pickle or survive fork; the forkserver's workers start clean
            ctx = mp.get_context("forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn")
            previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # the workers inherit it: Ctrl-C is ours
            try:
                pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker,
                                           initargs=(hand, feature_set, config))
                futures = [pool.submit(_replay_job, j) for j in jobs]
            finally:
                signal.signal(signal.SIGINT, previous)
            try:
                for fut in as_completed(futures):
                    i, res = fut.result()
                    results[i] = res
                    bar.update()
                    bar.set_postfix(ok=sum(r.success for r in results.values()))
            except BaseException:  # Ctrl-C or an error: drop the queued jobs, end the running ones
                running = list(pool._processes.values())
                pool.shutdown(wait=False, cancel_futures=True)
                for process in running:
                    process.terminate()
                raise
            pool.shutdown()
    return [results[i] for i, _, _ in jobs]


# -- summary and dataset -----------------------------------------------------------------
def _rates(results: list) -> dict[str, float | int]:
    n = len(results)
    raw = sum(r.raw_success for r in results)
    ok = sum(r.success for r in results)
    return {"demos": n, "raw_successes": raw, "successes": ok,
            "raw_rate": raw / n if n else 0.0, "after_sampling_rate": ok / n if n else 0.0}


def summarize(results: list) -> dict[str, Any]:
    """Raw and after-sampling success rates overall, per object and per category."""
    by_object, by_category = defaultdict(list), defaultdict(list)
    for r in results:
        by_object[r.object].append(r)
        by_category[r.category].append(r)
    return {
        "overall": _rates(results),
        "per_object": {k: _rates(v) for k, v in sorted(by_object.items())},
        "per_category": {k: _rates(v) for k, v in sorted(by_category.items())},
    }


def rates_table(rates: dict[str, dict], key: str = "category") -> str:
    """A markdown table of {name: _rates} rows plus the overall row when given."""
    lines = [f"| {key} | demos | raw success % | after sampling % |", "|---|---:|---:|---:|"]
    for name, r in rates.items():
        lines.append(f"| {name} | {r['demos']} | {100 * r['raw_rate']:.1f} | {100 * r['after_sampling_rate']:.1f} |")
    return "\n".join(lines)


def build_dataset(results: list, paths: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict]]:
    """(observations, actions, episode_starts, per-demo records) from the kept episodes."""
    obs, act, starts, records = [], [], [], []
    for r, path in zip(results, paths):
        ep = r.episode
        rec = {"file": path, "object": r.object, "category": r.category, "seed": r.seed,
               "placement": asdict(r.placement), "raw_success": r.raw_success, "success": r.success,
               "attempts": [[k, bool(s), round(float(lift), 4)] for k, s, lift in r.outcomes],
               "kept_attempt": None if ep is None else ep.attempt,
               "kind": "failed" if ep is None else ("sampled" if ep.sampled else "raw"),
               "episode": None if ep is None else len(obs)}
        if ep is not None:
            obs.append(ep.observations)
            act.append(ep.actions)
            s = np.zeros(len(ep.actions), bool)
            s[0] = True
            starts.append(s)
        records.append(rec)
    if not obs:
        raise DexdrakeError(f"no replay succeeded ({len(results)} demos, raw and sampled); nothing to write")
    return np.concatenate(obs), np.concatenate(act), np.concatenate(starts), records


def command_line(args: argparse.Namespace) -> str:
    """The exact `dexdrake demos replay` command for `args`."""
    return flags.command_line(["demos", "replay"], args, args.recorded_options)


def run_replay(demos_dir: Path, out: Path, hand: str, config, feature_set: str | None = None,
               seed: int = 0, objects: list[str] | None = None, workers: int = 1,
               command: str = "", progress: bool = True) -> dict[str, Any]:
    """Replay every demo in `demos_dir` (optionally only `objects`), write the dataset to
    `out` and return its metadata. `config` is a `ReplayConfig`."""
    from dexdrake.learn.demo_dataset import save_demo_dataset
    from dexdrake.systems.demo_replay import observation_blocks_for

    blocks = observation_blocks_for(hand, feature_set)  # fails early on a bad name
    demos = find_demos(demos_dir, objects)
    jobs = [(i, str(p), demo_seed(seed, i) if made_for is None else made_for)
            for i, (p, _, made_for) in enumerate(demos)]
    results = replay_demos(jobs, hand, feature_set, config, workers, progress)
    summary = summarize(results)
    if progress:
        print(rates_table(summary["per_category"]))
        o = summary["overall"]
        print(f"overall: {o['demos']} demos, raw {100 * o['raw_rate']:.1f} %, after sampling "
              f"{100 * o['after_sampling_rate']:.1f} %")
    obs, act, starts, records = build_dataset(results, [str(p) for p, _, _ in demos])
    if sum(blocks.values()) != obs.shape[1]:
        raise DexdrakeError(f"observation blocks {blocks} sum to {sum(blocks.values())}, "
                            f"observations have {obs.shape[1]} columns")
    metadata = {
        "format": DATASET_FORMAT,
        "source": "demo_replay",
        "hand": hand,
        "feature_set": feature_set,
        "observation_blocks": blocks,
        "objects": sorted({r.object for r in results}),
        "demos": records,
        "success_rates": summary,
        "counts": {"demos": len(results), "episodes": int(starts.sum()), "samples": int(len(obs)),
                   "raw_episodes": sum(r["kind"] == "raw" for r in records),
                   "sampled_episodes": sum(r["kind"] == "sampled" for r in records),
                   "attempts_run": sum(len(r["attempts"]) for r in records)},
        "config": asdict(config),
        "seed": seed,
        "command": command,
    }
    path = save_demo_dataset(out, obs, act, starts, metadata)
    if progress:
        print(f"wrote {len(obs)} samples from {int(starts.sum())} episodes "
              f"({obs.shape[1]}-d observations) to {path}")
    return metadata


def cmd_replay(args: argparse.Namespace) -> int:
    from dexdrake.objects.library import resolve_objects
    from dexdrake.systems.demo_replay import ReplayConfig

    config = ReplayConfig(horizon=args.horizon, attempts=args.attempts)
    objects = None if args.objects is None else resolve_objects(args.objects)[1]
    run_replay(args.demos, args.out, args.hand, config, args.feature_set, args.seed, objects,
               args.workers, command_line(args))
    return 0
