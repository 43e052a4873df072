"""The DexRepNet policy: one linear encoder per observation group, an MLP, a Gaussian head.

Architecture (paper): each observation group (e.g. hand state 105, occupancy+surface 1088,
local-geo 1408) passes its own single fully-connected layer to 128 features; we follow each
encoder with a ReLU (`encoder_activation="relu"`, the default; "none" keeps it purely
linear, which would compose with the first MLP layer into one low-rank linear map). The
features are concatenated and fed to an MLP with hidden sizes [512, 128] and ReLU whose
output is the action mean (no tanh; the env clips actions to [-1, 1]). With `residual_arm`
the arm's actions are the MLP's output added to the arm joints' current positions (the hand
block's first entries), normalised like the actions: the network learns how far its
set-point leads the arm instead of rebuilding the arm's position from its input (a departure
from the paper's absolute set-points, which `residual_arm=False` keeps). `arm_action` says
how the actions command the arm: its joints, or the palm's pose (dexdrake/hands/action_map.py).
For RL the
policy is a diagonal Gaussian around that mean with a learned, state-independent log-std,
kept in [min_log_std, max_log_std] by clamping the parameter itself after each update
(`clamp_log_std_`), so its gradient never vanishes. Before RL the log-std is set from the
spread of the demonstration actions (`set_log_std_from_actions`), as mjrl's behaviour cloning
does for the DAPG hand tasks, instead of std 1 over the whole [-1, 1] action range.

Observations are normalised inside the module with stored (mean, std) buffers, so a
checkpoint carries everything needed to run the policy on raw env observations.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from dexdrake.errors import DexdrakeError, NonFiniteError
from dexdrake.learn.env_protocol import observation_dim

CHECKPOINT_FORMAT = "dexdrake.policy/1"
# The scenario a checkpoint without a record of its own (metadata "scenario") was trained
# under: the shipped weights' plant step and control period (s), no driver target limits.
UNRECORDED_SCENARIO = {"time_step": 0.005, "control_period": 0.02, "target_limits": None, "depth_noise": False}
DEMO_STD_FRACTION = 0.5  # exploration std = this fraction of the demo actions' std, per dimension
ENCODER_ACTIVATIONS = ("relu", "none")
ACT_CHUNK = 8  # rows per network call in act_batch (see there)


@dataclass(frozen=True)
class PolicyConfig:
    """Everything needed to rebuild a policy's architecture (stored in checkpoints)."""

    blocks: tuple[tuple[str, int], ...]  # ordered (group name, size)
    action_dim: int
    feature_set: str = "unspecified"  # e.g. "dexrep", "hand2obj", "pglo"
    hand: str = "unspecified"  # hand description name, e.g. "adroit"
    encoder_dim: int = 128
    hidden_sizes: tuple[int, ...] = (512, 128)
    encoder_activation: str = "relu"
    init_log_std: float = 0.0
    min_log_std: float = -3.0
    max_log_std: float = 0.0  # std 1: the half-width of the normalised action range
    residual_arm: bool = False  # arm actions = current arm position (normalised) + MLP output
    arm_action: str = "joints"  # how the actions command the arm (dexdrake/hands/action_map.py)

    @classmethod
    def from_blocks(cls, blocks: Mapping[str, int], action_dim: int, **kwargs: Any) -> PolicyConfig:
        """Config from an env's `observation_blocks` mapping."""
        return cls(blocks=tuple((str(k), int(v)) for k, v in blocks.items()), action_dim=action_dim, **kwargs)

    @property
    def obs_dim(self) -> int:
        return observation_dim(dict(self.blocks))

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["blocks"] = [[name, size] for name, size in self.blocks]
        d["hidden_sizes"] = list(self.hidden_sizes)
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> PolicyConfig:
        d = dict(d)
        d["blocks"] = tuple((str(n), int(s)) for n, s in d["blocks"])
        d["hidden_sizes"] = tuple(int(h) for h in d["hidden_sizes"])
        return cls(**d)


class DexRepNetPolicy(nn.Module):
    """Per-group encoders -> MLP [512, 128] -> action mean; Gaussian head for RL."""

    def __init__(self, config: PolicyConfig):
        super().__init__()
        obs_dim = config.obs_dim  # validates the blocks
        if config.action_dim <= 0:
            raise DexdrakeError(f"action_dim must be positive, got {config.action_dim}")
        if not config.min_log_std <= config.init_log_std <= config.max_log_std:
            raise DexdrakeError(f"need min_log_std <= init_log_std <= max_log_std, got {config.min_log_std}, "
                                f"{config.init_log_std}, {config.max_log_std}")
        if config.encoder_activation not in ENCODER_ACTIVATIONS:
            raise DexdrakeError(
                f"encoder_activation {config.encoder_activation!r} not in {ENCODER_ACTIVATIONS}"
            )
        self.config = config
        self.block_names = [name for name, _ in config.blocks]
        self.block_sizes = [size for _, size in config.blocks]
        self.encoders = nn.ModuleDict({name: nn.Linear(size, config.encoder_dim) for name, size in config.blocks})
        layers: list[nn.Module] = []
        width = config.encoder_dim * len(config.blocks)
        for h in config.hidden_sizes:
            layers += [nn.Linear(width, h), nn.ReLU()]
            width = h
        layers.append(nn.Linear(width, config.action_dim))
        self.mlp = nn.Sequential(*layers)
        self.log_std = nn.Parameter(torch.full((config.action_dim,), float(config.init_log_std)))
        self.register_buffer("obs_mean", torch.zeros(obs_dim))
        self.register_buffer("obs_std", torch.ones(obs_dim))
        self.register_buffer("encoders_frozen", torch.tensor(False))
        if config.residual_arm:
            mid, half = arm_action_map(config)
            self.register_buffer("arm_mid", torch.as_tensor(mid, dtype=torch.float32))
            self.register_buffer("arm_half", torch.as_tensor(half, dtype=torch.float32))

    # ---------------------------------------------------------------- forward passes
    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Action mean for raw (unnormalised) observations of shape (..., obs_dim)."""
        if obs.shape[-1] != self.obs_mean.shape[0]:
            raise DexdrakeError(f"observation has size {obs.shape[-1]}, policy expects {self.obs_mean.shape[0]}")
        x = (obs - self.obs_mean) / self.obs_std
        parts = torch.split(x, self.block_sizes, dim=-1)
        feats = [self.encoders[name](part) for name, part in zip(self.block_names, parts)]
        if self.config.encoder_activation == "relu":
            feats = [torch.relu(f) for f in feats]
        mean = self.mlp(torch.cat(feats, dim=-1))
        if not self.config.residual_arm:
            return mean
        n = self.arm_mid.shape[0]
        arm = mean[..., :n] + (obs[..., :n] - self.arm_mid) / self.arm_half
        return torch.cat([arm, mean[..., n:]], dim=-1)

    def clamped_log_std(self) -> torch.Tensor:
        """The log-std in use (equal to the parameter once `clamp_log_std_` has run)."""
        return torch.clamp(self.log_std, self.config.min_log_std, self.config.max_log_std)

    def clamp_log_std_(self) -> None:
        """Clamp the log-std parameter itself into [min_log_std, max_log_std] (after each update)."""
        with torch.no_grad():
            self.log_std.clamp_(self.config.min_log_std, self.config.max_log_std)

    def set_log_std_from_actions(self, actions: np.ndarray, fraction: float = DEMO_STD_FRACTION) -> np.ndarray:
        """Set the log-std to log(fraction * per-dimension std of `actions` (N, A)), clamped
        into [min_log_std, max_log_std]; returns the std set."""
        actions = np.asarray(actions, dtype=np.float64)
        if actions.ndim != 2 or actions.shape[1] != self.config.action_dim or actions.shape[0] < 2:
            raise DexdrakeError(f"need >= 2 actions of size {self.config.action_dim}, got shape {actions.shape}")
        if not fraction > 0 or not np.all(np.isfinite(actions)):
            raise DexdrakeError(f"fraction must be positive and actions finite (fraction {fraction})")
        log_std = np.log(fraction * actions.std(axis=0) + 1e-12)
        with torch.no_grad():
            self.log_std.copy_(torch.as_tensor(log_std, dtype=torch.float32))
        self.clamp_log_std_()
        return np.exp(self.log_std.detach().numpy().astype(np.float64))

    def log_prob(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Gaussian log-likelihood of `actions` (N, A) under the policy at `obs` (N, D)."""
        mean = self.forward(obs)
        log_std = self.clamped_log_std()
        z = (actions - mean) / torch.exp(log_std)
        return -0.5 * (z**2).sum(-1) - log_std.sum() - 0.5 * self.config.action_dim * math.log(2 * math.pi)

    def act(self, obs: np.ndarray, rng: np.random.Generator | None = None) -> tuple[np.ndarray, float]:
        """One action for one observation: the mean if `rng` is None, else a Gaussian sample.

        Returns (action, log-probability of that action under the Gaussian); `act_batch` of one row.
        """
        actions, log_probs = self.act_batch(np.asarray(obs)[None], [rng])
        return actions[0], float(log_probs[0])

    @torch.inference_mode()
    def act_batch(self, obs: np.ndarray, rngs: Sequence[np.random.Generator | None]) -> tuple[np.ndarray, np.ndarray]:
        """Actions (K, A) and their log-probabilities (K,) for K observations (K, obs_dim): row k
        is the mean if rngs[k] is None, else a Gaussian sample drawn from rngs[k].

        The network runs on chunks of exactly ACT_CHUNK rows (the last zero-padded): a GEMM
        rounds by its row count, so a fixed count makes a row's action independent of K (1
        included) wherever the layers round alike at every row position, as the DexRep
        policies' do (tests/test_lockstep.py checks the shipped one); a tiny layer (a 2-wide
        output) may round by position, within float32 precision."""
        o = np.asarray(obs, dtype=np.float32)
        k = len(o)
        padded = np.zeros((-(-k // ACT_CHUNK) * ACT_CHUNK, o.shape[1]), dtype=np.float32)
        padded[:k] = o
        x = torch.from_numpy(padded)
        mean = torch.cat([self.forward(c) for c in x.split(ACT_CHUNK)])[:k].numpy().astype(np.float64)
        log_std = self.clamped_log_std().numpy().astype(np.float64)
        noise = np.stack([np.zeros(mean.shape[1]) if r is None else r.standard_normal(mean.shape[1]) for r in rngs])
        actions = mean + np.exp(log_std) * noise
        log_probs = (-0.5 * np.einsum("ij,ij->i", noise, noise) - float(log_std.sum())
                     - 0.5 * mean.shape[1] * math.log(2 * math.pi))
        return actions, log_probs

    # ---------------------------------------------------------------- normalisation
    def set_obs_normalization(self, mean: np.ndarray, std: np.ndarray, min_std: float = 1e-3,
                              keep_function: bool = False) -> None:
        """Store observation statistics; std below `min_std` (constant features) becomes 1.

        With `keep_function` the encoders are re-expressed for the new statistics (each input
        column's weights scaled by new/old std, the bias moved by the mean's shift), so a trained
        policy acts exactly as before: refitting the statistics of a warm-started policy to data
        of other objects otherwise moves its inputs by up to tens of their old stds at once."""
        mean = np.asarray(mean, dtype=np.float32)
        std = np.asarray(std, dtype=np.float32)
        d = self.obs_mean.shape[0]
        if mean.shape != (d,) or std.shape != (d,):
            raise DexdrakeError(f"normalisation stats must have shape ({d},), got {mean.shape} and {std.shape}")
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(std))):
            raise DexdrakeError("normalisation stats contain non-finite values")
        std = np.where(std < min_std, 1.0, std).astype(np.float32)
        if keep_function:
            with torch.no_grad():
                shift = (torch.from_numpy(mean) - self.obs_mean) / self.obs_std
                ratio = torch.from_numpy(std) / self.obs_std
                for name, cols in zip(self.block_names, torch.split(torch.arange(len(std)), self.block_sizes)):
                    enc = self.encoders[name]
                    enc.bias += enc.weight @ shift[cols]
                    enc.weight *= ratio[cols]
        self.obs_mean.copy_(torch.from_numpy(mean))
        self.obs_std.copy_(torch.from_numpy(std))

    # ---------------------------------------------------------------- parameters
    def freeze_encoders(self) -> None:
        """Stop training the per-group encoders (done after behaviour cloning)."""
        for p in self.encoders.parameters():
            p.requires_grad_(False)
        self.encoders_frozen.fill_(True)

    def trainable_parameters(self) -> Iterator[nn.Parameter]:
        return (p for p in self.parameters() if p.requires_grad)

    def load_weights(self, state_dict: Mapping[str, torch.Tensor]) -> None:
        """Load a state dict and re-apply the encoder freeze it records."""
        self.load_state_dict(state_dict)
        if bool(self.encoders_frozen):
            self.freeze_encoders()


def widened(policy: DexRepNetPolicy, config: PolicyConfig) -> DexRepNetPolicy:
    """`policy` with the observation groups that `config` appends to its own: their encoders
    start random and the MLP's first layer reads them through zero weights, so the widened
    policy acts exactly as `policy` until training makes use of the new inputs."""
    old = policy.config
    n = len(old.blocks)
    if config.blocks[:n] != old.blocks or replace(config, blocks=old.blocks, feature_set=old.feature_set) != old:
        raise DexdrakeError(f"cannot widen a policy with blocks {old.blocks} to {config.blocks}: the new "
                            "blocks must extend the old ones, and the rest of the architecture must match")
    new = DexRepNetPolicy(config)
    state = new.state_dict()
    for key, value in policy.state_dict().items():
        target = state[key]
        if key == "mlp.0.weight":
            target.zero_()
            target[:, : value.shape[1]] = value
        elif key in ("obs_mean", "obs_std"):
            target[: value.shape[0]] = value
        else:
            target.copy_(value)
    new.load_weights(state)
    return new


def check_policy_fits(config: PolicyConfig, hand: str, feature_set: str, source: str) -> None:
    """The one compatibility check of a policy with what will run it: raise DexdrakeError
    (naming `source`, the checkpoint) unless `config` was trained for hand `hand` on
    `feature_set`, with that hand's joint count as actions and that feature set's size as
    observations."""
    from dexdrake.dexrep.feature_sets import observation_blocks
    from dexdrake.hands.description import load_hand

    if config.hand != hand:
        raise DexdrakeError(f"{source} was trained for hand {config.hand!r}, not {hand!r}")
    if config.feature_set != feature_set:
        raise DexdrakeError(f"{source} was trained on feature set {config.feature_set!r}, not {feature_set!r}")
    description = load_hand(hand)
    if config.action_dim != description.num_actuators:
        raise DexdrakeError(f"{source} has {config.action_dim} actions, hand {hand!r} has "
                            f"{description.num_actuators} joints")
    size = sum(observation_blocks(description, feature_set).values())
    if size != config.obs_dim:
        raise DexdrakeError(f"{source} expects {config.obs_dim} observations, feature set {feature_set!r} "
                            f"gives {size}")


def arm_action_map(config: PolicyConfig) -> tuple[np.ndarray, np.ndarray]:
    """(mid, half) of the joint action map (dexdrake/hands/action_map.py) on the arm joints of
    `config.hand` (a prefix of its actions), for a residual arm head, whose observation must
    begin with the hand block's joint positions."""
    from dexdrake.hands.action_map import ActionMap
    from dexdrake.hands.description import load_hand

    if not config.blocks or config.blocks[0][0] != "hand":
        raise DexdrakeError(f"a residual arm needs the hand block first; the blocks are {config.blocks}")
    if config.arm_action != "joints":
        raise DexdrakeError(f"a residual arm leads the arm's joints; the policy's arm action is {config.arm_action!r}")
    hand = load_hand(config.hand)
    if len(hand.policy_joints) != config.action_dim:
        raise DexdrakeError(f"hand {config.hand} has {len(hand.policy_joints)} joints, the policy {config.action_dim} actions")
    actions = ActionMap(hand)
    n = len(hand.arm_joints)
    return actions.mid[:n], actions.half[:n]


def non_finite_tensors(state: Mapping[str, Any]) -> list[str]:
    """Names of the floating-point tensors in `state` holding a NaN or an infinity."""
    return [k for k, v in state.items()
            if isinstance(v, torch.Tensor) and v.is_floating_point() and not bool(torch.isfinite(v).all())]


def policy_payload(policy: DexRepNetPolicy, metadata: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The checkpoint contents: format tag, config dict, CPU state dict, free-form metadata;
    NonFiniteError if a weight is NaN or infinite (a diverged training is never saved)."""
    bad = non_finite_tensors(policy.state_dict())
    if bad:
        raise NonFiniteError(f"the policy's weights {bad[:3]} are not finite: the training diverged "
                             "(lower the learning rate); no checkpoint written")
    return {
        "format": CHECKPOINT_FORMAT,
        "config": policy.config.to_dict(),
        "state_dict": {k: v.detach().cpu().clone() for k, v in policy.state_dict().items()},
        "metadata": dict(metadata or {}),
    }


def save_policy(path: str | Path, policy: DexRepNetPolicy, metadata: Mapping[str, Any] | None = None) -> Path:
    """Write a checkpoint (format tag, config dict, state dict, free-form metadata)."""
    return save_payload(path, policy_payload(policy, metadata))


def save_payload(path: str | Path, payload: Mapping[str, Any]) -> Path:
    """Write a checkpoint payload atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(dict(payload), tmp)
    tmp.replace(path)
    return path


def policy_from_payload(payload: Mapping[str, Any]) -> DexRepNetPolicy:
    """Rebuild a policy from an in-memory checkpoint payload (see `save_policy`)."""
    if payload.get("format") != CHECKPOINT_FORMAT:
        raise DexdrakeError(f"not a {CHECKPOINT_FORMAT} checkpoint (format={payload.get('format')!r})")
    try:
        policy = DexRepNetPolicy(PolicyConfig.from_dict(payload["config"]))
        policy.load_weights(payload["state_dict"])
    except (KeyError, TypeError, RuntimeError) as exc:
        raise DexdrakeError(f"policy checkpoint does not match its config: {exc}") from exc
    return policy


def load_policy(path: str | Path) -> tuple[DexRepNetPolicy, dict[str, Any]]:
    """Rebuild a policy from a checkpoint file alone, or from a training state that holds one
    under "policy" (DAPG's resumable states); returns (policy in eval mode, metadata). The
    metadata's "scenario" is the one it was trained under (systems/scenario.scenario_record),
    UNRECORDED_SCENARIO for a checkpoint that records none."""
    path = Path(path)
    if path.is_dir():
        raise DexdrakeError(f"policy checkpoint {path} is a folder; give the .pt file in it "
                            f"(e.g. {path / 'dagger_policy.pt'})")
    if not path.is_file():
        raise DexdrakeError(f"policy checkpoint {path} does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a bad file; its advice to load
        # with weights_only=False (running pickled code) is not repeated
        raise DexdrakeError(f"cannot read policy checkpoint {path}: not a dexdrake policy file "
                            f"({type(exc).__name__}; only tensors and plain data are loaded)") from exc
    if not isinstance(payload, Mapping):
        raise DexdrakeError(f"policy checkpoint {path} holds a {type(payload).__name__}, not a policy")
    if isinstance(payload.get("policy"), Mapping):  # a training state (e.g. DAPG's dapg_iter_XXXX.pt)
        payload = payload["policy"]
    bad = non_finite_tensors(payload.get("state_dict") or {})
    if bad:
        raise NonFiniteError(f"policy checkpoint {path} holds non-finite weights {bad[:3]} "
                             "(from a diverged training); train again with a lower learning rate")
    policy = policy_from_payload(payload)
    policy.eval()
    metadata = dict(payload.get("metadata", {}))
    metadata.setdefault("scenario", dict(UNRECORDED_SCENARIO))
    return policy, metadata

