"""Trains the PointNet auto-encoder on a set of meshes and writes the frozen encoder.

Data: `train` uses the object library's "train" split (evaluated on "unseen"), `primitives`
a seeded set of trimesh primitives (for debugging without the library), any other value is
a folder of meshes (every 5th file, sorted, is held out as unseen). Each step samples a
fresh 2048-point cloud from a random training mesh under a random rotation and anisotropic
scale (augmentation), normalised by centroid and max radius. Loss: Chamfer + 1e-3 times the
feature-transform orthogonality penalty. Writes the encoder weights and <out>.json.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from dexdrake import argtypes
from dexdrake.dexrep.pointnet import (
    NUM_POINTS,
    PointNetAutoEncoder,
    chamfer_distance,
    normalise_cloud,
    orthogonality_penalty,
    save_encoder,
)
from dexdrake.errors import DexdrakeError, NonFiniteError

MESH_SUFFIXES = (".obj", ".stl", ".ply", ".off", ".glb")


@dataclass(frozen=True)
class TrainConfig:
    """The auto-encoder's training settings, `dexdrake encoder train`'s flags."""

    meshes: str = field(default="train", metadata={"help": "'train' (object library), 'primitives' or a folder"})
    epochs: int = field(default=10, metadata={"help": "training epochs", "type": argtypes.count})
    steps_per_epoch: int = field(default=8, metadata={"help": "minibatches per epoch", "type": argtypes.count})
    batch_size: int = field(default=8, metadata={"help": "point clouds per minibatch", "type": argtypes.count})
    lr: float = field(default=1e-3, metadata={"help": "Adam learning rate", "type": argtypes.positive})
    seed: int = field(default=0, metadata={"help": "sampling and initialisation", "type": argtypes.seed})
    threads: int = field(default=1, metadata={"help": "torch CPU threads", "type": argtypes.count})


def primitive_meshes(seed: int = 0, count: int = 24) -> list[trimesh.Trimesh]:
    """A seeded variety of boxes, spheres, ellipsoids, cylinders, capsules, cones, tori."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        kind = i % 6
        a, b = rng.uniform(0.02, 0.08, 2)
        if kind == 0:
            m = trimesh.creation.box(rng.uniform(0.02, 0.15, 3))
        elif kind == 1:
            m = trimesh.creation.icosphere(3, a)
            m.apply_scale(rng.uniform(0.5, 1.5, 3))
        elif kind == 2:
            m = trimesh.creation.cylinder(a, 2 * b + 0.02, sections=32)
        elif kind == 3:
            m = trimesh.creation.capsule(2 * b, a * 0.6, count=[16, 16])
        elif kind == 4:
            m = trimesh.creation.cone(a, 2 * b + 0.02, sections=32)
        else:
            m = trimesh.creation.torus(a + 0.02, 0.3 * a + 0.005)
        out.append(m)
    return out


def load_mesh_sets(spec: str, seed: int = 0) -> tuple[list[trimesh.Trimesh], list[trimesh.Trimesh], str]:
    """(train meshes, unseen meshes, description of the data) for `--meshes spec`."""
    if spec == "primitives":
        return primitive_meshes(seed), primitive_meshes(seed + 1, 12), f"trimesh primitives (seed {seed})"
    if spec == "train":
        from dexdrake.objects.library import list_objects

        train = [trimesh.load(o.mesh_path, force="mesh") for o in list_objects("train")]
        unseen = [trimesh.load(o.mesh_path, force="mesh") for o in list_objects("unseen")]
        if not train:
            raise DexdrakeError("the object library has no 'train' objects")
        return train, unseen, f"object library: {len(train)} train, {len(unseen)} unseen"
    folder = Path(spec)
    if not folder.is_dir():
        raise DexdrakeError(f"--meshes must be 'train', 'primitives' or a folder; {spec!r} is neither")
    files = sorted(p for p in folder.rglob("*") if p.suffix.lower() in MESH_SUFFIXES)
    if len(files) < 2:
        raise DexdrakeError(f"{folder} holds {len(files)} meshes; need at least 2 (one held out)")
    meshes = [_load_mesh(p) for p in files]
    unseen = [m for i, m in enumerate(meshes) if i % 5 == 4] or meshes[-1:]
    train = [m for i, m in enumerate(meshes) if i % 5 != 4] if len(meshes) > 1 else meshes
    return train, unseen, f"{folder}: {len(train)} train, {len(unseen)} unseen"


def _load_mesh(path: Path) -> trimesh.Trimesh:
    """The mesh in `path`, or DexdrakeError naming the file if it holds no triangles."""
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as exc:  # trimesh raises many types for a damaged file
        raise DexdrakeError(f"cannot read {path} as a mesh ({type(exc).__name__}: {exc}); "
                            "remove it from the --meshes folder") from exc
    if len(getattr(mesh, "faces", ())) == 0 or not mesh.area > 0:
        raise DexdrakeError(f"{path} holds no triangles (an empty or damaged mesh); remove it from the --meshes folder")
    return mesh


def sample_cloud(mesh: trimesh.Trimesh, rng: np.random.Generator, augment: bool) -> np.ndarray:
    """A normalised (2048, 3) surface sample, randomly rotated and scaled if `augment`."""
    pts, _ = trimesh.sample.sample_surface(mesh, NUM_POINTS, seed=int(rng.integers(2**31)))
    if augment:
        pts = pts * rng.uniform(0.8, 1.2, 3)
        pts = pts @ Rotation.random(random_state=int(rng.integers(2**31))).as_matrix().T
    return normalise_cloud(pts).astype(np.float32)


@torch.no_grad()
def mean_chamfer(model: PointNetAutoEncoder, meshes: list[trimesh.Trimesh], seed: int) -> float:
    """Mean Chamfer distance (normalised units) of reconstructions of unaugmented samples."""
    if not meshes:
        return float("nan")
    model.eval()
    rng = np.random.default_rng(seed)
    x = torch.from_numpy(np.stack([sample_cloud(m, rng, False) for m in meshes]))
    values = [chamfer_distance(model(x[i:i + 8])[0], x[i:i + 8]).item() * len(x[i:i + 8])
              for i in range(0, len(x), 8)]
    return float(np.sum(values) / len(x))


def train(config: TrainConfig, out: Path, command: str = "") -> dict:
    """Trains, writes the encoder to `out` and the manifest to `out`.json; returns the manifest."""
    if config.epochs < 1 or config.batch_size < 2:
        raise DexdrakeError("need epochs >= 1 and batch size >= 2 (BatchNorm)")
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    train_meshes, unseen_meshes, data = load_mesh_sets(config.meshes, config.seed)
    model = PointNetAutoEncoder()
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=config.epochs * config.steps_per_epoch)
    start, history = time.time(), []
    for epoch in (bar := tqdm(range(config.epochs), desc="encoder", file=sys.stderr)):
        model.train()
        losses = []
        for _ in range(config.steps_per_epoch):
            idx = rng.integers(len(train_meshes), size=config.batch_size)
            x = torch.from_numpy(np.stack([sample_cloud(train_meshes[i], rng, True) for i in idx]))
            recon, t_feat = model(x)
            loss = chamfer_distance(recon, x) + 1e-3 * orthogonality_penalty(t_feat)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            losses.append(loss.item())
            if not math.isfinite(losses[-1]):
                raise NonFiniteError(f"encoder epoch {epoch}: the loss is {losses[-1]} (learning rate {config.lr:g}); "
                                     f"training stopped, {out} not written; lower the learning rate")
        history.append(float(np.mean(losses)))
        bar.set_postfix(loss=f"{history[-1]:.4f}")
    out = Path(out)
    save_encoder(model, out)
    manifest = dict(
        command=command or " ".join(sys.argv),
        data=data,
        config=config.__dict__,
        chamfer_train=mean_chamfer(model, train_meshes, config.seed + 100),
        chamfer_unseen=mean_chamfer(model, unseen_meshes, config.seed + 200),
        chamfer_units="squared distance on clouds normalised to unit max radius",
        loss_per_epoch=history,
        seconds=round(time.time() - start, 1),
        date=dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        torch=torch.__version__,
        weights="encoder only (the decoder is not needed at run time)",
    )
    out.with_suffix(".json").write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest
