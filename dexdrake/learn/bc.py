"""Behaviour cloning of the DexRepNet policy from demonstration (observation, action) pairs.

Paper defaults: Adam, 150 epochs, batch 64, lr 1e-5, loss mean_i ||pi(s_i) - a_i||^2.
"""

from __future__ import annotations

import math
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
from dexdrake.learn.curves import CsvLog, plot_curves
from dexdrake.learn.demo_dataset import DemoDataset, load_demo_dataset, save_demo_dataset
from dexdrake.learn.policy import DexRepNetPolicy, save_policy
from dexdrake.outputs import RUN_LOGS

__all__ = ["BCConfig", "BCResult", "bc_loss", "train_bc", "split_train_val", "load_demo_dataset", "save_demo_dataset"]


@dataclass(frozen=True)
class BCConfig:
    """A behaviour-cloning fit's settings; those with a "help" are `dexdrake train bc`'s flags."""

    epochs: int = field(default=150, metadata={"help": "training epochs", "type": argtypes.count})
    batch_size: int = field(default=64, metadata={"help": "minibatch size", "type": argtypes.count})
    lr: float = field(default=1e-5, metadata={"help": "Adam(W) learning rate", "type": argtypes.positive})
    weight_decay: float = field(default=0.0, metadata={"type": argtypes.non_negative,
                                                       "help": "decoupled weight decay of the BC fits (AdamW; 0: Adam)"})
    obs_noise: float = field(default=0.0, metadata={
        "type": argtypes.non_negative,
        "help": "Gaussian noise on the BC fits' training inputs, in observation stds (0: none)"})
    val_fraction: float = 0.1  # split by episode when the dataset has episode_starts
    checkpoint_every: int = 25  # epochs; 0 disables periodic checkpoints
    seed: int = field(default=0, metadata={"help": "shuffling and initialisation", "type": argtypes.seed})
    split_seed: int | None = None  # the train/validation split (None: `seed`)
    fit_normalization: bool = True  # set the policy's observation stats from the train split ...
    keep_function: bool = False  # ... re-expressing its encoders so it acts as before (warm starts)
    action_weights: tuple[float, ...] = ()  # per-dimension weights of the fitted loss (empty: all 1);
    # the logged losses stay unweighted
    progress: bool = True  # tqdm bar
    device: str = "cpu"


@dataclass
class BCResult:
    train_loss: list[float] = field(default_factory=list)
    val_loss: list[float] = field(default_factory=list)
    best_epoch: int = -1
    best_val_loss: float = float("inf")
    best_checkpoint: Path | None = None
    last_checkpoint: Path | None = None
    log_csv: Path | None = None
    val_indices: np.ndarray | None = None  # the held-out samples (whole episodes where known)


def split_train_val(dataset: DemoDataset, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Train/validation sample indices; whole episodes go to one side when episodes are known.

    Episode e is held out when the e-th draw of a `seed`ed uniform stream is below
    `val_fraction`, so a dataset that grows by appending episodes (DAgger) keeps its earlier
    episodes on the same side: a held-out episode is never trained on in a later fit (at
    least one episode goes to each side).
    """
    if not 0.0 <= val_fraction < 1.0:
        raise DexdrakeError(f"val_fraction must be in [0, 1), got {val_fraction}")
    rng = np.random.default_rng(seed)
    n = len(dataset)
    if val_fraction == 0.0:
        return np.arange(n), np.arange(0)
    episodes = dataset.episode_ids()
    n_ep = int(episodes.max()) + 1
    if n_ep >= 2:
        draws = rng.random(n_ep)
        val_eps = np.nonzero(draws < val_fraction)[0]
        if len(val_eps) == 0:
            val_eps = np.array([int(np.argmin(draws))])
        elif len(val_eps) == n_ep:
            val_eps = np.delete(val_eps, int(np.argmax(draws)))
        is_val = np.isin(episodes, val_eps)
    else:
        n_val = max(1, int(round(val_fraction * n)))
        if n_val >= n:
            raise DexdrakeError(f"val_fraction {val_fraction} leaves no training sample out of {n}")
        is_val = np.zeros(n, dtype=bool)
        is_val[rng.choice(n, size=n_val, replace=False)] = True
    return np.nonzero(~is_val)[0], np.nonzero(is_val)[0]


def _bc_loss(policy: DexRepNetPolicy, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
    return ((policy(obs) - act) ** 2).sum(-1).mean()


def _action_weights(config: BCConfig, action_dim: int) -> torch.Tensor:
    if not config.action_weights:
        return torch.ones(action_dim)
    w = torch.as_tensor(config.action_weights, dtype=torch.float32)
    if w.shape != (action_dim,) or not bool(torch.all(w > 0)) or not bool(torch.all(torch.isfinite(w))):
        raise DexdrakeError(f"action_weights must be {action_dim} positive numbers, got {config.action_weights}")
    return w


def bc_loss(policy: DexRepNetPolicy, dataset: DemoDataset) -> float:
    """The cloning loss (squared error summed over action dimensions, mean over samples) of
    `policy` on all of `dataset`."""
    policy.eval()
    return _eval_loss(policy, torch.as_tensor(dataset.observations), torch.as_tensor(dataset.actions),
                      torch.arange(len(dataset)))


@torch.no_grad()
def _eval_loss(policy: DexRepNetPolicy, obs: torch.Tensor, act: torch.Tensor, rows: torch.Tensor,
               batch: int = 4096) -> float:
    """The mean cloning loss over `rows` of (obs, act), gathered a batch at a time."""
    total = 0.0
    for i in range(0, rows.shape[0], batch):
        r = rows[i : i + batch]
        total += float(_bc_loss(policy, obs[r].float(), act[r])) * r.shape[0]
    return total / rows.shape[0]


def _mean_std(x: np.ndarray, rows: np.ndarray, chunk: int = 16384) -> tuple[np.ndarray, np.ndarray]:
    """Per-column mean and standard deviation of x[rows], two passes over chunks of rows
    (float64 sums), so a dataset of 10^6 observations is never copied whole."""
    total = np.zeros(x.shape[1])
    for i in range(0, len(rows), chunk):
        total += x[rows[i : i + chunk]].sum(0, dtype=np.float64)
    mean = total / len(rows)
    squares = np.zeros(x.shape[1])
    for i in range(0, len(rows), chunk):
        squares += ((x[rows[i : i + chunk]] - mean) ** 2).sum(0)
    return mean.astype(np.float32), np.sqrt(squares / len(rows)).astype(np.float32)


def _check_finite(loss: float, which: str, epoch: int, config: BCConfig) -> None:
    """NonFiniteError (training stops, this epoch writes nothing) if `loss` is NaN or infinite."""
    if not math.isfinite(loss):
        raise NonFiniteError(f"BC epoch {epoch}: the {which} loss is {loss} (learning rate {config.lr:g}); "
                             "training stopped, no checkpoint written for it; lower the learning rate")


def train_bc(
    policy: DexRepNetPolicy,
    dataset: DemoDataset,
    out_dir: str | Path,
    config: BCConfig = BCConfig(),
    metadata: Mapping[str, Any] | None = None,
) -> BCResult:
    """Fit the policy mean to the demo actions (squared error, weighted per action dimension by
    `config.action_weights`); writes bc_log.csv/png and checkpoints to out_dir.

    Checkpoints: bc_best.pt (lowest validation loss; training loss without a split),
    bc_last.pt, and bc_epoch_XXXX.pt every `checkpoint_every` epochs. The policy is left
    with its final-epoch weights.
    """
    if config.epochs <= 0 or config.batch_size <= 0 or config.lr <= 0:
        raise DexdrakeError(f"epochs, batch_size and lr must be positive: {config}")
    if not (config.weight_decay >= 0 and config.obs_noise >= 0):
        raise DexdrakeError(f"weight_decay and obs_noise must be >= 0: {config}")
    d, a = policy.config.obs_dim, policy.config.action_dim
    if dataset.observations.shape[1] != d or dataset.actions.shape[1] != a:
        raise DexdrakeError(
            f"dataset has obs/action sizes {dataset.observations.shape[1]}/{dataset.actions.shape[1]}, "
            f"policy expects {d}/{a}"
        )
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(config.seed)
    split_seed = config.seed if config.split_seed is None else config.split_seed
    train_idx, val_idx = split_train_val(dataset, config.val_fraction, split_seed)
    if config.fit_normalization:
        policy.set_obs_normalization(*_mean_std(dataset.observations, train_idx), keep_function=config.keep_function)
    device = torch.device(config.device)
    policy.to(device).train()
    # Batches are gathered from the whole arrays by row (no copy of the training split).
    obs = torch.as_tensor(dataset.observations, device=device)
    act = torch.as_tensor(dataset.actions, device=device)
    rows_tr = torch.as_tensor(train_idx, device=device)
    rows_va = torch.as_tensor(val_idx, device=device)
    weights = _action_weights(config, a).to(device)
    optimiser = torch.optim.AdamW(policy.trainable_parameters(), lr=config.lr, weight_decay=config.weight_decay)
    gen = torch.Generator().manual_seed(config.seed)
    meta = {"stage": "bc", "bc_config": asdict(config), **dict(metadata or {})}
    result = BCResult(log_csv=out_dir / RUN_LOGS["BC"], val_indices=val_idx)
    log = CsvLog(result.log_csv, ["epoch", "train_loss", "val_loss", "seconds"])
    bar = tqdm(range(1, config.epochs + 1), desc="BC", unit="epoch", disable=not config.progress)
    for epoch in bar:
        t0 = time.perf_counter()
        perm = torch.randperm(rows_tr.shape[0], generator=gen).to(device)
        total = 0.0
        for i in range(0, perm.shape[0], config.batch_size):
            idx = rows_tr[perm[i : i + config.batch_size]]
            x = obs[idx].float()  # a batch of float16 observations (DAgger's aggregate) in float32
            if config.obs_noise:
                x = x + config.obs_noise * policy.obs_std * torch.randn(x.shape, generator=gen).to(device)
            err = (policy(x) - act[idx]) ** 2
            optimiser.zero_grad(set_to_none=True)
            (err * weights).sum(-1).mean().backward()
            optimiser.step()
            total += err.detach().sum().item()
            _check_finite(total, "training", epoch, config)
        train_loss = total / perm.shape[0]
        val_loss = _eval_loss(policy, obs, act, rows_va) if len(val_idx) else float("nan")
        if len(val_idx):
            _check_finite(val_loss, "validation", epoch, config)
        result.train_loss.append(train_loss)
        result.val_loss.append(val_loss)
        log.append({"epoch": epoch, "train_loss": train_loss, "val_loss": val_loss, "seconds": time.perf_counter() - t0})
        bar.set_postfix(train=f"{train_loss:.4g}", val=f"{val_loss:.4g}")
        score = val_loss if len(val_idx) else train_loss
        ep_meta = {**meta, "epoch": epoch, "train_loss": train_loss, "val_loss": val_loss}
        if score < result.best_val_loss:
            result.best_val_loss, result.best_epoch = score, epoch
            result.best_checkpoint = save_policy(out_dir / "bc_best.pt", policy, ep_meta)
        if config.checkpoint_every and epoch % config.checkpoint_every == 0:
            save_policy(out_dir / f"bc_epoch_{epoch:04d}.pt", policy, ep_meta)
    result.last_checkpoint = save_policy(out_dir / "bc_last.pt", policy, ep_meta)
    plot_curves(result.log_csv, out_dir / "bc_log.png", "epoch", ["train_loss", "val_loss"], title="behaviour cloning")
    policy.cpu().eval()
    return result
