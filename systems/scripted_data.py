"""A behaviour-cloning dataset from successful scripted grasps, re-featurisable per feature set.

`record_object` runs `systems.scripted_grasp.ScriptedGrasp` (with a faster phase timing from
`TIMINGS`, so the grasp succeeds within the paper's 100-step evaluation episodes) in
`GraspEnv` and keeps every step's raw plant state (positions and velocities of the hand
joints and the object) with the normalised action applied. `featurise` turns raw states into
the observations of any feature set by setting the plant state and calling the env's feature
extractor, so one recording serves every ablation.

With `noise > 0` the recording is DART-style: the env executes the expert's action plus
temporally correlated noise (`dexdrake.eval.action_noise.OUActionNoise`) while the clean
expert action is recorded as the label, so the data covers the states a slightly wrong
policy drifts into together with the expert's correction from there.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dexdrake.episode import run_episode
from dexdrake.errors import DexdrakeError
from dexdrake.eval.action_noise import DEFAULT_RHO, OUActionNoise

RAW_FORMAT = "dexdrake.scripted_raw/2"  # /1 kept plant positions only
DATASET_FORMAT = "dexdrake.scripted/1"


@dataclass(frozen=True)
class ScriptTiming:
    """Phase end times (s) of the scripted grasp used for data (see GraspScript)."""

    approach_end: float = 0.3
    descend_end: float = 0.55
    close_end: float = 0.8
    lift_end: float = 1.05


FAST_SCRIPT = ScriptTiming()
# Lift finished by 0.9 s (step 45) after a 0.35 s close: the 50-step hold ends by step ~95 of the
# paper's 100-step episode, leaving slack for a policy that lags the expert by a few steps
# (FAST_SCRIPT's hold ends with the episode).
EARLY_LIFT = ScriptTiming(approach_end=0.2, descend_end=0.35, close_end=0.7, lift_end=0.9)
TIMINGS: dict[str, ScriptTiming] = {"fast": FAST_SCRIPT, "early_lift": EARLY_LIFT}


def timing_named(name: str) -> ScriptTiming:
    """The script timing called `name` (one of TIMINGS)."""
    if name not in TIMINGS:
        raise DexdrakeError(f"unknown script timing {name!r}; choose one of {sorted(TIMINGS)}")
    return TIMINGS[name]


@dataclass
class RawEpisodes:
    """Raw per-step states of recorded episodes (all objects share the plant layout)."""

    hand: str
    objects: list[str]  # object of each episode
    seeds: np.ndarray  # int (E,)
    success: np.ndarray  # bool (E,)
    episode_starts: np.ndarray  # bool (N,)
    states: np.ndarray  # float64 (N, nq + nv): full plant positions and velocities before each action
    actions: np.ndarray  # float32 (N, A): normalised actions in [-1, 1]

    def episode_ids(self) -> np.ndarray:
        return np.cumsum(self.episode_starts) - 1

    def select_successful(self) -> RawEpisodes:
        """Only the successful episodes."""
        keep_ep = np.nonzero(self.success)[0]
        keep = np.isin(self.episode_ids(), keep_ep)
        return RawEpisodes(self.hand, [self.objects[i] for i in keep_ep], self.seeds[keep_ep], self.success[keep_ep],
                           self.episode_starts[keep], self.states[keep], self.actions[keep])


def record_object(hand: str, name: str, seeds: list[int], horizon: int = 100,
                  timing: ScriptTiming = FAST_SCRIPT, noise: float = 0.0, noise_seed: int = 0,
                  noise_rho: float = DEFAULT_RHO) -> RawEpisodes:
    """Run the scripted grasp on object `name` for each seed; record raw states and actions.

    `noise` is the per-step standard deviation (normalised action units) of OU noise with
    step correlation `noise_rho` added to the executed action on every joint; the recorded
    action is always the clean expert action. Episode `seed`'s noise is seeded with
    (noise_seed, seed), so a recording is reproducible.
    """
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.scripted_grasp import GraspScript

    if horizon < 1:
        raise DexdrakeError(f"horizon must be >= 1, got {horizon}")
    if not noise >= 0:
        raise DexdrakeError(f"noise std must be >= 0, got {noise}")
    env = GraspEnv(training_scenario(hand, name), feature_set=None, horizon=horizon)
    script = GraspScript(**asdict(timing))
    states: list[np.ndarray] = []
    actions: list[np.ndarray] = []
    starts: list[bool] = []
    success = []
    for seed in seeds:
        perturb = OUActionNoise(env.action_dim, noise, noise_rho, seed=[int(noise_seed), int(seed)]) if noise > 0 else None
        first = len(actions)
        success.append(_scripted_episode(env, script, int(seed), perturb, states, actions))
        starts += [True] + [False] * (len(actions) - first - 1)
    return RawEpisodes(hand, [name] * len(seeds), np.asarray(seeds, dtype=np.int64), np.asarray(success, bool),
                       np.asarray(starts, bool), np.asarray(states), np.asarray(actions, np.float32))


def _scripted_episode(env, script, seed: int, perturb: OUActionNoise | None, states: list[np.ndarray],
                      actions: list[np.ndarray]) -> bool:
    """One episode of the scripted grasp (the one episode loop, dexdrake/episode.py), its
    controller made after the reset: appends the plant state before each step to `states`
    and the clean expert action to `actions`, executes it plus `perturb`'s noise (clipped);
    returns whether it succeeded."""
    from dexdrake.systems.scripted_grasp import ScriptedGrasp

    controller: ScriptedGrasp | None = None

    def act(observation: np.ndarray) -> np.ndarray:
        nonlocal controller
        controller = ScriptedGrasp(env, script) if controller is None else controller
        states.append(env.scene.plant.GetPositionsAndVelocities(env.plant_context).copy())
        a = np.clip(env.normalise(controller(env)), -1.0, 1.0)
        actions.append(a.astype(np.float32))
        return a if perturb is None else np.clip(a + perturb.sample(), -1.0, 1.0)

    return run_episode(env, act, seed).success


def concat(parts: list[RawEpisodes]) -> RawEpisodes:
    """Join recordings of the same hand."""
    if not parts:
        raise DexdrakeError("nothing to concatenate")
    if len({p.hand for p in parts}) != 1:
        raise DexdrakeError(f"recordings of different hands: {sorted({p.hand for p in parts})}")
    return RawEpisodes(parts[0].hand, [o for p in parts for o in p.objects],
                       np.concatenate([p.seeds for p in parts]), np.concatenate([p.success for p in parts]),
                       np.concatenate([p.episode_starts for p in parts]), np.concatenate([p.states for p in parts]),
                       np.concatenate([p.actions for p in parts]))


def save_raw(path: str | Path, raw: RawEpisodes, metadata: dict[str, Any] | None = None) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"format": RAW_FORMAT, "hand": raw.hand, "objects": raw.objects, **(metadata or {})}
    with open(path, "wb") as f:
        np.savez_compressed(f, seeds=raw.seeds, success=raw.success, episode_starts=raw.episode_starts,
                            states=raw.states, actions=raw.actions, metadata=np.array(json.dumps(meta)))
    return path


def load_raw(path: str | Path) -> tuple[RawEpisodes, dict[str, Any]]:
    path = Path(path)
    if not path.is_file():
        raise DexdrakeError(f"raw recording {path} does not exist")
    with np.load(path, allow_pickle=False) as d:
        meta = json.loads(str(d["metadata"]))
        if meta.get("format") != RAW_FORMAT:
            raise DexdrakeError(f"{path} is not a {RAW_FORMAT} file (recordings from before plant velocities were "
                                "kept cannot be read: record again)")
        raw = RawEpisodes(meta["hand"], list(meta["objects"]), d["seeds"], d["success"].astype(bool),
                          d["episode_starts"].astype(bool), d["states"], d["actions"])
    return raw, meta


def _featurise_object(job: tuple[str, str, str, np.ndarray]) -> tuple[str, np.ndarray, dict[str, int]]:
    """Observations of `feature_set` for the raw `states` of object `name` (one env)."""
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.env_factory import training_scenario

    hand, feature_set, name, states = job
    env = GraspEnv(training_scenario(hand, name), feature_set=feature_set, horizon=1)
    blocks = dict(env.observation_blocks)
    obs = np.empty((len(states), sum(blocks.values())), dtype=np.float32)
    for i, state in enumerate(states):
        env.scene.plant.SetPositionsAndVelocities(env.plant_context, state)
        obs[i] = env.observation()
    return name, obs, blocks


def featurise(raw: RawEpisodes, feature_set: str, progress: bool = False,
              workers: int = 1) -> tuple[np.ndarray, dict[str, int]]:
    """Observations (N, D) of `feature_set` for every recorded state, and the block sizes;
    objects are featurised on `workers` processes (1: in this one)."""
    import multiprocessing as mp
    from contextlib import nullcontext

    from tqdm.auto import tqdm

    episode_object = np.asarray(raw.objects)[raw.episode_ids()]
    jobs = [(raw.hand, feature_set, name, raw.states[episode_object == name]) for name in sorted(set(raw.objects))]
    obs: np.ndarray | None = None
    blocks: dict[str, int] = {}
    with mp.get_context("spawn").Pool(workers) if workers > 1 else nullcontext() as pool:
        results = pool.imap_unordered(_featurise_object, jobs) if pool else map(_featurise_object, jobs)
        for name, part, blocks in tqdm(results, total=len(jobs), desc=f"featurise {feature_set}", disable=not progress):
            if obs is None:
                obs = np.empty((len(raw.actions), part.shape[1]), dtype=np.float32)
            obs[episode_object == name] = part
    assert obs is not None
    return obs, blocks


def featurise_labelled(hand: str, data, feature_set: str, workers: int = 1) -> tuple[np.ndarray, dict[str, int]]:
    """`featurise` of expert-labelled DAgger states (dexdrake.learn.dagger.DaggerData) of `hand`,
    with progress bars (`eval.ablations.Featurise`)."""
    raw = RawEpisodes(hand, data.objects, data.seeds, data.success, data.episode_starts, data.states, data.labels)
    return featurise(raw, feature_set, progress=True, workers=workers)


def dataset_metadata(recorded: RawEpisodes, kept: RawEpisodes, raw_meta: dict[str, Any], feature_set: str,
                     blocks: dict[str, int]) -> dict[str, Any]:
    """Metadata of a featurised dataset (of the `kept` episodes) in the shape `dexdrake train bc` reads."""
    per_object: dict[str, list[int]] = {}
    for name, ok in zip(recorded.objects, recorded.success):
        s = per_object.setdefault(name, [0, 0])
        s[0] += int(ok)
        s[1] += 1
    return {
        "format": DATASET_FORMAT,
        "source": "scripted_grasp",
        "hand": kept.hand,
        "feature_set": feature_set,
        "observation_blocks": blocks,
        "objects": sorted(set(kept.objects)),
        "counts": {"recorded_episodes": len(recorded.objects), "episodes": len(kept.objects),
                   "samples": int(len(kept.actions))},
        "script": raw_meta.get("script"),
        "seeds": raw_meta.get("seeds"),
        "command": raw_meta.get("command"),
        "merged_from": raw_meta.get("merged_from"),
        "success_rates": {"overall": float(np.mean(recorded.success)),
                          "per_object_successes_of_episodes": per_object},
    }
