"""Value-function baseline: an MLP on (normalised observation, time) fit to returns.

As in mjrl's MLPBaseline it is refit each DAPG iteration with a persistent Adam
(defaults: batch 64, 2 epochs, lr 1e-3). The time feature t / horizon lets it represent a
finite-horizon value. Targets are standardised with statistics fixed at the first fit,
because DexRep rewards reach tens per step and raw returns are in the thousands.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from dexdrake.errors import DexdrakeError


class MLPBaseline(nn.Module):
    def __init__(
        self,
        obs_dim: int,
        horizon: int,
        obs_mean: np.ndarray | None = None,
        obs_std: np.ndarray | None = None,
        hidden_sizes: Sequence[int] = (128, 128),
        lr: float = 1e-3,
    ):
        super().__init__()
        if obs_dim <= 0 or horizon <= 0:
            raise DexdrakeError(f"obs_dim and horizon must be positive, got {obs_dim}, {horizon}")
        self.horizon = int(horizon)
        layers: list[nn.Module] = []
        width = obs_dim + 1
        for h in hidden_sizes:
            layers += [nn.Linear(width, h), nn.ReLU()]
            width = h
        layers.append(nn.Linear(width, 1))
        self.net = nn.Sequential(*layers)
        mean = np.zeros(obs_dim) if obs_mean is None else np.asarray(obs_mean)
        std = np.ones(obs_dim) if obs_std is None else np.asarray(obs_std)
        self.register_buffer("obs_mean", torch.as_tensor(mean, dtype=torch.float32).clone())
        self.register_buffer("obs_std", torch.as_tensor(std, dtype=torch.float32).clamp_min(1e-6).clone())
        self.register_buffer("target_mean", torch.tensor(0.0))
        self.register_buffer("target_std", torch.tensor(1.0))
        self.register_buffer("fitted", torch.tensor(False))
        self.optimiser = torch.optim.Adam(self.net.parameters(), lr=lr)

    def _features(self, obs: np.ndarray, times: np.ndarray) -> torch.Tensor:
        o = (torch.as_tensor(obs, dtype=torch.float32) - self.obs_mean) / self.obs_std
        t = torch.as_tensor(np.asarray(times, dtype=np.float32) / self.horizon).unsqueeze(-1)
        return torch.cat([o, t], dim=-1)

    @torch.no_grad()
    def predict(self, obs: np.ndarray, times: np.ndarray) -> np.ndarray:
        """Value estimates (N,) for observations (N, D) at step indices `times` (N,)."""
        out = self.net(self._features(obs, times)).squeeze(-1)
        return (out * self.target_std + self.target_mean).numpy().astype(np.float64)

    def fit(
        self,
        obs: np.ndarray,
        times: np.ndarray,
        returns: np.ndarray,
        rng: np.random.Generator,
        epochs: int = 2,
        batch_size: int = 64,
    ) -> tuple[float, float]:
        """Regress returns by minibatch Adam; returns the MSE (in return units) before and after."""
        returns = np.asarray(returns, dtype=np.float64)
        if not np.all(np.isfinite(returns)):
            raise DexdrakeError("baseline targets contain non-finite returns")
        if not bool(self.fitted):
            self.target_mean.fill_(float(returns.mean()))
            self.target_std.fill_(max(float(returns.std()), 1e-6))
            self.fitted.fill_(True)
        x = self._features(obs, times)
        y = (torch.as_tensor(returns, dtype=torch.float32) - self.target_mean) / self.target_std
        scale = float(self.target_std) ** 2
        with torch.no_grad():
            before = float(((self.net(x).squeeze(-1) - y) ** 2).mean()) * scale
        for _ in range(epochs):
            perm = torch.as_tensor(rng.permutation(x.shape[0]))
            for i in range(0, x.shape[0], batch_size):
                idx = perm[i : i + batch_size]
                loss = ((self.net(x[idx]).squeeze(-1) - y[idx]) ** 2).mean()
                self.optimiser.zero_grad(set_to_none=True)
                loss.backward()
                self.optimiser.step()
        with torch.no_grad():
            after = float(((self.net(x).squeeze(-1) - y) ** 2).mean()) * scale
        return before, after

    def full_state(self) -> dict[str, Any]:
        """Weights, statistics and optimiser state (for resumable checkpoints)."""
        return {"module": self.state_dict(), "optimiser": self.optimiser.state_dict()}

    def load_full_state(self, state: dict[str, Any]) -> None:
        self.load_state_dict(state["module"])
        self.optimiser.load_state_dict(state["optimiser"])
