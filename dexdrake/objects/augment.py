"""Scaled copies of the training objects: more shapes to train on, at no meshing cost.

Copy k of training object NAME is the object NAME_sK: NAME's mesh and convex pieces scaled
by (sx, sy, sz) about its centre of mass, each factor log-uniform in SCALE_RANGE and drawn
from a seed made of (NAME, k), so a copy's name fixes its shape. Scaling is affine: the
pieces stay convex (no CoACD run), the centre of mass stays at the origin and a stable
resting pose stays stable. Copies are split "augmented" (training only, never evaluated) and
keep the category of the object they copy, named in their meta.json as `derived_from` (the
grasp expert uses that object's grasp variant).
"""

from __future__ import annotations

import hashlib
import shutil

import numpy as np
import trimesh

from dexdrake.errors import DexdrakeError
from dexdrake.objects import store
from dexdrake.objects.meshfile import load_obj

SCALE_RANGE = (0.8, 1.25)  # per-axis scale factors of a copy


def copy_name(name: str, k: int) -> str:
    return f"{name}_s{k}"


def copy_scales(name: str, k: int) -> np.ndarray:
    """The (sx, sy, sz) of copy `k` of object `name`."""
    seed = int.from_bytes(hashlib.sha256(f"{name}:{k}".encode()).digest()[:8], "little")
    lo, hi = np.log(SCALE_RANGE)
    return np.exp(np.random.default_rng(seed).uniform(lo, hi, 3))


def _scaled(mesh: trimesh.Trimesh, scales: np.ndarray) -> trimesh.Trimesh:
    return trimesh.Trimesh(np.asarray(mesh.vertices) * scales, np.asarray(mesh.faces), process=False)


def build_copies(copies: int, names: list[str] | None = None) -> list[str]:
    """Make copies 1..`copies` of the training objects `names` (default: all) in
    store.augmented_root(), replacing the copies there (existing up-to-date ones are kept);
    returns the copies' names."""
    from dexdrake.objects.library import get_object, list_objects

    if copies < 1:
        raise DexdrakeError(f"copies must be >= 1, got {copies}")
    infos = list_objects("train") if names is None else [get_object(n) for n in names]
    not_train = [i.name for i in infos if i.split != "train"]
    if not_train:
        raise DexdrakeError(f"only training objects are copied; {not_train} are not")
    root = store.augmented_root()
    wanted = {copy_name(i.name, k): (i, k) for i in infos for k in range(1, copies + 1)}
    for folder in (p for p in root.iterdir() if p.is_dir()) if root.is_dir() else []:
        if folder.name not in wanted:
            shutil.rmtree(folder)
    for name, (info, k) in wanted.items():
        folder, scales = root / name, copy_scales(info.name, k)
        meta = {"name": name, "category": info.category, "split": store.AUGMENTED_SPLIT, "derived_from": info.name,
                "derived_from_hash": info.content_hash, "scales": [round(float(s), 6) for s in scales],
                "convex": {"scaled_from": info.name}}
        if (folder / store.META_FILE).is_file():
            old = store.read_meta(folder)
            if all(old.get(key) == meta[key] for key in ("derived_from_hash", "scales")):
                continue  # the same original at the same scales
        pieces = [_scaled(load_obj(p), scales) for p in info.convex_pieces()]
        store.write_object_dir(folder, _scaled(load_obj(info.mesh_path), scales), meta, pieces=lambda _: pieces)
    return sorted(wanted)
