"""Feature-set ablation: the same expert-labelled states and BC budget for every feature set.

The states are those of a finished DAgger run (`dexdrake train dagger`: the expert's and the
policy's visited states, every `stride`-th step, with the expert's labels). Their raw plant
states (positions and velocities) are re-featurised with each set, so every set sees the same
states and labels and gets the same BC budget (epochs, batch 64, lr, seed). Each set is
scored on unseen objects:
- open loop: the mean squared error (summed over joints, normalised action units) of its
  predictions against the expert's labels along the expert's own episodes on those objects
  (seeds 0 and 1);
- closed loop: success over `episodes` evaluation episodes per object (100 steps).
`objects="paper"` evaluates the paper's 10 unseen ablation objects (`eval.paper.PAPER_UNSEEN`).
Writes ablations.md/.csv beside the paper's numbers; each finished set is kept in
ablations.json, so the same settings run again go on with the sets still missing (other
settings into that folder are refused).

What needs the simulator comes in as arguments (the command line passes systems/ ones):
`featurise` (observations of a feature set for DAgger states), the env factories and the
expert.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from dexdrake.errors import DexdrakeError
from dexdrake.eval.seeds import FIRST_TEST_SEED
from dexdrake.learn.curves import write_csv
from dexdrake.learn.dagger import DaggerData, MakeExpert
from dexdrake.learn.env_protocol import MakeEnvFactory, PolicyEnvFactory
from dexdrake.objects.meshfile import write_atomic

COLUMNS = ("feature_set", "obs_dim", "train_mse", "unseen_open_loop_mse", "ours_paper_objects_pct", "ours_all_pct",
           "paper_pct", "mean_max_lift_m", "minutes")
HELD_OUT_SEEDS = (0, 1)  # the expert's own episodes that score the open loop
HORIZON = 100  # control steps of those episodes

# (hand, DAgger states, feature set, workers) -> observations (N, D) and block sizes
Featurise = Callable[[str, DaggerData, str, int], tuple[np.ndarray, dict[str, int]]]


class AblationSettingsError(DexdrakeError):
    """An output folder holds an ablation of other settings."""


@dataclass(frozen=True)
class AblationSettings:
    """What a table row depends on (recorded in ablations.json)."""

    dagger: str  # a `dexdrake train dagger` output folder
    stride: int = 2  # keep every n-th step of each episode
    epochs: int = 20
    lr: float = 1e-4
    episodes: int = 2  # closed-loop episodes per object
    objects: str = "paper"  # 'paper', 'unseen' or comma-separated names
    seed: int = 0  # BC seed
    eval_seed: int = FIRST_TEST_SEED


@dataclass(frozen=True)
class AblationRuntime:
    """What the command line passes in (systems/), where sets are featurised and evaluated."""

    featurise: Featurise  # systems.scripted_data.featurise_labelled
    make_env: MakeEnvFactory  # systems.env_factory.GraspEnvFactory
    env_for_policy: PolicyEnvFactory  # systems.env_factory.env_factory_for_policy
    make_expert: MakeExpert  # systems.reactive_grasp.ReactiveGrasp
    workers: int = 2
    command: str = ""  # the command line, named in the table


def every_nth_step(data: DaggerData, stride: int) -> DaggerData:
    """Every `stride`-th step of each episode (episode starts kept)."""
    index = np.arange(len(data.labels))
    step = index - np.maximum.accumulate(np.where(data.episode_starts, index, 0))
    keep = step % stride == 0
    return DaggerData(data.objects, data.seeds, data.success, data.episode_starts[keep], data.states[keep],
                      data.observations[keep], data.labels[keep])


def expert_episodes(runtime: AblationRuntime, hand: str, objects: Sequence[str],
                    seeds: Sequence[int]) -> DaggerData:
    """The expert's own episodes on `objects` (states and labels)."""
    from dexdrake.learn.dagger import labelled_episode

    env = runtime.make_env(hand, None, tuple(objects), HORIZON)()
    return DaggerData.concat([labelled_episode(env, name, s, None, 0.0, runtime.make_expert)
                              for name in objects for s in seeds])


def finished_rows(out: Path, settings: AblationSettings) -> dict[str, dict[str, object]]:
    """The rows an earlier run of `settings` finished in `out` ({} if none); raises
    AblationSettingsError, naming each difference, if that folder holds other settings."""
    path = Path(out) / "ablations.json"
    if not path.is_file():
        return {}
    done = json.loads(path.read_text())
    now = asdict(settings)
    if done["settings"] != now:
        diff = "; ".join(f"{k} {done['settings'].get(k)!r} (now {now[k]!r})"
                         for k in now if done["settings"].get(k) != now[k])
        raise AblationSettingsError(f"{out} holds an ablation with other settings: {diff}; "
                                    "use another --out or delete it")
    return done["rows"]


def run_set(feature_set: str, hand: str, train: DaggerData, held_out: DaggerData, settings: AblationSettings,
            runtime: AblationRuntime, objects: list[str], out: Path) -> dict[str, object]:
    """Featurise, train BC, score open and closed loop for one feature set; returns its table row."""
    import torch

    from dexdrake.eval.evaluate import evaluate_policy
    from dexdrake.eval.paper import PAPER_ABLATIONS, PAPER_UNSEEN
    from dexdrake.learn.bc import BCConfig, train_bc
    from dexdrake.learn.demo_dataset import DemoDataset
    from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig

    slug = feature_set.replace("+", "_").replace("-", "_").lower()
    t0 = time.perf_counter()
    obs, blocks = runtime.featurise(hand, train, feature_set, runtime.workers)
    held_obs, _ = runtime.featurise(hand, held_out, feature_set, runtime.workers)
    config = PolicyConfig.from_blocks(blocks, train.labels.shape[1], feature_set=feature_set, hand=hand)
    policy = DexRepNetPolicy(config)
    bc = train_bc(policy, DemoDataset(obs, train.labels, train.episode_starts), out / slug,
                  BCConfig(epochs=settings.epochs, lr=settings.lr, seed=settings.seed, checkpoint_every=0,
                           val_fraction=0.0),
                  {"command": runtime.command})
    with torch.no_grad():
        pred = policy(torch.as_tensor(held_obs)).numpy()
    open_loop = float(np.mean(np.sum((pred - held_out.labels) ** 2, axis=1)))
    report = evaluate_policy(bc.last_checkpoint, runtime.env_for_policy, objects, settings.episodes,
                             settings.eval_seed, runtime.workers, label="unseen", command=runtime.command)
    per = report.per_object()
    paper_objs = [n for n in per if n in PAPER_UNSEEN]
    return {
        "feature_set": feature_set,
        "obs_dim": sum(blocks.values()),
        "train_mse": f"{bc.train_loss[-1]:.3f}",
        "unseen_open_loop_mse": f"{open_loop:.3f}",
        "ours_paper_objects_pct": f"{sum(per[n]['success_pct'] for n in paper_objs) / max(1, len(paper_objs)):.1f}",
        "ours_all_pct": f"{report.average_pct():.1f}",
        "paper_pct": f"{PAPER_ABLATIONS[feature_set]:.1f}" if feature_set in PAPER_ABLATIONS else "",
        "mean_max_lift_m": f"{sum(e.max_lift for e in report.episodes) / len(report.episodes):.3f}",
        "minutes": f"{(time.perf_counter() - t0) / 60:.1f}",
    }


def write_table(rows: list[dict[str, object]], out: Path, settings: AblationSettings, command: str,
                objects: list[str], n_train: int, n_held: int) -> str:
    """ablations.csv and ablations.md in `out`; returns the markdown."""
    write_csv(out / "ablations.csv", COLUMNS, rows)
    s = settings
    lines = [
        "# Feature-set ablation (same states, labels and BC budget for every set)",
        "",
        f"- command: `{command}`",
        f"- training data: {n_train} expert-labelled states of the DAgger run in `{s.dagger}` (one step in "
        f"{s.stride}), re-featurised per set; BC {s.epochs} epochs, batch 64, lr {s.lr}, seed {s.seed}",
        f"- open loop: MSE (summed over joints, normalised units) against the expert's labels on its own episodes on "
        f"{len(objects)} unseen objects, seeds {HELD_OUT_SEEDS[0]}..{HELD_OUT_SEEDS[-1]} ({n_held} states)",
        f"- closed loop: {len(objects)} unseen objects x {s.episodes} episodes (seeds {s.eval_seed}.."
        f"{s.eval_seed + s.episodes - 1}), {HORIZON} steps, mean actions",
        "- paper: after BC + DAPG, 10 unseen GRAB objects, 3 seeds",
        "",
        "| feature set | obs dim | train MSE | unseen open-loop MSE | ours, paper objects (%) | ours, all evaluated (%) "
        "| paper (%) | mean max lift (m) | minutes |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    lines += ["| " + " | ".join(str(r[k]) for k in COLUMNS) + " |" for r in rows]
    text = "\n".join(lines) + "\n"
    write_atomic(out / "ablations.md", text.encode())
    return text


def ablation_objects(spec: str) -> list[str]:
    """'paper' -> the paper's unseen ablation objects; else the library's resolution of `spec`."""
    from dexdrake.eval.paper import PAPER_UNSEEN
    from dexdrake.objects.library import resolve_objects

    return list(PAPER_UNSEEN) if spec == "paper" else resolve_objects(spec)[1]


def run_ablations(settings: AblationSettings, feature_sets: Sequence[str], out: Path,
                  runtime: AblationRuntime) -> str:
    """Run (or go on with) the ablation of `feature_sets` into `out`; returns the table's markdown."""
    from dexdrake.dexrep.feature_sets import FEATURE_SETS
    from dexdrake.learn.policy import load_policy

    unknown = [s for s in feature_sets if s not in FEATURE_SETS]
    if unknown:
        raise DexdrakeError(f"unknown feature sets {unknown}; valid: {list(FEATURE_SETS)}")
    out = Path(out)
    done = finished_rows(out, settings)
    dagger = Path(settings.dagger)
    files = sorted(dagger.glob("data_*.npz"))
    if not files:
        raise DexdrakeError(f"no DAgger data (data_*.npz) in {dagger}")
    objects = ablation_objects(settings.objects)
    hand = load_policy(dagger / "dagger_policy.pt")[0].config.hand
    train = every_nth_step(DaggerData.concat([DaggerData.load(f) for f in files]), settings.stride)
    held_out = expert_episodes(runtime, hand, objects, HELD_OUT_SEEDS)
    text = ""
    for fs in feature_sets:
        if fs not in done:
            done[fs] = run_set(fs, hand, train, held_out, settings, runtime, objects, out)
            write_atomic(out / "ablations.json",
                         json.dumps({"settings": asdict(settings), "rows": done}, indent=1).encode())
        text = write_table([done[f] for f in feature_sets if f in done], out, settings, runtime.command, objects,
                           len(train.labels), len(held_out.labels))
    return text
