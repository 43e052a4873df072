"""DAgger with the grasp expert (the command line passes in
`systems.reactive_grasp.ReactiveGrasp`).

Iteration 0 runs the expert itself (optionally with DART-style correlated action noise);
every later iteration runs the current policy, and the expert labels every state the
policy visits. All data are aggregated and the policy is
re-fit by behaviour cloning (warm-started) after each iteration. Because the labels come
from states rather than from a clock, the policy learns to move from wherever it is, which
plain cloning of the timed script did not teach (it stalled at the start pose).

Each iteration's data (the raw plant states [q; v] too, so any feature set can be re-derived and
any expert can label the states anew) and the policy after it are written to the output folder; a
re-run skips finished iterations. A run can start from an earlier run: its states labelled anew
by this run's expert (`prior`, see `relabelled`) are aggregated before iteration 0, and iteration
0 is then driven by a given policy (`init`, fine-tuned from there) instead of the expert.
With `probe_per_object` > 0 each iteration's driver also runs episodes on probe objects
(the unseen split), labelled but never trained on: the log gets the driver's executed
success there and the new policy's loss on those states, the generalisation signal.
The returned policy is the iterate that succeeded most often on its own training rollouts.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dexdrake import argtypes
from dexdrake.dexrep.feature_sets import observation_blocks
from dexdrake.episode import run_lockstep
from dexdrake.errors import DexdrakeError
from dexdrake.eval.seeds import check_training_seeds
from dexdrake.npz import open_npz
from dexdrake.hands.action_map import ARM_ACTIONS, ActionMap
from dexdrake.hands.description import HandDescription, load_hand
from dexdrake.learn.bc import BCConfig, bc_loss, train_bc
from dexdrake.learn.curves import CsvLog, read_csv
from dexdrake.learn.demo_dataset import DemoDataset
from dexdrake.learn.env_protocol import MakeEnvFactory
from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig, load_policy, save_policy, widened
from dexdrake.learn.samplers import ENVS_PER_WORKER, Sampler, check_backend, make_sampler
from dexdrake.outputs import RUN_LOGS

DATA_FORMAT = "dexdrake.dagger/2"  # /1 kept plant positions only
PROBE_SEEDS = 5000  # probe episode seeds start this far above the iteration's training seeds


_BC = {f.name: f for f in fields(BCConfig)}


@dataclass(frozen=True)
class DaggerConfig:
    """A DAgger run's settings; those with a "help" are `dexdrake train dagger`'s flags."""

    hand: str = field(default="adroit", metadata={"help": "the hand (e.g. adroit, allegro_z1)"})
    feature_set: str = field(default="DexRep", metadata={"help": "observation feature set (`dexdrake features "
                                                                 "describe` lists them)"})
    iterations: int = field(default=6, metadata={"help": "DAgger iterations", "type": argtypes.count})
    episodes_per_object: int = field(default=2, metadata={
        "type": argtypes.episodes, "metavar": "N", "help": argtypes.episodes_per_object_help("each iteration")})
    horizon: int = field(default=100, metadata={"type": argtypes.steps, "metavar": "N", "help": argtypes.horizon_help()})
    expert_noise: float = field(default=0.0, metadata={
        "type": argtypes.float_in(0.0, 1.0, low_open=False),
        "help": "DART-style correlated (OU) action-noise std on the expert's iteration 0 (normalised action units; "
                "the labels stay clean)"})
    epochs: int = field(default=20, metadata={"help": "BC epochs after each iteration", "type": argtypes.count})
    arm_weight: float = field(default=1.0, metadata={"type": argtypes.positive,
                                                     "help": "loss weight of the arm's action dimensions (the fingers' is 1)"})
    lr: float = field(default=1e-4, metadata={"help": "learning rate of the BC fits", "type": argtypes.positive})
    weight_decay: float = field(default=BCConfig.weight_decay, metadata=_BC["weight_decay"].metadata)
    obs_noise: float = field(default=BCConfig.obs_noise, metadata=_BC["obs_noise"].metadata)
    batch_size: int = 64
    workers: int = field(default=2, metadata={"help": "rollout worker processes", "type": argtypes.count})
    envs_per_worker: int = ENVS_PER_WORKER  # a policy's episodes each worker steps in lockstep
    backend: str = "process"  # sampler backend (samplers.BACKENDS)
    seed: int = field(default=0, metadata={"type": argtypes.seed, "help": "episode seeds of iteration i: "
                                           "seed * 10**6 + i * 10**4 + j * episodes_per_object + k for "
                                           f"episode k of object j (probes: + {PROBE_SEEDS})"})
    probe_per_object: int = field(default=0, metadata={
        "type": argtypes.int_at_least(0),
        "help": "episodes per validation object per iteration, labelled but never trained on: the log's "
                "unseen_success and unseen_loss (0: no probe)"})
    init: str = field(default="", metadata={
        "type": Path, "help": "policy checkpoint that drives iteration 0 and is fine-tuned (default: the expert "
                              "drives, a new network)"})
    prior: tuple[str, ...] = field(default=(), metadata={
        "type": Path, "metavar": "DIR",
        "help": "earlier DAgger runs' folders: their states, labelled anew by this expert, are trained on too"})
    residual_arm: bool = field(default=False, metadata={
        "help": "a new network's arm actions are added to the arm's current position (it learns the lead)"})
    arm_action: str = field(default="joints", metadata={
        "choices": ARM_ACTIONS, "help": "how a new network's actions command the arm: its joints, the palm's pose, "
                                        "or the palm's step from where it is (dexdrake/hands/action_map.py)"})


@dataclass
class DaggerData:
    """Visited states with expert labels, episode by episode."""

    objects: list[str]  # object of each episode
    seeds: np.ndarray  # int (E,)
    success: np.ndarray  # bool (E,): the executed episode succeeded
    episode_starts: np.ndarray  # bool (N,)
    states: np.ndarray  # float64 (N, nq + nv): plant positions and velocities before each action
    observations: np.ndarray  # float32 (N, D)
    labels: np.ndarray  # float32 (N, A): the expert's normalised action at that state

    @staticmethod
    def concat(parts: list[DaggerData]) -> DaggerData:
        if not parts:
            raise DexdrakeError("no DAgger data to join")
        return DaggerData([o for p in parts for o in p.objects], *(np.concatenate([getattr(p, k) for p in parts]) for k in
                          ("seeds", "success", "episode_starts", "states", "observations", "labels")))

    def save(self, path: Path, metadata: dict[str, Any]) -> None:
        meta = {"format": DATA_FORMAT, "objects": self.objects, **metadata}
        tmp = path.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, seeds=self.seeds, success=self.success, episode_starts=self.episode_starts,
                            states=self.states, observations=self.observations, labels=self.labels,
                            metadata=np.array(json.dumps(meta)))
        tmp.replace(path)

    @staticmethod
    def load(path: Path) -> DaggerData:
        with open_npz(path) as d:
            meta = json.loads(str(d["metadata"]))
            if meta.get("format") != DATA_FORMAT:
                raise DexdrakeError(f"{path} is not a {DATA_FORMAT} file (DAgger data from before plant velocities "
                                    "were recorded cannot be read: run DAgger again)")
            return DaggerData(list(meta["objects"]), d["seeds"], d["success"].astype(bool), d["episode_starts"].astype(bool),
                              d["states"], d["observations"], d["labels"])


class Aggregate:
    """Every iteration's observations and labels in arrays allocated once for the whole run, so
    aggregating an iteration copies only its own samples (concatenating all of them anew each
    iteration held several copies of the data and ran out of 24 GB at ~360k states). The
    observations are held as float16, half the memory of float32 (954k states of 2631 values
    filled 10 of the machine's 24 GB): on 53k states of a run the rounding is at most 0.09 and
    at the 99th percentile 0.002 of a feature's standard deviation."""

    def __init__(self, capacity: int):
        self.capacity, self.n = capacity, 0
        self.observations: np.ndarray | None = None
        self.labels: np.ndarray | None = None
        self.episode_starts = np.zeros(capacity, dtype=bool)

    def add(self, data: DaggerData) -> None:
        k = len(data.labels)
        if self.n + k > self.capacity:
            raise DexdrakeError(f"DAgger data of {self.n + k} samples exceeds the {self.capacity} allocated")
        if self.observations is None:
            self.observations = np.empty((self.capacity, data.observations.shape[1]), dtype=np.float16)
            self.labels = np.empty((self.capacity, data.labels.shape[1]), dtype=np.float32)
        self.observations[self.n : self.n + k] = data.observations
        self.labels[self.n : self.n + k] = data.labels
        self.episode_starts[self.n : self.n + k] = data.episode_starts
        self.n += k

    def dataset(self) -> DemoDataset:
        """The samples so far, as views (no copy)."""
        assert self.observations is not None and self.labels is not None
        n = self.n
        return DemoDataset(self.observations[:n], self.labels[:n], self.episode_starts[:n])


def _metadata(path: Path) -> dict[str, Any]:
    with open_npz(path) as d:
        return json.loads(str(d["metadata"]))


def run_config(out_dir: Path) -> DaggerConfig:
    """The DaggerConfig a run's first data file was made with (fields newer than the run: their
    defaults)."""
    first = out_dir / "data_00.npz"
    if not first.is_file():
        raise DexdrakeError(f"{out_dir} holds no DAgger run (no data_00.npz)")
    made = _metadata(first).get("config", {})
    return DaggerConfig(**{k: made[k] for k in asdict(DaggerConfig()) if k in made})


def init_sha256(out_dir: Path) -> str | None:
    """The sha256 of the policy a run started from (its `init`), as recorded when that policy
    drove iteration 0 (the file may have changed since, e.g. replaced by this run's own
    result); None without an init or for a run made before this was recorded."""
    path = out_dir / "data_00.npz"
    return _metadata(path).get("init_sha256") if path.is_file() else None


def _samples_in(path: Path) -> int:
    with open_npz(path) as d:
        return len(d["episode_starts"])


def run_capacity(out_dir: Path, config: DaggerConfig, n_objects: int) -> int:
    """Samples a run can hold: those of its prior and data files on disk, and a full horizon
    for every episode of the iterations still to collect."""
    total = sum(_samples_in(path) for path in prior_files(config))
    for it in range(config.iterations):
        path = out_dir / f"data_{it:02d}.npz"
        if path.is_file():
            total += _samples_in(path)
        else:
            total += n_objects * config.episodes_per_object * config.horizon
    return total


def prior_files(config: DaggerConfig) -> list[Path]:
    """The states of `config.prior`'s runs, run by run: each one's own prior files (relabelled
    states of the runs before it), then its data files, in iteration order; refused when a run
    has none or when their observations are another hand's or feature set's than `config`'s."""
    files = []
    for prior_dir in map(Path, config.prior):
        found = sorted(prior_dir.glob("prior_[0-9][0-9].npz")) + sorted(prior_dir.glob("data_[0-9][0-9].npz"))
        if not found:
            raise DexdrakeError(f"{prior_dir} holds no DAgger data (prior_XX.npz or data_XX.npz)")
        files += found
    for path in files:
        made = _metadata(path).get("config", {})
        if (made.get("hand"), made.get("feature_set")) != (config.hand, config.feature_set):
            raise DexdrakeError(f"{path} holds {made.get('hand')} {made.get('feature_set')} observations; this run is "
                                f"{config.hand} {config.feature_set}")
    return files


MakeExpert = Callable[[Any], Callable[[Any], np.ndarray]]
"""env -> the expert for its current episode: called with the env, it returns the action in
joint units. Picklable (systems.reactive_grasp.ReactiveGrasp), as sampler workers call it."""


def labelled_episode(env, name: str, seed: int, policy: DexRepNetPolicy | None, noise: float,
                     make_expert: MakeExpert) -> DaggerData:
    """One episode on object `name` (the one episode loop, dexdrake/episode.py): the policy
    acts (the expert if `policy` is None, with OU noise of std `noise` seeded by `seed`), the
    expert labels every visited state."""
    return labelled_lockstep([env], [(name, seed)], policy, noise, make_expert)[0]


def labelled_lockstep(envs: list, jobs: list[tuple[str, int]], policy: DexRepNetPolicy | None, noise: float,
                      make_expert: MakeExpert) -> list[DaggerData]:
    """`labelled_episode` of each job (object, seed) on its own env, all in lockstep with one
    policy call per step for the envs still running; each result is the one it gives alone."""
    from dexdrake.eval.action_noise import OUActionNoise

    perturbs = [OUActionNoise(env.action_dim, noise, seed=seed) if noise > 0 else None
                for env, (_, seed) in zip(envs, jobs, strict=True)]
    experts: list = [None] * len(jobs)
    states: list[list] = [[] for _ in jobs]
    observations: list[list] = [[] for _ in jobs]
    labels: list[list] = [[] for _ in jobs]

    def act(obs: list[np.ndarray], live: list[int]) -> list[np.ndarray]:
        for k, o in zip(live, obs):
            env = envs[k]
            experts[k] = experts[k] or make_expert(env)
            states[k].append(env.scene.plant.GetPositionsAndVelocities(env.plant_context).copy())
            observations[k].append(o)
            labels[k].append(np.clip(env.normalise(experts[k](env)), -1.0, 1.0))
        actions = ([labels[k][-1] for k in live] if policy is None
                   else policy.act_batch(np.asarray(obs, dtype=np.float32), [None] * len(live))[0])
        return [a if perturbs[k] is None else a + perturbs[k].sample() for k, a in zip(live, actions)]

    results = run_lockstep(envs, act, [seed for _, seed in jobs], object_names=[name for name, _ in jobs])
    out = []
    for k, ((name, seed), result) in enumerate(zip(jobs, results)):
        starts = np.zeros(len(labels[k]), dtype=bool)
        starts[0] = True
        out.append(DaggerData([name], np.array([seed]), np.array([result.success]), starts, np.asarray(states[k]),
                              np.asarray(observations[k], dtype=np.float32), np.asarray(labels[k], dtype=np.float32)))
    return out


def relabel_job(make_expert: MakeExpert, env, policy: None, job: tuple[str, int, np.ndarray]) -> np.ndarray:
    """The expert's labels (normalised, clipped) of one recorded episode's states (job = (object,
    seed, plant states [q; v] per step)), replayed state by state: a fresh expert at the
    episode's first state, the plant put in each recorded state."""
    name, seed, states = job
    env.reset(int(seed), object_name=name)
    plant, ctx = env.scene.plant, env.plant_context
    expert, labels = None, np.empty((len(states), env.action_dim), dtype=np.float32)
    for i, x in enumerate(states):
        plant.SetPositionsAndVelocities(ctx, x)
        expert = expert or make_expert(env)
        labels[i] = np.clip(env.normalise(expert(env)), -1.0, 1.0)
    return labels


def relabelled(sampler: Sampler, data: DaggerData, make_expert: MakeExpert, desc: str) -> DaggerData:
    """`data` with every state labelled anew by `make_expert`'s expert (`relabel_job`, episodes
    on the sampler's workers): the states an earlier run's policies visited, taught by this
    run's expert, which is DAgger's own rule (the expert labels whatever states were visited)."""
    starts = np.flatnonzero(data.episode_starts)
    ends = np.r_[starts[1:], len(data.labels)]
    jobs = [(name, seed, data.states[a:b]) for name, seed, a, b in zip(data.objects, data.seeds, starts, ends)]
    labels = sampler.map(partial(relabel_job, make_expert), None, jobs, desc)
    if len(labels) != len(jobs):
        raise DexdrakeError(f"{desc}: {len(jobs) - len(labels)} episodes were lost with their workers; run again")
    return DaggerData(data.objects, data.seeds, data.success, data.episode_starts, data.states,
                      data.observations, np.concatenate(labels))


def dagger_job(make_expert: MakeExpert, noise: float, env, policy: DexRepNetPolicy | None,
               job: tuple[str, int]) -> DaggerData:
    """`labelled_episode` as a sampler Episode (job = (object, seed)), with the expert and
    `noise` bound first."""
    name, seed = job
    return labelled_episode(env, name, seed, policy, noise, make_expert)


def dagger_lockstep_job(make_expert: MakeExpert, noise: float, envs: list, policy: DexRepNetPolicy | None,
                        jobs: tuple[tuple[str, int], ...]) -> list[DaggerData]:
    """`labelled_lockstep` as a sampler Lockstep episode, with the expert and `noise` bound first."""
    return labelled_lockstep(envs, list(jobs), policy, noise, make_expert)


def collect(sampler: Sampler, policy: DexRepNetPolicy | None, jobs: list[tuple[str, int]], noise: float,
            desc: str, make_expert: MakeExpert) -> DaggerData:
    """Run `jobs` (object, seed) on the sampler's workers, a policy's episodes `envs_per_worker`
    at a time in lockstep on each (the expert's one at a time: batching saves it nothing);
    results in job order (a job whose worker died is left out, with a warning)."""
    if policy is None:
        return DaggerData.concat(sampler.map(partial(dagger_job, make_expert, noise), policy, jobs, desc))
    return DaggerData.concat(sampler.map_lockstep(partial(dagger_lockstep_job, make_expert, noise), policy, jobs, desc))


# DaggerConfig fields a resumed run may change: how later iterations collect and fit (the data
# files and the log record each iteration's episodes and samples); those but where the rollouts
# run change results, and a change is made only when asked for (`resume_changed`)
RESUMABLE = ("iterations", "workers", "envs_per_worker", "backend", "probe_per_object", "episodes_per_object", "epochs", "lr",
             "batch_size", "arm_weight")
PLACE = ("workers", "envs_per_worker", "backend")  # where rollouts run: the same episodes


def check_resume(out_dir: Path, config: DaggerConfig, objects: list[str], resume_changed: bool = False) -> None:
    """Refuse to resume into `out_dir` if its data were made with other arguments; the
    message names each difference (resuming would mix the runs and mislabel the policy).
    A change of a RESUMABLE setting (against the latest iteration's) needs `resume_changed`."""
    first = out_dir / "data_00.npz"
    if not first.is_file():
        return
    if not resume_changed:
        latest = _metadata(sorted(out_dir.glob("data_[0-9][0-9].npz"))[-1]).get("config", {})
        now = json.loads(json.dumps(asdict(config)))
        changed = [f"{k} {latest[k]!r} (now {now[k]!r})" for k in RESUMABLE
                   if k not in PLACE and k in latest and latest[k] != now[k]]
        if changed:
            raise DexdrakeError(f"{out_dir} holds a run made with {'; '.join(changed)}; pass --resume-changed to go on "
                                "with the new settings (later iterations use them; fewer iterations choose "
                                "dagger_policy.pt again among the first ones) or use another --out")
    meta = _metadata(first)
    old, now = meta.get("config", {}), json.loads(json.dumps(asdict(config)))  # as the file holds it
    if isinstance(old.get("prior"), str):  # a run from before several priors: one folder or none
        old["prior"] = [old["prior"]] if old["prior"] else []
    default = json.loads(json.dumps(asdict(DaggerConfig())))  # a field newer than the run: its default then
    diff = [f"{k} {old.get(k, default[k])!r} (now {now[k]!r})" for k in now
            if k not in RESUMABLE and old.get(k, default[k]) != now[k]]
    old_objects, new_objects = sorted(set(meta.get("objects", []))), sorted(set(objects))
    if old_objects != new_objects:
        diff.append(f"objects {','.join(old_objects)} (now {','.join(new_objects)})")
    if diff:
        raise DexdrakeError(f"{out_dir} holds DAgger data made with other arguments: "
                            f"{'; '.join(diff)}; use another --out or delete that folder")


def episode_jobs(config: DaggerConfig, iteration: int, objects: list[str], probe: bool = False) -> list[tuple[str, int]]:
    """Iteration `iteration`'s episodes (object, seed), episode k of object j at seed
    seed * 10**6 + iteration * 10**4 + j * n + k (n = episodes_per_object, or probe_per_object for
    the probes, whose seeds start PROBE_SEEDS above): every episode has its own seed, so its own
    placement (a seed fixes the placement), none shared across objects. Episode-major order."""
    n = config.probe_per_object if probe else config.episodes_per_object
    if len(objects) * n > PROBE_SEEDS:
        raise DexdrakeError(f"{len(objects)} objects x {n} episodes per iteration exceed the {PROBE_SEEDS} "
                            "seeds an iteration has for them")
    first = config.seed * 10**6 + iteration * 10**4 + (PROBE_SEEDS if probe else 0)
    return [(name, first + j * n + k) for k in range(n) for j, name in enumerate(objects)]


def train_dagger(objects: list[str], out_dir: Path, make_env: MakeEnvFactory, make_expert: MakeExpert,
                 config: DaggerConfig = DaggerConfig(), metadata: dict[str, Any] | None = None,
                 address: str | None = None, probe_objects: list[str] | None = None,
                 resume_changed: bool = False) -> Path:
    """Run DAgger on `objects`; returns the chosen policy checkpoint (out_dir/dagger_policy.pt,
    see SELECTION). Episodes run in envs from `make_env` on `config.workers` workers of
    `config.backend` (`address`: a Ray cluster to join), labelled by `make_expert`'s expert.

    Writes per iteration data_XX.npz and policy_XX.pt, and dagger_log.csv with the executed
    success rate (iteration 0: the expert, or the `config.init` policy; later: the previous
    iteration's policy); with `config.probe_per_object` also probe_XX.npz on `probe_objects`
    and the unseen columns; with `config.prior`, prior_XX.npz (that run's data relabelled).
    A run in `out_dir` is resumed; with other settings only if `resume_changed` (check_resume).
    """
    if config.iterations < 1 or not 1 <= config.episodes_per_object <= PROBE_SEEDS:
        raise DexdrakeError(f"need iterations >= 1 and 1 <= episodes_per_object <= {PROBE_SEEDS}: {config}")
    if not 0 <= config.probe_per_object <= PROBE_SEEDS or not config.arm_weight > 0:
        raise DexdrakeError(f"need 0 <= probe_per_object <= {PROBE_SEEDS} and arm_weight > 0: {config}")
    probes = list(probe_objects or []) if config.probe_per_object else []
    if config.probe_per_object and not probes:
        raise DexdrakeError("probe_per_object needs probe objects")
    if set(probes) & set(objects):
        raise DexdrakeError(f"probe objects {sorted(set(probes) & set(objects))} are also training objects")
    last = episode_jobs(config, config.iterations - 1, objects) + episode_jobs(config, config.iterations - 1, probes,
                                                                                 probe=True)
    check_training_seeds([max(s for _, s in last)],
                         f"DAgger's episode seeds (seed * 10**6 + iteration * 10**4 + ...; --seed {config.seed})")
    check_backend(config.backend, address)
    check_resume(out_dir, config, objects, resume_changed)
    torch.manual_seed(config.seed)
    hand = load_hand(config.hand)
    policy = load_policy(Path(config.init))[0] if config.init else None
    if policy is not None and policy.config.feature_set != config.feature_set and policy.config.hand == config.hand:
        policy = widened_init(policy, hand, config)
    if policy is not None and (policy.config.hand, policy.config.feature_set) != (config.hand, config.feature_set):
        raise DexdrakeError(f"{config.init} was trained for {policy.config.hand} with {policy.config.feature_set} "
                            f"features; this run is {config.hand} with {config.feature_set}")
    if policy is not None and policy.config.residual_arm != config.residual_arm:
        raise DexdrakeError(f"{config.init} has {'a residual' if policy.config.residual_arm else 'an absolute'} arm "
                            f"head; {'drop' if not config.residual_arm else 'add'} --residual-arm to match it")
    if policy is not None and policy.config.arm_action != config.arm_action:
        raise DexdrakeError(f"{config.init} commands the arm by {policy.config.arm_action}; this run by "
                            f"{config.arm_action} (--arm-action)")
    if config.residual_arm and config.arm_action != "joints":
        raise DexdrakeError("a residual arm leads the arm's joints: --residual-arm needs --arm-action joints")
    ActionMap(hand, config.arm_action)  # refuses a hand without that arm action before any work
    out_dir.mkdir(parents=True, exist_ok=True)
    finished = next((it for it in range(config.iterations) if not (out_dir / f"policy_{it:02d}.pt").is_file()),
                    config.iterations)
    log = CsvLog(out_dir / RUN_LOGS["DAgger"], ["iteration", "driver", "episodes", "success_rate", "samples_total",
                                               "train_loss", "val_loss", "hold_val_loss", "unseen_success", "unseen_loss",
                                               "collect_s", "train_s"],
                 resume=True, key="iteration", resume_from=finished)
    meta = {"stage": "dagger", "dagger_config": asdict(config), "objects": objects, **(metadata or {})}
    aggregate = Aggregate(run_capacity(out_dir, config, len(objects)))
    n_arm = len(hand.arm_joints)
    factory = make_env(config.hand, config.feature_set, tuple(objects + probes), config.horizon,
                       arm_action=config.arm_action)
    actions = ActionMap(hand, config.arm_action)
    with make_sampler(factory, config.backend, config.workers, address, config.envs_per_worker) as sampler:
        print(f"DAgger: {sampler.describe()}", flush=True)
        for k, source in enumerate(prior_files(config)):
            path = out_dir / f"prior_{k:02d}.npz"
            if path.is_file():
                data = DaggerData.load(path)
            else:
                data = relabelled(sampler, DaggerData.load(source), make_expert, f"relabel {source.name}")
                data.save(path, {"relabelled_from": str(source), "config": asdict(config)})
            aggregate.add(data)
        for it in range(config.iterations):
            data_path, policy_path = out_dir / f"data_{it:02d}.npz", out_dir / f"policy_{it:02d}.pt"
            t0 = time.perf_counter()
            if data_path.is_file():
                data = DaggerData.load(data_path)
            else:
                jobs = episode_jobs(config, it, objects)
                driver = _driver(config.init, it)
                data = collect(sampler, policy, jobs, config.expert_noise if policy is None else 0.0,
                               f"DAgger {it} ({driver})", make_expert)
                started = ({"init_sha256": hashlib.sha256(Path(config.init).read_bytes()).hexdigest()}
                           if driver == "init" else {})
                data.save(data_path, {"iteration": it, "driver": driver, "config": asdict(config), **started})
            probe = None
            if probes and it >= finished:
                probe_path = out_dir / f"probe_{it:02d}.npz"
                if probe_path.is_file():
                    probe = DaggerData.load(probe_path)
                else:
                    probe = collect(sampler, policy, episode_jobs(config, it, probes, probe=True), 0.0,
                                    f"DAgger {it} (probe)", make_expert)
                    probe.save(probe_path, {"iteration": it, "probe": True, "config": asdict(config)})
            collect_s = time.perf_counter() - t0
            aggregate.add(data)
            if it < finished:
                policy = load_policy(policy_path)[0]
                continue
            t1 = time.perf_counter()
            warm = policy is not None  # a trained policy: refitting its statistics must not change it
            if policy is None:
                blocks = observation_blocks(hand, config.feature_set)
                policy = DexRepNetPolicy(PolicyConfig.from_blocks(blocks, data.labels.shape[1],
                                                                  feature_set=config.feature_set, hand=config.hand,
                                                                  residual_arm=config.residual_arm,
                                                                  arm_action=config.arm_action))
            dataset = aggregate.dataset()
            weights = (config.arm_weight,) * n_arm + (1.0,) * (data.labels.shape[1] - n_arm)
            bc = BCConfig(epochs=config.epochs, batch_size=config.batch_size, lr=config.lr,
                          weight_decay=config.weight_decay, obs_noise=config.obs_noise, seed=config.seed + it,
                          split_seed=config.seed, keep_function=warm, checkpoint_every=0, action_weights=weights)
            result = train_bc(policy, dataset, out_dir / f"bc_{it:02d}", bc, {**meta, "iteration": it})
            save_policy(policy_path, policy, {**meta, "iteration": it, "samples": len(dataset)})
            hold = hold_still_loss(dataset, result.val_indices, actions)
            unseen = {} if probe is None else {
                "unseen_success": float(np.mean(probe.success)),
                "unseen_loss": bc_loss(policy, DemoDataset(probe.observations, probe.labels, probe.episode_starts))}
            log.append({"iteration": it, "driver": _driver(config.init, it), "episodes": len(data.objects),
                        "success_rate": float(np.mean(data.success)), "samples_total": len(dataset),
                        "train_loss": result.train_loss[-1], "val_loss": result.val_loss[-1],
                        "hold_val_loss": hold, **unseen, "collect_s": round(collect_s, 1),
                        "train_s": round(time.perf_counter() - t1, 1)})
            print(f"DAgger iteration {it}: executed success {np.mean(data.success):.1%} over {len(data.objects)} "
                  f"episodes; {len(dataset)} samples; train loss {result.train_loss[-1]:.4g}, val loss {result.val_loss[-1]:.4g} "
                  f"(holding still: {hold:.4g})" + ("" if probe is None else
                  f"; unseen: executed success {unseen['unseen_success']:.1%}, loss {unseen['unseen_loss']:.4g}"),
                  flush=True)
    assert policy is not None
    best = best_measured_iteration(out_dir / RUN_LOGS["DAgger"], config.iterations)
    chosen = policy if best == config.iterations - 1 else load_policy(out_dir / f"policy_{best:02d}.pt")[0]
    final = out_dir / "dagger_policy.pt"
    save_policy(final, chosen, {**meta, "iteration": best, "selection": SELECTION})
    return final


def widened_init(policy: DexRepNetPolicy, hand: HandDescription, config: DaggerConfig) -> DexRepNetPolicy:
    """The init policy widened to the run's feature set when that set appends groups to the
    policy's (e.g. DexRep -> DexRep+Vel), so it starts acting as before; else unchanged (and
    refused by the caller)."""
    blocks = tuple(observation_blocks(hand, config.feature_set).items())
    old = policy.config.blocks
    if blocks[: len(old)] != old or len(blocks) == len(old):
        return policy
    print(f"DAgger: the init policy ({policy.config.feature_set}) widened to {config.feature_set}: "
          f"new groups {[name for name, _ in blocks[len(old):]]} enter through zero weights", flush=True)
    return widened(policy, replace(policy.config, blocks=blocks, feature_set=config.feature_set))


def _driver(init: str, it: int) -> str:
    """Who drives iteration `it`: the expert or the `init` policy first, then each iterate."""
    return ("init" if init else "expert") if it == 0 else "policy"


def hold_still_loss(dataset: DemoDataset, idx: np.ndarray, actions: ActionMap) -> float:
    """The behaviour-cloning loss on samples `idx` of the action that holds the measured joints
    (set-point = current position, read from the hand block's joint positions): a policy whose
    held-out loss is not well below this has learnt little beyond copying its own state."""
    q = dataset.observations[idx, : len(actions.mid)]
    hold = np.array([actions.normalise(row, row) for row in q])
    return float(np.mean(np.sum((dataset.actions[idx] - hold) ** 2, axis=1)))


SELECTION = ("the policy with the highest executed success on the training objects, as measured by the next "
             "iteration's own rollouts (training seeds); the last policy when none was measured")


def best_measured_iteration(log_csv: Path, iterations: int) -> int:
    """The iteration whose policy succeeded most often when it drove the next iteration's
    rollouts (ties: the later one); the last iteration when no policy was measured."""
    measured = [(float(r["success_rate"]), int(r["iteration"]) - 1) for r in read_csv(log_csv) if r["driver"] == "policy"]
    return max(measured)[1] if measured else iterations - 1
