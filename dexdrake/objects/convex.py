"""Convex decomposition of object meshes (CoACD) for Drake contact, cached by content hash.

Drake's point contact treats every `<drake:declare_convex/>` mesh as its convex hull, so a
non-convex object is represented by several convex pieces. A mesh that is already convex
(volume within 0.5 % of its hull's) is one piece, its hull, without running CoACD.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import trimesh

from dexdrake.objects.meshfile import content_hash, load_obj, obj_bytes
from dexdrake.paths import cache_dir

# Chosen for speed on 2 cores (a few seconds per non-convex object) at a concavity good
# enough for grasp contact. Changing them changes every cache key.
COACD_PARAMS: dict[str, object] = {
    "threshold": 0.07,
    "max_convex_hull": 16,
    "preprocess_mode": "off",  # our meshes are manifold already
    "resolution": 1000,
    "mcts_nodes": 10,
    "mcts_iterations": 60,
    "seed": 0,
}
CONVEX_RATIO = 0.995  # volume / hull volume above which a mesh counts as convex


def pieces_key(mesh_hash: str, params: dict[str, object] | None = None) -> str:
    """Cache key of a decomposition: hash of the mesh content hash and the CoACD params."""
    spec = json.dumps({"mesh": mesh_hash, "coacd": params or COACD_PARAMS}, sort_keys=True)
    return content_hash(spec.encode())[:32]


def decompose(mesh: trimesh.Trimesh) -> list[trimesh.Trimesh]:
    """Convex pieces (each a closed convex hull) covering `mesh`."""
    hull = mesh.convex_hull
    if mesh.volume >= CONVEX_RATIO * hull.volume:
        return [hull]
    import coacd

    coacd.set_log_level("error")
    parts = coacd.run_coacd(coacd.Mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces)), **COACD_PARAMS)
    pieces = []
    for verts, _faces in parts:
        piece = trimesh.Trimesh(np.asarray(verts, dtype=float)).convex_hull
        if piece.volume > 1e-12:
            pieces.append(piece)
    if not pieces:  # CoACD found nothing usable: fall back to the hull
        return [hull]
    return pieces


def write_pieces(pieces: list[trimesh.Trimesh], folder: Path) -> list[Path]:
    """Write pieces as folder/piece_XX.obj, atomically (temp folder then rename).

    `folder` must not hold pieces yet; if a concurrent writer created it first, its pieces win.
    """
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=folder.parent, prefix=f".{folder.name}."))
    try:
        for i, piece in enumerate(pieces):
            (tmp / f"piece_{i:02d}.obj").write_bytes(obj_bytes(piece))
        tmp.rename(folder)
    except OSError:
        shutil.rmtree(tmp, ignore_errors=True)
        if not piece_files(folder):  # not a concurrent writer that finished first
            raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return piece_files(folder)


def piece_files(folder: Path) -> list[Path]:
    """The piece OBJ files in `folder`, in order."""
    return sorted(Path(folder).glob("piece_*.obj"))


def cached_pieces(mesh_path: Path, mesh_hash: str) -> list[Path]:
    """Convex pieces of the mesh at `mesh_path` from cache_dir()/convex/<key>/, made if missing."""
    folder = cache_dir() / "convex" / pieces_key(mesh_hash)
    files = piece_files(folder) if folder.is_dir() else []
    if files:
        return files
    return write_pieces(decompose(load_obj(mesh_path)), folder)
