"""On-disk layout of object folders: mesh.obj + meta.json (+ convex/ for shipped objects).

Shipped objects live in `models_dir()/objects/<name>/`, imported ones in the user's data
folder, `data_dir()/objects/<name>/` (not the cache: clearing the cache keeps them), scaled
copies of the training objects (dexdrake.objects.augment) in `data_dir()/augmented/<name>/`. A folder is written completely in a temporary
sibling and renamed into place, so a failed write leaves nothing behind; writers of a split
hold its lock (`writing`), which also clears what a killed writer left.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import trimesh

from dexdrake.objects.convex import COACD_PARAMS, pieces_key, write_pieces
from dexdrake.objects.meshfile import content_hash, load_obj, obj_bytes
from dexdrake.outputs import WriterLock

MESH_FILE, META_FILE, CONVEX_DIR = "mesh.obj", "meta.json", "convex"
AUGMENTED_SPLIT = "augmented"  # the split of the scaled copies (dexdrake.objects.augment)


def shipped_root() -> Path:
    """Folder of the shipped object set."""
    from dexdrake.paths import models_dir

    return models_dir() / "objects"


def user_root() -> Path:
    """Folder of imported (user) objects."""
    from dexdrake.paths import data_dir

    return data_dir() / "objects"


def augmented_root() -> Path:
    """Folder of the scaled copies of the training objects."""
    from dexdrake.paths import data_dir

    return data_dir() / AUGMENTED_SPLIT


@contextmanager
def writing(root: Path, what: str) -> Iterator[None]:
    """Hold the writer lock of `root` (a split's folder; `what` names it for the message a
    second writer gets) and remove the hidden temporary folders a killed writer left there."""
    with WriterLock(root, what):
        for tmp in root.iterdir():
            if tmp.name.startswith(".") and tmp.is_dir():
                shutil.rmtree(tmp, ignore_errors=True)
        yield


def describe(mesh: trimesh.Trimesh) -> dict[str, Any]:
    """Geometric facts recorded in meta.json for a mesh already in the object frame."""
    lo, hi = mesh.bounds
    return {
        "extents": [round(float(x), 6) for x in hi - lo],
        "rest_height": round(float(-lo[2]), 6),
        "volume": float(f"{mesh.volume:.6g}"),
        "faces": int(len(mesh.faces)),
    }


def write_object_dir(folder: Path, mesh: trimesh.Trimesh, meta: dict[str, Any],
                     pieces: Callable[[trimesh.Trimesh], list[trimesh.Trimesh]] | None) -> dict:
    """Write mesh.obj and meta.json (and convex/ pieces, `pieces` of the written mesh, e.g.
    convex.decompose, unless None) into `folder`.

    `meta` holds name, category, split and provenance; geometric facts and the content hash
    are added here from the written (quantised) mesh. Replaces an existing folder.
    Returns the final meta.
    """
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=folder.parent, prefix=f".{folder.name}."))
    try:
        data = obj_bytes(mesh)
        (tmp / MESH_FILE).write_bytes(data)
        written = load_obj(tmp / MESH_FILE)
        mesh_hash = content_hash(data)
        meta = {**meta, **describe(written), "content_hash": mesh_hash}
        if pieces is not None:
            files = write_pieces(pieces(written), tmp / CONVEX_DIR)
            made = meta.get("convex", {"coacd": COACD_PARAMS})  # how the pieces were made
            meta["convex"] = {**made, "key": pieces_key(mesh_hash), "pieces": len(files)}
        (tmp / META_FILE).write_text(json.dumps(meta, indent=1, sort_keys=True) + "\n")
        old = None
        if folder.exists():
            old = folder.with_name(f".{folder.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            folder.rename(old)
        tmp.rename(folder)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return meta


def read_meta(folder: Path) -> dict[str, Any]:
    """meta.json of an object folder."""
    return json.loads((Path(folder) / META_FILE).read_text())
