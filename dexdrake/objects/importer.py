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
UP_AXES = ("x", "y", "z", "-x", "-y", "-z")
GLTF_SUFFIXES = (".glb", ".gltf")  # glTF's convention is y up (glTF 2.0 spec, 3.4)
MIN_FRAGMENT_AREA = 1e-6  # m^2: a connected part smaller than this, or enclosing no volume, is dropped
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
    if path.is_dir():
        raise MeshFileError(f"{path} is a folder; give a mesh file ({', '.join(SUPPORTED_SUFFIXES)})")
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


def up_rotation(axis: str) -> np.ndarray:
    """The 3x3 rotation that turns the file's `axis` (x, y, z, -x, -y, -z) to +z."""
    if axis not in UP_AXES:
        raise MeshImportError(f"unknown up axis {axis!r}; valid: {', '.join(UP_AXES)}")
    angle = {"x": -np.pi / 2, "y": np.pi / 2, "z": 0.0, "-x": np.pi / 2, "-y": -np.pi / 2,
             "-z": np.pi}[axis]
    about = [0, 1, 0] if axis.endswith("x") else [1, 0, 0]
    return trimesh.transformations.rotation_matrix(angle, about)[:3, :3]


def _boundary_edges(mesh: trimesh.Trimesh) -> int:
    return int(np.sum(np.bincount(mesh.edges_unique_inverse) == 1)) if len(mesh.faces) else 0


def repair(mesh: trimesh.Trimesh, notes: list[str] | None = None) -> trimesh.Trimesh:
    """Merge vertices, drop degenerate/duplicate faces, fill small holes, fix winding and
    normals; `notes` (if given) receives one line per repair made."""
    notes = [] if notes is None else notes
    mesh = mesh.copy()
    faces = len(mesh.faces)
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) < faces:
        notes.append(f"removed {faces - len(mesh.faces)} degenerate or duplicate faces")
    if len(mesh.faces) == 0:
        return mesh
    if not mesh.is_watertight:
        open_edges = _boundary_edges(mesh)
        trimesh.repair.fill_holes(mesh)
        if _boundary_edges(mesh) < open_edges:
            notes.append(f"filled holes ({open_edges - _boundary_edges(mesh)} of {open_edges} "
                         "boundary edges closed)")
    with np.errstate(divide="ignore", invalid="ignore"):  # zero-volume meshes are refused later
        trimesh.repair.fix_normals(mesh)  # consistent winding, outward (positive volume)
    return mesh


def drop_fragments(mesh: trimesh.Trimesh, notes: list[str]) -> trimesh.Trimesh:
    """The mesh without connected parts that have (almost) no area or enclose no volume
    (scanner debris); what was dropped goes to `notes`."""
    parts = mesh.split(only_watertight=False)
    if len(parts) < 2:
        return mesh
    with np.errstate(divide="ignore", invalid="ignore"):
        keep = [p for p in parts if p.area >= MIN_FRAGMENT_AREA and abs(p.volume) >= MIN_VOLUME]
    if len(keep) == len(parts) or not keep:
        return mesh
    dropped = [p for p in parts if not any(p is k for k in keep)]
    notes.append(f"dropped {len(dropped)} fragments with no area or volume "
                 f"({sum(len(p.faces) for p in dropped)} faces)")
    return trimesh.util.concatenate(keep)


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


def prepare_mesh(path: Path, scale: float = 1.0, up_axis: str | None = None
                 ) -> tuple[trimesh.Trimesh, dict]:
    """Load, scale, turn up, repair and validate a mesh; return it in the object frame and a
    report whose "repairs" list says every change made (rescaled, turned, holes filled,
    fragments dropped, simplified, reoriented).

    up_axis: the file's up direction (default: y for glTF, whose convention is y up, else z).
    Object frame: origin at the centre of mass; the file's (turned) z-up orientation is kept
    if it is a stable resting pose, else the most probable stable pose is used instead.
    Raises a MeshImportError subclass saying why a mesh is refused.
    """
    if not np.isfinite(scale) or scale <= 0:
        raise MeshImportError(f"scale must be a positive number, got {scale}")
    path = Path(path)
    up = up_axis or ("y" if path.suffix.lower() in GLTF_SUFFIXES else "z")
    rotation = up_rotation(up)
    mesh = load_mesh(path)
    if len(mesh.faces) > MAX_INPUT_FACES:
        raise TooManyFacesError(f"too many faces ({len(mesh.faces)} > {MAX_INPUT_FACES}); simplify the mesh first")
    repairs: list[str] = []
    if scale != 1.0:
        mesh.apply_scale(scale)
        repairs.append(f"rescaled by {scale:g} to metres")
    if up != "z":
        mesh.vertices = mesh.vertices @ rotation.T
        why = " (glTF convention)" if up_axis is None else ""
        repairs.append(f"turned {up} up to z up{why}")
    _check_scale(mesh)
    mesh = drop_fragments(repair(mesh, repairs), repairs)
    report: dict = {"source": str(path.resolve()), "scale": scale, "up_axis": up,
                    "faces": int(len(mesh.faces))}
    if len(mesh.faces) > MAX_FACES:
        mesh = repair(_simplify(mesh, SIMPLIFY_TARGET))
        report["simplified_to"] = int(len(mesh.faces))
        repairs.append(f"simplified {report['faces']} -> {len(mesh.faces)} faces")
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
        repairs.append("reoriented to its most stable resting pose (it would tip over as given)")
    report["repairs"] = repairs
    return mesh, report
