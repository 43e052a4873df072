"""The augmented split: scaled copies of the training objects and procedural shapes, to train on.

Copy k of training object NAME is the object NAME_sK: NAME's mesh and convex pieces scaled
by (sx, sy, sz) about its centre of mass, each factor log-uniform in SCALE_RANGE and drawn
from a seed made of (NAME, k), so a copy's name fixes its shape. Scaling is affine: the
pieces stay convex (no CoACD run), the centre of mass stays at the origin and a stable
resting pose stays stable. Copies are split "augmented" (training only, never evaluated) and
keep the category of the object they copy, named in their meta.json as `derived_from` (the
grasp expert uses that object's grasp variant).

Procedural shape k (dexdrake.objects.procedural) is the object shape_K (K three digits),
category "procedural", its parts its contact pieces; its `derived_from` is the training
object nearest to it in footprint and height, whose grasp variant the expert uses.
"""

from __future__ import annotations

import hashlib
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from dexdrake.errors import DexdrakeError
from dexdrake.objects import store
from dexdrake.objects.meshfile import load_obj
from dexdrake.objects.procedural import GENERATOR, procedural_shape

if TYPE_CHECKING:
    from dexdrake.objects.library import ObjectInfo

SCALE_RANGE = (0.8, 1.25)  # per-axis scale factors of a copy
# bounds on a request (an object folder is ~45 kB): 50 copies of every training object,
# and as many shapes as shape_name's three digits name
MAX_COPIES, MAX_SHAPES = 50, 999


def copy_name(name: str, k: int) -> str:
    return f"{name}_s{k}"


def copy_scales(name: str, k: int) -> np.ndarray:
    """The (sx, sy, sz) of copy `k` of object `name`."""
    seed = int.from_bytes(hashlib.sha256(f"{name}:{k}".encode()).digest()[:8], "little")
    lo, hi = np.log(SCALE_RANGE)
    return np.exp(np.random.default_rng(seed).uniform(lo, hi, 3))


def _scaled(mesh: trimesh.Trimesh, scales: np.ndarray) -> trimesh.Trimesh:
    return trimesh.Trimesh(np.asarray(mesh.vertices) * scales, np.asarray(mesh.faces), process=False)


def shape_name(k: int) -> str:
    return f"shape_{k:03d}"


def augment_command(names: Sequence[str]) -> str | None:
    """The `dexdrake objects augment` command that makes the augmented objects among `names`
    (copies and shapes are numbered from 1, so the largest numbers fix it); None if there are none."""
    from dexdrake.objects.library import list_objects

    train = {i.name for i in list_objects("train")}
    copies, shapes = [0], [0]
    for name in names:
        base, _, k = name.rpartition("_s")
        if base in train and k.isdigit() and copy_name(base, int(k)) == name:
            copies.append(int(k))
        k = name.partition("_")[2]
        if k.isdigit() and shape_name(int(k)) == name:
            shapes.append(int(k))
    if max(copies + shapes) == 0:
        return None
    return f"dexdrake objects augment --copies {max(max(copies), 1)} --shapes {max(shapes)}"


def _size_key(extents: Sequence[float]) -> np.ndarray:
    """Log of the footprint's sides (longer first) and the height: what `nearest_training_object` compares."""
    e = np.asarray(extents, dtype=float)
    return np.log(np.r_[np.sort(e[:2])[::-1], e[2]])


def nearest_training_object(extents: Sequence[float], infos: Sequence[ObjectInfo]) -> str:
    """The name of the object in `infos` nearest to `extents` by `_size_key`."""
    return min(infos, key=lambda i: float(np.linalg.norm(_size_key(i.extents) - _size_key(extents)))).name


def build_augmented(copies: int, shapes: int = 0, names: list[str] | None = None) -> list[str]:
    """Make copies 1..`copies` of the training objects `names` (default: all) and procedural
    shapes 1..`shapes` in store.augmented_root(), replacing what is there (existing up-to-date
    objects are kept); returns the objects' names."""
    from dexdrake.objects.library import get_object, list_objects

    if not 1 <= copies <= MAX_COPIES or not 0 <= shapes <= MAX_SHAPES:
        raise DexdrakeError(f"need 1 <= copies <= {MAX_COPIES} and 0 <= shapes <= {MAX_SHAPES}, "
                            f"got {copies} and {shapes}")
    train = list_objects("train")
    infos = train if names is None else [get_object(n) for n in names]
    not_train = [i.name for i in infos if i.split != "train"]
    if not_train:
        raise DexdrakeError(f"only training objects are copied; {not_train} are not")
    root = store.augmented_root()
    with store.writing(root, "the augmented split"):
        return _build(root, infos, train, copies, shapes)


def _build(root: Path, infos: list, train: list, copies: int, shapes: int) -> list[str]:
    wanted = {copy_name(i.name, k): (i, k) for i in infos for k in range(1, copies + 1)}
    wanted_shapes = {shape_name(k): k for k in range(1, shapes + 1)}
    for folder in (p for p in root.iterdir() if p.is_dir()):
        if folder.name not in wanted and folder.name not in wanted_shapes:
            shutil.rmtree(folder)
    for name, (info, k) in wanted.items():
        folder, scales = root / name, copy_scales(info.name, k)
        meta = {"name": name, "category": info.category, "split": store.AUGMENTED_SPLIT, "derived_from": info.name,
                "derived_from_hash": info.content_hash, "scales": [round(float(s), 6) for s in scales],
                "convex": {"scaled_from": info.name}}
        if _up_to_date(folder, meta, ("derived_from_hash", "scales")):
            continue  # the same original at the same scales
        pieces = [_scaled(load_obj(p), scales) for p in info.convex_pieces()]
        store.write_object_dir(folder, _scaled(load_obj(info.mesh_path), scales), meta, pieces=lambda _: pieces)
    for name, k in wanted_shapes.items():
        mesh, parts = procedural_shape(k)
        meta = {"name": name, "category": "procedural", "split": store.AUGMENTED_SPLIT,
                "derived_from": nearest_training_object(mesh.extents, train), "generator": GENERATOR,
                "convex": {"procedural": "parts"}}
        if _up_to_date(root / name, meta, ("generator", "derived_from")):
            continue
        store.write_object_dir(root / name, mesh, meta, pieces=lambda _: parts)
    return sorted(wanted) + sorted(wanted_shapes)


def _up_to_date(folder: Path, meta: dict, keys: tuple[str, ...]) -> bool:
    """`folder` holds an object whose meta.json agrees with `meta` on `keys`."""
    if not (folder / store.META_FILE).is_file():
        return False
    old = store.read_meta(folder)
    return all(old.get(key) == meta[key] for key in keys)
