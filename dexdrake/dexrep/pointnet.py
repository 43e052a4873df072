"""The PointNet auto-encoder of DexRepNet's public code, CPU-friendly.

Encoder: input T-net (3x3), shared MLP 3->64, feature T-net (64x64); the 64-d per-point
feature is taken after the feature transform; then 64->128->128->256->1024 and a max-pool
to the 1024-d global feature. Decoder: FC 1024->512->512->2048*3. Loss: Chamfer distance.
Clouds are normalised by their centroid and maximum radius before encoding.

Only the encoder is needed at run time; `save_encoder` writes just its weights.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from dexdrake.errors import DexdrakeError, NonFiniteError
from dexdrake.paths import models_dir

NUM_POINTS = 2048
LOCAL_DIM = 64
GLOBAL_DIM = 1024


def default_encoder_path() -> Path:
    """The shipped encoder weights: models/weights/pointnet_encoder.pt."""
    return models_dir() / "weights" / "pointnet_encoder.pt"


class TNet(nn.Module):
    """Predicts a k x k transform (initialised near the identity) from a (B, k, N) cloud."""

    def __init__(self, k: int):
        super().__init__()
        self.k = k
        self.convs = nn.Sequential(
            nn.Conv1d(k, 64, 1), nn.BatchNorm1d(64), nn.ReLU(),
            nn.Conv1d(64, 128, 1), nn.BatchNorm1d(128), nn.ReLU(),
            nn.Conv1d(128, 1024, 1), nn.BatchNorm1d(1024), nn.ReLU(),
        )
        self.fc = nn.Sequential(
            nn.Linear(1024, 512), nn.BatchNorm1d(512), nn.ReLU(),
            nn.Linear(512, 256), nn.BatchNorm1d(256), nn.ReLU(),
            nn.Linear(256, k * k),
        )
        nn.init.zeros_(self.fc[-1].weight)
        nn.init.zeros_(self.fc[-1].bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        feat = self.convs(x).amax(dim=2)
        eye = torch.eye(self.k, dtype=x.dtype, device=x.device)
        return self.fc(feat).view(-1, self.k, self.k) + eye


class PointNetEncoder(nn.Module):
    """(B, N, 3) normalised clouds -> (per-point (B, N, 64), global (B, 1024), T_feat)."""

    def __init__(self):
        super().__init__()
        self.input_tnet = TNet(3)
        self.conv1 = nn.Sequential(nn.Conv1d(3, 64, 1), nn.BatchNorm1d(64), nn.ReLU())
        self.feature_tnet = TNet(64)
        self.convs = nn.Sequential(
            nn.Conv1d(64, 128, 1), nn.BatchNorm1d(128), nn.ReLU(),
            nn.Conv1d(128, 128, 1), nn.BatchNorm1d(128), nn.ReLU(),
            nn.Conv1d(128, 256, 1), nn.BatchNorm1d(256), nn.ReLU(),
            nn.Conv1d(256, 1024, 1), nn.BatchNorm1d(1024),
        )

    def forward(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        x = points.transpose(1, 2)  # (B, 3, N)
        x = torch.bmm(self.input_tnet(x).transpose(1, 2), x)
        x = self.conv1(x)
        t_feat = self.feature_tnet(x)
        local = torch.bmm(t_feat.transpose(1, 2), x)  # (B, 64, N)
        glob = self.convs(local).amax(dim=2)
        return local.transpose(1, 2), glob, t_feat


class PointNetDecoder(nn.Module):
    """Global feature (B, 1024) -> reconstructed cloud (B, NUM_POINTS, 3)."""

    def __init__(self, num_points: int = NUM_POINTS):
        super().__init__()
        self.num_points = num_points
        self.fc = nn.Sequential(
            nn.Linear(GLOBAL_DIM, 512), nn.ReLU(),
            nn.Linear(512, 512), nn.ReLU(),
            nn.Linear(512, num_points * 3),
        )

    def forward(self, glob: torch.Tensor) -> torch.Tensor:
        return self.fc(glob).view(-1, self.num_points, 3)


class PointNetAutoEncoder(nn.Module):
    def __init__(self, num_points: int = NUM_POINTS):
        super().__init__()
        self.encoder = PointNetEncoder()
        self.decoder = PointNetDecoder(num_points)

    def forward(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Returns (reconstruction (B, N, 3), feature transform (B, 64, 64))."""
        _, glob, t_feat = self.encoder(points)
        return self.decoder(glob), t_feat


def chamfer_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean symmetric Chamfer distance (squared Euclidean) between (B, N, 3) and (B, M, 3)."""
    d = torch.cdist(a, b).square()
    return (d.amin(dim=2).mean(dim=1) + d.amin(dim=1).mean(dim=1)).mean()


def orthogonality_penalty(t: torch.Tensor) -> torch.Tensor:
    """PointNet's regulariser ||T T^T - I||^2 on the feature transform."""
    eye = torch.eye(t.shape[1], dtype=t.dtype, device=t.device)
    return (torch.bmm(t, t.transpose(1, 2)) - eye).square().sum(dim=(1, 2)).mean()


def normalise_cloud(points: np.ndarray) -> np.ndarray:
    """Centres a (N, 3) cloud on its centroid and scales its maximum radius to 1."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise DexdrakeError(f"expected an (N, 3) point cloud, got shape {pts.shape}")
    centred = pts - pts.mean(axis=0)
    radius = np.linalg.norm(centred, axis=1).max()
    if radius <= 0.0:
        raise DexdrakeError("point cloud has zero extent")
    return centred / radius


def _non_finite(state: dict[str, torch.Tensor]) -> list[str]:
    return [k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]


def save_encoder(model: PointNetAutoEncoder, path: Path) -> None:
    """Writes the encoder's weights (the decoder is not needed at run time) atomically;
    NonFiniteError if one is NaN or infinite."""
    state = model.encoder.state_dict()
    if _non_finite(state):
        raise NonFiniteError(f"the encoder's weights {_non_finite(state)[:3]} are not finite; {path} not written")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save(state, tmp)
    tmp.replace(path)


def load_encoder(path: Path | None = None) -> PointNetEncoder:
    """The frozen encoder from `path` (default: the shipped weights), in eval mode."""
    path = Path(path) if path is not None else default_encoder_path()
    if not path.exists():
        raise DexdrakeError(
            f"no PointNet encoder weights at {path}; train them with "
            "`dexdrake encoder train --meshes train --out models/weights/pointnet_encoder.pt`"
        )
    encoder = PointNetEncoder()
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        encoder.load_state_dict(state)
    except Exception as exc:  # torch raises many types for a damaged or foreign file
        raise DexdrakeError(f"cannot read PointNet encoder weights {path} ({type(exc).__name__}); "
                            "train them again with `dexdrake encoder train`") from exc
    if _non_finite(state):
        raise NonFiniteError(f"PointNet encoder weights {path} hold non-finite values {_non_finite(state)[:3]}; "
                             "train them again with a lower learning rate")
    encoder.eval()
    for p in encoder.parameters():
        p.requires_grad_(False)
    return encoder


@torch.no_grad()
def encode_cloud(encoder: PointNetEncoder, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-point (N, 64) and global (1024,) features of one cloud (normalised here)."""
    encoder.eval()
    x = torch.as_tensor(normalise_cloud(points), dtype=torch.float32)[None]
    local, glob, _ = encoder(x)
    return local[0].numpy().astype(np.float32), glob[0].numpy().astype(np.float32)
