"""DAPG: natural policy gradient fine-tuning with a demo-augmented gradient (Rajeswaran 2018).

Gradient (DexRepNet spec):
    g = sum_{rollouts} grad log pi(a|s) A(s,a) + sum_{demos} grad log pi(a|s) w_k,
    w_k = lambda0 * lambda1^k * max A,  lambda0 = 0.1, lambda1 = 0.95, max A = 1,
where A is GAE with rollout advantages standardised to zero mean and unit std (so max A = 1
is on that scale) and the sum is averaged over all rollout and demo samples, as in mjrl.
Each iteration: sample seeded rollouts, compute advantages with the current baseline, take
one NPG step (with the measured-KL backtracking safeguard of `npg.natural_gradient_step`),
then refit the baseline on the new returns. On a fresh start the exploration std is set
from the demonstrations' action spread (`DexRepNetPolicy.set_log_std_from_actions`).

Artefacts in out_dir, all written atomically every iteration: dapg_log.csv + dapg_log.png
(return, success, KL against iteration and environment steps), dapg_objects.csv + .png (each
iteration's rollouts, successes and mean return per object; the success map), dapg_state.pt (resumable:
policy, baseline + optimiser, iteration, RNG states, log rows, step and CPU counters),
dapg_manifest.json (config, commands, steps, CPU-hours, last row), dapg_policy_last.pt and
dapg_policy_best.pt (policy checkpoints, see policy.load_policy; "best" is the policy whose
own rollouts had the highest mean return), dapg_iter_XXXX.pt (the state, whose policy
load_policy reads) every `checkpoint_every` iterations, and dapg.rrd (dapg_from_XXXX.rrd
after a resume) when rerun logging is on.
"""

from __future__ import annotations

import json
import random
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from dexdrake import argtypes
from dexdrake.errors import DexdrakeError, NonFiniteError
from dexdrake.npz import open_npz
from dexdrake.learn.baseline import MLPBaseline
from dexdrake.eval.seeds import TRAINING_SEEDS
from dexdrake.learn.curves import plot_curves, plot_success_map, write_csv
from dexdrake.learn.demo_dataset import DemoDataset, load_demo_dataset
from dexdrake.learn.gae import discounted_returns, gae_advantages
from dexdrake.learn.npg import flat_grad, natural_gradient_step
from dexdrake.learn.policy import DEMO_STD_FRACTION, DexRepNetPolicy, policy_payload, save_payload, save_policy
from dexdrake.learn.samplers import Sampler
from dexdrake.learn.trajectory import Trajectory
from dexdrake.outputs import RUN_LOGS
from dexdrake.task import TARGET_THRESHOLDS, TaskSpec

STATE_FORMAT = "dexdrake.dapg/2"
LOG_COLUMNS = [
    "iteration", "mean_return", "success_rate", "mean_length", "num_samples", "env_steps", "demo_weight",
    "alpha", "kl", "kl_target", "backtracks", "mean_std", "baseline_mse_before", "baseline_mse_after", "seconds",
    "cpu_s",
]  # fmt: skip
OBJECT_COLUMNS = ["iteration", "object", "rollouts", "successes", "mean_return"]  # dapg_objects.csv, per seed group


@dataclass(frozen=True)
class DAPGConfig:
    """A DAPG run's settings; those with a "help" are `dexdrake train dapg`'s flags."""

    iterations: int = field(default=500, metadata={"type": argtypes.count,
                                                   "help": "iterations in all; a resumed run goes on up to this count"})
    rollouts_per_iteration: int = 10
    gamma: float = 0.995
    gae_lambda: float = 0.97
    step_size: float = 0.05  # normalised NPG step delta (mjrl); the target KL is delta / 2
    max_kl_ratio: float = 1.5  # backtrack while the measured KL exceeds this times the target
    max_backtracks: int = 10  # halvings of the step before it is undone
    demo_std_fraction: float | None = field(default=DEMO_STD_FRACTION, metadata={  # None: keep the policy's std
        "type": argtypes.positive, "help": "fresh start: exploration std = this x the demo actions' std, per dimension"})
    seed_groups: int = 1  # rollout i's seed is i mod seed_groups (one group per object: a balanced batch)
    cg_iters: int = 10
    damping: float = 1e-4
    lam0: float = field(default=0.1, metadata={
        "flag": "demo-weight", "type": argtypes.positive,
        "help": "the demonstration term's weight lambda0 at iteration 0 (the paper's), decaying by lambda1 per "
                "iteration; a run started from a DAPG policy may go on from its run's decayed weight"})
    lam1: float = 0.95
    reward: str = field(default=TaskSpec.reward, metadata={  # the rollout env's (recorded here; built outside)
        "choices": sorted(TARGET_THRESHOLDS),
        "help": "paper: r_t as the paper writes it (full pay up to 0.22 m from the target); aligned: Adroit "
                "relocate's 0.05/0.10 m radii, paying r_t only inside the success radius (see dexdrake.task)"})
    max_adv: float = 1.0
    demo_samples: int | None = None  # demo pairs per iteration (None: all)
    fisher_samples: int | None = None  # rollout samples for Fisher products (None: all)
    baseline_epochs: int = 2
    baseline_batch: int = 64
    baseline_lr: float = 1e-3
    baseline_hidden: tuple[int, ...] = (128, 128)
    time_scale: int = field(default=200, metadata={  # also normalises the baseline's time feature
        "flag": "horizon", "type": argtypes.steps, "metavar": "N", "help": argtypes.horizon_help()})
    freeze_encoders: bool = True  # paper: encoders frozen after behaviour cloning
    checkpoint_every: int = 10
    seed: int = field(default=0, metadata={"type": argtypes.seed, "help": "rollout seeds, initialisation and the "
                                                                        "demonstration pairs kept"})
    progress: bool = True
    rerun: bool = False  # also log curves to out_dir/dapg.rrd (needs rerun-sdk)


RESUMABLE_CHANGES = ("iterations", "progress", "rerun", "checkpoint_every")  # config fields a resume may change


@dataclass
class DAPGResult:
    rows: list[dict[str, float]] = field(default_factory=list)  # this run's log rows (not those before a resume)
    iterations_done: int = 0  # total, including iterations before a resume
    log_csv: Path | None = None
    plot_png: Path | None = None
    state_path: Path | None = None


def rollout_seeds(seed: int, iteration: int, n: int, groups: int = 1) -> list[int]:
    """The n rollout seeds of an iteration: a pure function of (run seed, iteration), inside
    TRAINING_SEEDS, with seed i = i (mod groups)."""
    raw = np.random.SeedSequence([seed, iteration]).generate_state(n, dtype=np.uint64)
    span = TRAINING_SEEDS.stop // groups
    return [int(r % span) * groups + i % groups for i, r in enumerate(raw)]


def demo_weight(config: DAPGConfig, iteration: int) -> float:
    """lambda0 * lambda1^k * max A for iteration k."""
    return config.lam0 * config.lam1**iteration * config.max_adv


class _RerunCurves:
    def __init__(self, path: Path):
        try:
            import rerun as rr
        except ImportError as exc:
            raise DexdrakeError("rerun logging needs the rerun-sdk package") from exc
        self._rr = rr
        self._rec = rr.RecordingStream("dexdrake_dapg")
        self._rec.save(path)

    def log(self, row: Mapping[str, float]) -> None:
        self._rec.set_time("iteration", sequence=int(row["iteration"]))
        for key, value in row.items():
            if key != "iteration":
                self._rec.log(f"dapg/{key}", self._rr.Scalars(float(value)))

    def flush(self) -> None:
        self._rec.flush()


class DAPGTrainer:
    """Owns the policy, value baseline, RNGs, log and artefacts of one DAPG run."""

    def __init__(
        self,
        policy: DexRepNetPolicy,
        sampler: Sampler,
        out_dir: str | Path,
        config: DAPGConfig = DAPGConfig(),
        demos: DemoDataset | None = None,
        metadata: Mapping[str, Any] | None = None,
    ):
        if config.rollouts_per_iteration < 1 or config.iterations < 0 or config.seed < 0 or config.seed_groups < 1:
            raise DexdrakeError(f"need rollouts_per_iteration >= 1, iterations >= 0, seed >= 0, seed_groups >= 1: {config}")
        self.policy, self.sampler, self.config = policy, sampler, config
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.metadata = {"stage": "dapg", "dapg_config": asdict(config), **dict(metadata or {})}
        if demos is not None and (
            demos.observations.shape[1] != policy.config.obs_dim or demos.actions.shape[1] != policy.config.action_dim
        ):
            raise DexdrakeError(
                f"demos have obs/action sizes {demos.observations.shape[1]}/{demos.actions.shape[1]}, "
                f"policy expects {policy.config.obs_dim}/{policy.config.action_dim}"
            )
        self.demos = demos
        if config.freeze_encoders:
            policy.freeze_encoders()
        if demos is not None and config.demo_std_fraction is not None:
            std = policy.set_log_std_from_actions(demos.actions, config.demo_std_fraction)
            self.metadata["initial_std"] = [round(float(x), 5) for x in std]
        policy.clamp_log_std_()
        torch.manual_seed(config.seed)  # baseline initialisation
        random.seed(config.seed)
        self.baseline = MLPBaseline(
            policy.config.obs_dim,
            config.time_scale,
            policy.obs_mean.numpy(),
            policy.obs_std.numpy(),
            config.baseline_hidden,
            config.baseline_lr,
        )
        self.iteration = 0
        self.best_return = -float("inf")
        self.rows: list[dict[str, float]] = []  # every iteration's log row, since iteration 0
        self.object_rows: list[dict[str, Any]] = []  # per iteration and seed group (object)
        names = list(self.metadata.get("objects") or [])
        self.group_names = names if len(names) == config.seed_groups else [f"group_{g}" for g in range(config.seed_groups)]
        self.env_steps = 0
        self.cpu_s = 0.0  # this process since the last iteration (sampling aside) + every rollout's own CPU
        self._cpu_mark = time.process_time()
        self.sessions: list[dict[str, Any]] = []  # one entry per start or resume
        self.saved_config: dict[str, Any] = {}  # the config a loaded state was made with
        self.rng = np.random.default_rng(config.seed)
        self.state_path = self.out_dir / "dapg_state.pt"
        self.log_csv, self.plot_png = self.out_dir / RUN_LOGS["DAPG"], self.out_dir / "dapg_log.png"
        self.objects_csv = self.out_dir / "dapg_objects.csv"
        self.manifest_path = self.out_dir / "dapg_manifest.json"
        self._rerun: _RerunCurves | None = None
        self._sampled_state: dict[str, torch.Tensor] = {}  # weights that produced the last rollouts

    # ------------------------------------------------------------------ checkpoints
    def save_state(self, path: Path | None = None) -> Path:
        path = path or self.state_path
        state = {
            "format": STATE_FORMAT,
            "iteration": self.iteration,
            "best_return": self.best_return,
            "rows": self.rows,
            "object_rows": self.object_rows,
            "env_steps": self.env_steps,
            "cpu_s": self.cpu_s,
            "sessions": json.dumps(self.sessions),
            "policy": policy_payload(self.policy, self.metadata),
            "baseline": self.baseline.full_state(),
            "numpy_rng": self.rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
            "python_rng": random.getstate(),
        }
        return save_payload(path, state)

    def load_state(self, path: Path | None = None) -> None:
        """Restore a run saved by `save_state`; the policy architecture must match."""
        path = path or self.state_path
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:
            raise DexdrakeError(f"cannot read DAPG state {path}: {exc}") from exc
        if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
            raise DexdrakeError(f"{path} is not a {STATE_FORMAT} file")
        saved_cfg = state["policy"]["config"]
        if saved_cfg != self.policy.config.to_dict():
            raise DexdrakeError(f"{path} holds a policy with config {saved_cfg}, not {self.policy.config.to_dict()}")
        self.policy.load_weights(state["policy"]["state_dict"])
        for key in ("initial_std", "init_sha256"):  # facts of the run's start, not of this session
            self.metadata[key] = state["policy"]["metadata"].get(key)
        self.saved_config = json.loads(json.dumps(state["policy"]["metadata"].get("dapg_config", {})))
        self.baseline.load_full_state(state["baseline"])
        self.iteration = int(state["iteration"])
        self.best_return = float(state["best_return"])
        self.rows = [dict(r) for r in state["rows"]]
        self.object_rows = [dict(r) for r in state.get("object_rows", [])]  # absent in states of older runs
        self.env_steps = int(state["env_steps"])
        self.cpu_s = float(state["cpu_s"])
        self.sessions = json.loads(state["sessions"])
        self.rng.bit_generator.state = state["numpy_rng"]
        torch.set_rng_state(state["torch_rng"])
        random.setstate(state["python_rng"])

    # ------------------------------------------------------------------ one iteration
    def _subsample(self, n: int, k: int | None) -> np.ndarray:
        return np.arange(n) if k is None or k >= n else np.sort(self.rng.choice(n, size=k, replace=False))

    def step(self) -> dict[str, float]:
        """Run one DAPG iteration (sample, NPG step, baseline refit); returns its log row."""
        cfg, t0, k = self.config, time.perf_counter(), self.iteration
        seeds = rollout_seeds(cfg.seed, k, cfg.rollouts_per_iteration, cfg.seed_groups)
        sample_start, rollout_cpu = time.process_time(), self.sampler.episode_cpu_s
        trajs: list[Trajectory] = self.sampler.sample(self.policy, seeds)
        sample_cpu = time.process_time() - sample_start  # in this process (all of it for a sequential sampler)
        rollout_cpu = self.sampler.episode_cpu_s - rollout_cpu  # the CPU seconds the rollouts took where they ran
        if not trajs or any(len(tr) == 0 for tr in trajs):
            raise DexdrakeError(f"iteration {k}: the sampler returned an empty trajectory")
        obs = np.concatenate([tr.observations for tr in trajs])
        act = np.concatenate([tr.actions for tr in trajs])
        times = np.concatenate([np.arange(len(tr)) for tr in trajs])
        values = self.baseline.predict(obs, times) if bool(self.baseline.fitted) else np.zeros(len(obs))
        adv_parts, ret_parts, start = [], [], 0
        for tr in trajs:
            v = values[start : start + len(tr)]
            adv_parts.append(gae_advantages(tr.rewards, v, cfg.gamma, cfg.gae_lambda))
            ret_parts.append(discounted_returns(tr.rewards, cfg.gamma))
            start += len(tr)
        adv = np.concatenate(adv_parts)
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        returns = np.concatenate(ret_parts)

        weights = [torch.as_tensor(adv, dtype=torch.float32)]
        all_obs, all_act = [torch.as_tensor(obs)], [torch.as_tensor(act)]
        w_demo = demo_weight(cfg, k) if self.demos is not None else 0.0
        if self.demos is not None and w_demo > 0.0:
            idx = self._subsample(len(self.demos), cfg.demo_samples)
            all_obs.append(torch.as_tensor(self.demos.observations[idx]))
            all_act.append(torch.as_tensor(self.demos.actions[idx]))
            weights.append(torch.full((len(idx),), w_demo))
        o, a, w = torch.cat(all_obs), torch.cat(all_act), torch.cat(weights)
        params = list(self.policy.trainable_parameters())
        objective = (self.policy.log_prob(o, a) * w).sum() / w.shape[0]
        grad = flat_grad(objective, params)
        if not (torch.isfinite(objective) and bool(torch.isfinite(grad).all())):
            raise NonFiniteError(f"DAPG iteration {k}: the objective or its gradient is not finite "
                                 f"(objective {float(objective):.4g}); training stopped, this iteration not saved")

        self._sampled_state = {name: t.clone() for name, t in self.policy.state_dict().items()}
        fisher_obs = torch.as_tensor(obs[self._subsample(len(obs), cfg.fisher_samples)])
        npg = natural_gradient_step(self.policy, grad, fisher_obs, cfg.step_size, cfg.cg_iters, cfg.damping,
                                    kl_obs=torch.as_tensor(obs), max_kl_ratio=cfg.max_kl_ratio,
                                    max_backtracks=cfg.max_backtracks)
        mse_before, mse_after = self.baseline.fit(
            obs, times, returns, self.rng, epochs=cfg.baseline_epochs, batch_size=cfg.baseline_batch
        )
        self.object_rows += self._object_rows(k, trajs)
        self.iteration = k + 1
        self.env_steps += len(obs)
        now = time.process_time()
        self.cpu_s += now - self._cpu_mark - sample_cpu + rollout_cpu
        self._cpu_mark = now
        return {
            "iteration": k,
            "mean_return": float(np.mean([tr.total_reward for tr in trajs])),
            "success_rate": float(np.mean([tr.success for tr in trajs])),
            "mean_length": float(np.mean([len(tr) for tr in trajs])),
            "num_samples": len(obs),
            "env_steps": self.env_steps,
            "demo_weight": w_demo,
            "alpha": npg.alpha,
            "kl": npg.kl,
            "kl_target": npg.kl_target,
            "backtracks": npg.backtracks,
            "mean_std": float(torch.exp(self.policy.clamped_log_std().detach()).mean()),
            "baseline_mse_before": mse_before,
            "baseline_mse_after": mse_after,
            "seconds": time.perf_counter() - t0,
            "cpu_s": self.cpu_s,
        }

    def _object_rows(self, k: int, trajs: list[Trajectory]) -> list[dict[str, Any]]:
        """Iteration k's rollouts per seed group (one group per object: rollout seed mod groups)."""
        groups = np.array([tr.seed % self.config.seed_groups for tr in trajs])
        success = np.array([tr.success for tr in trajs])
        ret = np.array([tr.total_reward for tr in trajs])
        return [{"iteration": k, "object": self.group_names[g], "rollouts": int(np.sum(groups == g)),
                 "successes": int(success[groups == g].sum()), "mean_return": float(ret[groups == g].mean())}
                for g in np.unique(groups)]  # fmt: skip

    # ------------------------------------------------------------------ the loop
    def train(self) -> DAPGResult:
        """Iterate from the current iteration up to config.iterations, writing artefacts each iteration."""
        cfg = self.config
        result = DAPGResult(log_csv=self.log_csv, plot_png=self.plot_png, state_path=self.state_path)
        self.sessions.append({"from_iteration": self.iteration, "command": self.metadata.get("command", ""),
                              "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())})
        if cfg.rerun and self._rerun is None:
            name = "dapg.rrd" if self.iteration == 0 else f"dapg_from_{self.iteration:04d}.rrd"
            self._rerun = _RerunCurves(self.out_dir / name)
        bar = tqdm(range(self.iteration, cfg.iterations), desc="DAPG", unit="it", disable=not cfg.progress)
        self._cpu_mark = time.process_time()
        for _ in bar:
            row = self.step()
            self.rows.append(row)
            result.rows.append(row)
            if self._rerun is not None:
                self._rerun.log(row)
            bar.set_postfix(ret=f"{row['mean_return']:.3g}", succ=f"{row['success_rate']:.2f}", kl=f"{row['kl']:.3g}")
            save_policy(self.out_dir / "dapg_policy_last.pt", self.policy, {**self.metadata, "updates": self.iteration})
            if row["mean_return"] > self.best_return:
                self.best_return = row["mean_return"]
                self._save_best(row)
            self._write_log()
            self.save_state()
            if cfg.checkpoint_every and self.iteration % cfg.checkpoint_every == 0:
                self.save_state(self.out_dir / f"dapg_iter_{self.iteration:04d}.pt")
        if self._rerun is not None:
            self._rerun.flush()
        result.iterations_done = self.iteration
        return result

    def _save_best(self, row: Mapping[str, float]) -> None:
        """Checkpoint the weights that were sampled in `row`'s iteration (before its update)."""
        meta = {**self.metadata, "updates": int(row["iteration"]), "mean_return": row["mean_return"],
                "success_rate": row["success_rate"]}  # fmt: skip
        payload = policy_payload(self.policy, meta)
        payload["state_dict"] = self._sampled_state
        save_payload(self.out_dir / "dapg_policy_best.pt", payload)

    def _write_log(self) -> None:
        """The CSV log, its curves and the manifest, rewritten from the run's rows (atomic files)."""
        write_csv(self.log_csv, LOG_COLUMNS, self.rows)
        write_csv(self.objects_csv, OBJECT_COLUMNS, self.object_rows)
        if self.object_rows:
            plot_success_map(self.objects_csv, self.objects_csv.with_suffix(".png"), title="DAPG rollouts per object")
        plot_curves(self.log_csv, self.plot_png, ["iteration", "env_steps"], ["mean_return", "success_rate", "kl"],
                    title="DAPG")
        manifest = {
            "stage": "dapg",
            "iterations_done": self.iteration,
            "env_steps": self.env_steps,
            "cpu_hours": round(self.cpu_s / 3600, 4),
            "cpu_note": "the sampler's worker CPU seconds (episode_cpu_s) plus the learner's CPU time outside "
                        "sampling; process start-up (imports, first env builds) excluded",
            "seeds": f"rollout seeds of iteration k: rollout_seeds({self.config.seed}, k, "
                     f"{self.config.rollouts_per_iteration}, {self.config.seed_groups}) in dexdrake.learn.dapg, "
                     f"inside the training range [{TRAINING_SEEDS.start}, {TRAINING_SEEDS.stop})",
            "sessions": self.sessions,
            "last_row": self.rows[-1] if self.rows else None,
            "best_return": self.best_return,
            "artefacts": {"log_csv": self.log_csv.name, "objects_csv": self.objects_csv.name,
                          "curves_png": self.plot_png.name, "state": self.state_path.name,
                          "last_policy": "dapg_policy_last.pt", "best_policy": "dapg_policy_best.pt"},
            "metadata": self.metadata,
        }
        tmp = self.manifest_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(manifest, indent=1, default=str) + "\n")
        tmp.replace(self.manifest_path)


def load_demo_term(
    path: str | Path, obs_dim: int, action_dim: int, max_samples: int | None = None, seed: int = 0
) -> DemoDataset:
    """The demonstration term's (observation, action) pairs from a demo dataset .npz or from a
    DAgger output folder (every data_XX.npz; the expert's labels are the actions), at most
    `max_samples` of them, drawn uniformly without replacement (seeded)."""
    from dexdrake.learn.dagger import DaggerData

    path = Path(path)
    if not path.is_dir():
        data = load_demo_dataset(path, obs_dim, action_dim)
        if max_samples is None or len(data) <= max_samples:
            return data
        idx = np.sort(np.random.default_rng(seed).choice(len(data), max_samples, replace=False))
        return DemoDataset(data.observations[idx], data.actions[idx], None, data.metadata)
    files = sorted(path.glob("data_*.npz"))
    if not files:
        raise DexdrakeError(f"{path} holds no DAgger data (data_XX.npz files)")
    sizes = []
    for f in files:
        with open_npz(f) as d:
            sizes.append(int(d["labels"].shape[0]))
    total = sum(sizes)
    keep = total if max_samples is None else min(max_samples, total)
    rng = np.random.default_rng(seed)
    chosen = np.sort(rng.choice(total, keep, replace=False))
    offsets = np.cumsum([0, *sizes])
    obs, act = [], []
    for f, lo, hi in zip(files, offsets[:-1], offsets[1:]):
        idx = chosen[(chosen >= lo) & (chosen < hi)] - lo
        if len(idx) == 0:
            continue
        part = DaggerData.load(f)
        if part.observations.shape[1] != obs_dim or part.labels.shape[1] != action_dim:
            raise DexdrakeError(f"{f}: observations/labels have {part.observations.shape[1]}/{part.labels.shape[1]} "
                                f"columns, the policy expects {obs_dim}/{action_dim}")
        obs.append(part.observations[idx])
        act.append(part.labels[idx])
    meta = {"source": "dagger", "folder": str(path), "files": [f.name for f in files], "pairs_total": total,
            "pairs_used": keep}
    return DemoDataset(np.concatenate(obs), np.concatenate(act), None, meta)


def train_dapg(
    policy: DexRepNetPolicy,
    sampler: Sampler,
    out_dir: str | Path,
    config: DAPGConfig = DAPGConfig(),
    demos: DemoDataset | None = None,
    resume: bool = False,
    metadata: Mapping[str, Any] | None = None,
) -> DAPGResult:
    """Fine-tune `policy` with DAPG; with resume=True continue from out_dir/dapg_state.pt if present.

    A fresh start refuses a folder that already holds a run; a resume refuses a changed config
    (only `iterations` and the logging options may change).
    """
    trainer = DAPGTrainer(policy, sampler, out_dir, config, demos, metadata)
    if trainer.state_path.is_file() and not resume:
        raise DexdrakeError(f"{out_dir} already holds a DAPG run ({trainer.state_path.name}); "
                            "continue it with --resume or choose another output folder")
    if resume and trainer.state_path.is_file():
        trainer.load_state()
        now = {k: v for k, v in json.loads(json.dumps(asdict(config))).items() if k not in RESUMABLE_CHANGES}
        defaults = json.loads(json.dumps(asdict(DAPGConfig())))  # a state older than a field ran its default
        saved = {k: v for k, v in {**defaults, **trainer.saved_config}.items() if k not in RESUMABLE_CHANGES}
        changed = sorted(k for k in now if saved.get(k) != now[k])
        if config.iterations < trainer.iteration:
            raise DexdrakeError(f"{out_dir} already ran {trainer.iteration} iterations; --iterations "
                                f"{config.iterations} would stop before them: give at least {trainer.iteration}")
        if changed:
            last = trainer.sessions[-1]["command"] if trainer.sessions else ""
            raise DexdrakeError(f"cannot resume {out_dir} with a changed config: {changed} "
                                f"(was {[saved.get(k) for k in changed]}, now {[now[k] for k in changed]}); "
                                f"resume with the options of its last session: {last}")
    return trainer.train()
