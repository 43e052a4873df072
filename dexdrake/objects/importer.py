"""Validate, repair and normalise a user mesh file before it joins the object library."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import trimesh

from dexdrake.errors import DexdrakeError
from dexdrake.objects.meshfile import is_stable_rest

SUPPORTED_SUFFIXES = (".obj", ".stl", ".ply", ".glb", ".gltf")
MIN_EXTENT, MAX_EXTENT = 0.01, 1.0  # metres, largest AABB side
MAX_FACES = 20_000  # above this the mesh is simplified to SIMPLIFY_TARGET
SIMPLIFY_TARGET = 10_000
MAX_INPUT_FACES = 2_000_000  # refused outright
MIN_VOLUME = 1e-9  # m^3 (1 mm^3)
NAME_PATTERN = re.compile(r"^[a-z0-9][a-z0-9_\-]{0,63}$")


class MeshImportError(DexdrakeError):
    """A mesh file was refused; the message says why and what to do."""


class MeshFileError(MeshImportError):
    """The file cannot be read as a triangle mesh."""


class OpenMeshError(MeshImportError):
    """The surface is not closed after repair."""


class DegenerateMeshError(MeshImportError):
    """No area or no enclosed volume."""


class ImplausibleScaleError(MeshImportError):
    """Largest extent outside 1 cm - 1 m (usually a units mistake)."""


class TooManyFacesError(MeshImportError):
    """Too many faces, and simplification could not fix it."""


class DisjointBodiesError(MeshImportError):
    """More than one connected body."""


def check_name(name: str) -> None:
    """Object names are lower-case identifiers usable as folder and Drake model names."""
    if not NAME_PATTERN.match(name):
        raise MeshImportError(
            f"invalid object name {name!r}: use 1-64 characters a-z, 0-9, '_' or '-', starting with a letter or digit"
        )


def load_mesh(path: Path) -> trimesh.Trimesh:
    """Read OBJ/STL/PLY/GLB/GLTF as one triangle mesh (scenes are concatenated)."""
    path = Path(path)
    if not path.is_file():
        raise MeshFileError(f"no such file: {path}")
    if path.suffix.lower() not in SUPPORTED_SUFFIXES:
        raise MeshFileError(f"unsupported mesh format {path.suffix!r} ({path}); use one of {', '.join(SUPPORTED_SUFFIXES)}")
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise MeshFileError(f"cannot read {path} as a mesh: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MeshFileError(f"{path} holds no triangles")
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshFileError(f"{path} has non-finite vertex coordinates")
    return trimesh.Trimesh(np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces), process=False)


def _check_scale(mesh: trimesh.Trimesh) -> None:
    largest = float(np.max(mesh.extents))
    if MIN_EXTENT <= largest <= MAX_EXTENT:
        return
    hints = [
        f"scale={s:g} (file in {unit})"
        for s, unit in ((0.001, "millimetres"), (0.01, "centimetres"), (0.0254, "inches"))
        if MIN_EXTENT <= largest * s <= MAX_EXTENT
    ]
    hint = "; try " + " or ".join(hints) if hints else "; check the file's units and pass a scale"
    raise ImplausibleScaleError(
        f"implausible size: largest extent {largest:.4g} m is outside {MIN_EXTENT * 100:g} cm - "
        f"{MAX_EXTENT:g} m (dexdrake works in metres){hint}"
    )


def repair(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Merge vertices, drop degenerate/duplicate faces, fill small holes, fix winding and normals."""
    mesh = mesh.copy()
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        return mesh
    if not mesh.is_watertight:
        trimesh.repair.fill_holes(mesh)
    with np.errstate(divide="ignore", invalid="ignore"):  # zero-volume meshes are refused later
        trimesh.repair.fix_normals(mesh)  # consistent winding, outward (positive volume)
    return mesh


def _simplify(mesh: trimesh.Trimesh, target: int) -> trimesh.Trimesh:
    import open3d as o3d

    o3 = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices), o3d.utility.Vector3iVector(mesh.faces))
    small = o3.simplify_quadric_decimation(target_number_of_triangles=target)
    return trimesh.Trimesh(np.asarray(small.vertices), np.asarray(small.triangles), process=False)


def _check_solid(mesh: trimesh.Trimesh) -> None:
    if len(mesh.faces) == 0:
        raise DegenerateMeshError("degenerate mesh: every face has zero area")
    bodies = mesh.split(only_watertight=False)
    if len(bodies) > 1:
        raise DisjointBodiesError(
            f"the mesh has {len(bodies)} disjoint bodies; an object must be one connected solid "
            "(join or delete the extra parts)"
        )
    if not mesh.is_watertight:
        open_edges = int(np.sum(np.bincount(mesh.edges_unique_inverse) == 1))
        raise OpenMeshError(
            f"open surface: {open_edges} boundary edges remain after repair (holes too large to "
            "fill); close the mesh (e.g. make it watertight/solid) and try again"
        )
    if not mesh.is_winding_consistent:
        raise OpenMeshError("non-manifold surface: face winding cannot be made consistent")
    if mesh.volume < MIN_VOLUME:
        raise DegenerateMeshError(
            f"degenerate mesh: it encloses (almost) no volume ({mesh.volume:.3g} m^3 < {MIN_VOLUME:g}); "
            "is it flat or a single-sided sheet?"
        )


def prepare_mesh(path: Path, scale: float = 1.0) -> tuple[trimesh.Trimesh, dict]:
    """Load, scale, repair and validate a mesh; return it in the object frame and a report.

    Object frame: origin at the centre of mass; the file's z-up orientation is kept if it
    is a stable resting pose, else the most probable stable pose is used instead.
    Raises a MeshImportError subclass saying why a mesh is refused.
    """
    if not np.isfinite(scale) or scale <= 0:
        raise MeshImportError(f"scale must be a positive number, got {scale}")
    mesh = load_mesh(path)
    if len(mesh.faces) > MAX_INPUT_FACES:
        raise TooManyFacesError(f"too many faces ({len(mesh.faces)} > {MAX_INPUT_FACES}); simplify the mesh first")
    mesh.apply_scale(scale)
    _check_scale(mesh)
    mesh = repair(mesh)
    report: dict = {"source": str(Path(path).resolve()), "scale": scale, "faces": int(len(mesh.faces))}
    if len(mesh.faces) > MAX_FACES:
        mesh = repair(_simplify(mesh, SIMPLIFY_TARGET))
        report["simplified_to"] = int(len(mesh.faces))
        if not mesh.is_watertight or len(mesh.faces) > MAX_FACES:
            raise TooManyFacesError(
                f"too many faces ({report['faces']} > {MAX_FACES}) and simplifying to "
                f"{SIMPLIFY_TARGET} did not keep the surface closed; simplify the mesh before importing"
            )
    _check_solid(mesh)
    mesh.apply_translation(-mesh.center_mass)
    report["reoriented"] = not is_stable_rest(mesh)
    if report["reoriented"]:
        transforms, probs = trimesh.poses.compute_stable_poses(mesh, n_samples=1)
        mesh.apply_transform(transforms[int(np.argmax(probs))])
        mesh.apply_translation(-mesh.center_mass)
    return mesh, report
