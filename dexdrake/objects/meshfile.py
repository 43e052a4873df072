"""Deterministic OBJ files, content hashes and mass properties of object meshes."""

from __future__ import annotations

import hashlib
import io
import os
import tempfile
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from dexdrake.errors import DexdrakeError


def obj_bytes(mesh: trimesh.Trimesh) -> bytes:
    """The mesh as OBJ text (vertices in metres, 6 decimals: 1 micron), byte-for-byte stable."""
    out = io.StringIO()
    out.write("# dexdrake object mesh (metres, object frame: origin at the centre of mass)\n")
    np.savetxt(out, np.asarray(mesh.vertices, dtype=float), fmt="v %.6f %.6f %.6f")
    np.savetxt(out, np.asarray(mesh.faces, dtype=np.int64) + 1, fmt="f %d %d %d")
    return out.getvalue().replace("-0.000000", "0.000000").encode()


def content_hash(data: bytes) -> str:
    """sha256 hex digest of file content."""
    return hashlib.sha256(data).hexdigest()


def file_hash(path: Path) -> str:
    """sha256 hex digest of a file's bytes."""
    return content_hash(Path(path).read_bytes())


class BrokenMeshFileError(DexdrakeError, ValueError):
    """An object's stored mesh file that is gone, empty or damaged."""


def load_obj(path: Path) -> trimesh.Trimesh:
    """Load one of our OBJ files exactly as written (no vertex merging or reordering)."""
    fix = "import the object again (`dexdrake objects import FILE --name NAME --overwrite`) or remove it"
    if not Path(path).is_file():
        raise BrokenMeshFileError(f"{path} is gone (was the object removed while in use?); {fix}")
    try:
        mesh = trimesh.load(str(path), file_type="obj", force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for a damaged file
        raise BrokenMeshFileError(f"{path} cannot be read ({type(exc).__name__}: {exc}); {fix}") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise BrokenMeshFileError(f"{path} holds no triangle mesh (empty or damaged); {fix}")
    return mesh


def write_atomic(path: Path, data: bytes) -> None:
    """Write `data` to `path` via a temporary file in the same folder and an atomic rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def inertia_about_com(mesh: trimesh.Trimesh, mass: float) -> np.ndarray:
    """3x3 rotational inertia (kg m^2) of the solid mesh with `mass`, about its centre of mass."""
    if mesh.volume <= 0:
        raise ValueError("inertia needs a closed mesh with positive volume")
    solid = mesh.copy()
    solid.density = mass / mesh.volume
    return np.asarray(solid.moment_inertia, dtype=float)


def is_stable_rest(mesh: trimesh.Trimesh, tol: float = 0.002, margin: float = 0.0) -> bool:
    """True if the centre of mass lies over the support polygon (at least `margin` inside it)
    when resting on z = min z.

    The support polygon is the convex hull (in xy) of the vertices within `tol` of the
    lowest point, so this accepts flat bases as well as round bottoms.
    """
    v = np.asarray(mesh.vertices)
    support = v[v[:, 2] < v[:, 2].min() + tol][:, :2]
    com = np.asarray(mesh.center_mass)[:2]
    if len(support) < 3 or np.linalg.matrix_rank(support - support[0], tol=1e-6) < 2:
        return False
    hull = ConvexHull(support)
    return bool(np.all(hull.equations[:, :2] @ com + hull.equations[:, 2] <= 1e-9 - margin))


def check_mesh(mesh: trimesh.Trimesh, label: str = "mesh") -> None:
    """Raises DexdrakeError unless `mesh` is non-degenerate, watertight and outward-wound."""
    if len(mesh.faces) < 4:
        raise DexdrakeError(f"{label}: has {len(mesh.faces)} faces; a closed surface needs at least 4")
    areas = mesh.area_faces
    tiny = int(np.sum(areas <= 1e-12 * max(areas.max(), 1e-30)))
    if tiny:
        raise DexdrakeError(f"{label}: {tiny} degenerate (zero-area) faces; repair the mesh first")
    if not mesh.is_watertight:
        raise DexdrakeError(f"{label}: not watertight (open boundary or non-manifold edges); "
                            "signed distances would be wrong")
    if not mesh.is_winding_consistent:
        raise DexdrakeError(f"{label}: inconsistent face winding; signed distances would be wrong")
    if mesh.volume <= 0.0:
        raise DexdrakeError(f"{label}: faces wound inward (volume {mesh.volume:.3g} m^3 <= 0); "
                            "flip the faces so normals point outward")
