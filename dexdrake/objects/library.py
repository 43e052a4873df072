"""The object library: shipped objects (splits train, unseen, validation, near; see
dexdrake.objects.shapes) plus user-imported meshes and the augmented training objects.

Every object has a watertight, outward-wound mesh in its OBJECT FRAME (origin = centre of
mass, z up, identity = a stable resting pose), convex pieces for contact and a Drake SDF.
Friction 1 follows the DexRepNet experiment settings; the mass is the scene's (objects/mass.py:
the paper's 0.5 kg, or the hand description's `object_mass` model).

Contact vs distance: the SDF's collision elements are the convex pieces, small support
spheres in their corners (objects/support.py: a resting face gets several contact points),
plus ONE extra element named DISTANCE_GEOMETRY_NAME holding the true (non-convex) mesh for
SceneGraph signed-distance queries. Drake would use that mesh's convex hull for point
contact, so every scene must call `exclude_distance_geometry_from_contact(scene_graph)` once
all models are added (before creating contexts).
"""

from __future__ import annotations

import shutil
import warnings
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from dexdrake.errors import DexdrakeError, DexdrakeWarning, UnknownNameError
from dexdrake.objects import importer, store
from dexdrake.objects.convex import cached_pieces, piece_files, pieces_key
from dexdrake.objects.mass import ObjectMass
from dexdrake.objects.meshfile import file_hash, inertia_about_com, load_obj
from dexdrake.objects.sdf import DISTANCE_GEOMETRY_NAME, object_sdf
from dexdrake.objects.support import SPHERE_RADIUS, support_centres

SPLITS = ("train", "unseen", "validation", "near", "user", store.AUGMENTED_SPLIT)
HELD_OUT_SPLITS = ("unseen", "validation", "near")  # never trained on

__all__ = [
    "DISTANCE_GEOMETRY_NAME",
    "ObjectInfo",
    "add_object",
    "exclude_distance_geometry_from_contact",
    "get_object",
    "import_mesh",
    "list_objects",
    "remove_user_object",
]


@dataclass(frozen=True)
class ObjectInfo:
    """One library object. `mesh_path` is watertight and outward-wound, in the object frame."""

    name: str
    category: str
    split: str  # one of SPLITS
    mesh_path: Path
    extents: tuple[float, float, float]  # AABB size in the object frame (m)
    rest_height: float  # z of the origin when resting on the plane z = 0
    friction: float = 1.0
    content_hash: str = ""  # sha256 of mesh.obj: key for per-object caches
    derived_from: str = ""  # the training object an augmented object is grasped as (a copy: the one it scales)

    def convex_pieces(self) -> list[Path]:
        """OBJ files of convex pieces for contact (shipped ones, else CoACD cached on disk)."""
        meta = store.read_meta(self.mesh_path.parent)
        shipped = self.mesh_path.parent / store.CONVEX_DIR
        if meta.get("convex", {}).get("key") == pieces_key(self.content_hash):
            files = piece_files(shipped)
            if len(files) == meta["convex"]["pieces"]:
                return files
        return cached_pieces(self.mesh_path, self.content_hash)

    def footprint_widths(self) -> np.ndarray:
        """Widths (m) of the horizontal footprint, resting pose, across 90 directions in [0, pi)."""
        return _footprint_widths(self.mesh_path, self.content_hash)

    def mass(self, model: ObjectMass = ObjectMass()) -> float:
        """The object's mass (kg) under `model` (default: the paper's 0.5 kg)."""
        return model.of(_volume(self.mesh_path, self.content_hash))

    def sdf_text(self, model_name: str | None = None, masses: ObjectMass = ObjectMass()) -> str:
        """The SDF text, with the model (and link) named `model_name` (default: the object name)
        and the mass `masses` gives it."""
        mass = self.mass(masses)
        inertia = inertia_about_com(load_obj(self.mesh_path), mass)
        pieces = self.convex_pieces()
        supports = np.concatenate([support_centres(p) for p in pieces])
        return object_sdf(model_name or self.name, self.mesh_path, pieces, mass, inertia, self.friction,
                          supports, SPHERE_RADIUS)


@cache
def _volume(mesh_path: Path, content_hash: str) -> float:
    return float(load_obj(mesh_path).volume)


@cache
def _footprint_widths(mesh_path: Path, content_hash: str) -> np.ndarray:
    xy = np.asarray(load_obj(mesh_path).vertices)[:, :2]
    angles = np.linspace(0.0, np.pi, 90, endpoint=False)
    along = xy @ np.stack([np.cos(angles), np.sin(angles)])
    return along.max(0) - along.min(0)


def _info(folder: Path) -> ObjectInfo:
    meta = store.read_meta(folder)
    mesh_path = (folder / store.MESH_FILE).resolve()
    return ObjectInfo(
        name=meta["name"],
        category=meta["category"],
        split=meta["split"],
        mesh_path=mesh_path,
        extents=tuple(meta["extents"]),
        rest_height=meta["rest_height"],
        content_hash=file_hash(mesh_path),
        derived_from=meta.get("derived_from", ""),
    )


class BrokenObjectWarning(DexdrakeWarning):
    """A user object folder that cannot be read; it is skipped."""


def _folders(split: str) -> list[Path]:
    root = {"user": store.user_root(), store.AUGMENTED_SPLIT: store.augmented_root()}.get(split, store.shipped_root())
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if not p.name.startswith(".") and p.is_dir())


def _user_info(folder: Path) -> ObjectInfo | None:
    """The user object in `folder`, or None (with a BrokenObjectWarning) if it is broken."""
    try:
        info = _info(folder)
        if info.split != "user" or info.name != folder.name:
            raise ValueError(f"meta.json names {info.split} object {info.name!r}")
        return info
    except (OSError, ValueError, KeyError, TypeError) as e:
        warnings.warn(f"skipping the broken user object {folder.name!r} ({folder}: "
                      f"{type(e).__name__}: {e}); remove it with `dexdrake objects remove "
                      f"{folder.name}`", BrokenObjectWarning, stacklevel=3)
        return None


def list_objects(split: str | None = None) -> list[ObjectInfo]:
    """All objects, or those of one split (SPLITS), sorted by name.
    Broken user objects are skipped with a BrokenObjectWarning."""
    if split is not None and split not in SPLITS:
        raise UnknownNameError("object split", split, SPLITS)
    infos = [_info(f) for f in _folders("train") if (f / store.META_FILE).is_file()]
    infos += [i for i in map(_user_info, _folders("user")) if i is not None]
    infos += [_info(f) for f in _folders(store.AUGMENTED_SPLIT) if (f / store.META_FILE).is_file()]
    return sorted((i for i in infos if split is None or i.split == split), key=lambda i: (SPLITS.index(i.split), i.name))


SPLIT_ALIASES = {"seen": "train", "train": "train", "unseen": "unseen", "validation": "validation", "near": "near"}
EMPTY_SPLIT_HINT = {store.AUGMENTED_SPLIT: "; make them with `dexdrake objects augment`"}


def resolve_objects(spec: str) -> tuple[str, list[str]]:
    """(label, object names) for 'seen' / 'train', 'unseen', 'validation', 'near',
    'train+augmented' (the training objects, their scaled copies and the procedural shapes)
    or a comma-separated name list.

    Names are checked against the object library (UnknownNameError lists the valid ones).
    """
    spec = spec.strip()
    if not spec:
        raise DexdrakeError("empty object selection; use 'seen', 'unseen', 'validation', 'near' or comma-separated names")
    if spec in SPLIT_ALIASES or spec == f"train+{store.AUGMENTED_SPLIT}":
        names = []
        for split in [SPLIT_ALIASES[spec]] if spec in SPLIT_ALIASES else ["train", store.AUGMENTED_SPLIT]:
            found = [o.name for o in list_objects(split)]
            if not found:
                raise DexdrakeError(f"the object library has no {split!r} objects{EMPTY_SPLIT_HINT.get(split, '')}")
            names += found
        split = SPLIT_ALIASES.get(spec, "")
        return ("seen" if split == "train" else split if split else "selected"), names
    names = [n.strip() for n in spec.split(",") if n.strip()]
    if len(set(names)) != len(names):
        raise DexdrakeError(f"object list {spec!r} repeats a name")
    for n in names:
        get_object(n)
    return "selected", names


def training_objects(spec: str) -> list[str]:
    """The objects `spec` names for training; the evaluation splits and held-out objects are refused."""
    if spec in ("seen", *HELD_OUT_SPLITS):
        raise DexdrakeError(f"train on 'train' objects or named ones; 'seen', {', '.join(map(repr, HELD_OUT_SPLITS))} "
                            "are evaluation splits")
    _, objects = resolve_objects(spec)
    held_out = [n for n in objects if get_object(n).split in HELD_OUT_SPLITS]
    if held_out:
        raise DexdrakeError(f"{held_out} are held-out objects, kept for evaluation; train on training or user objects")
    return objects


def get_object(name: str) -> ObjectInfo:
    """The object called `name`; UnknownNameError lists the valid names."""
    if importer.NAME_PATTERN.match(name):
        if (store.shipped_root() / name / store.META_FILE).is_file():
            return _info(store.shipped_root() / name)
        if (store.user_root() / name).is_dir():
            info = _user_info(store.user_root() / name)
            if info is not None:
                return info
        if (store.augmented_root() / name / store.META_FILE).is_file():
            return _info(store.augmented_root() / name)
    raise UnknownNameError("object", name, [i.name for i in list_objects() if i.split != store.AUGMENTED_SPLIT])


def import_mesh(path: str | Path, name: str, category: str = "user", scale: float = 1.0, overwrite: bool = False,
                up_axis: str | None = None) -> ObjectInfo:
    """Import a mesh file (OBJ/STL/PLY/GLB) as user object `name` under data_dir()/objects/.

    The mesh is scaled by `scale` (to metres), turned so `up_axis` (default: y for glTF,
    whose convention is y up, else z) points up, repaired, validated and re-centred at its
    centre of mass; what was repaired is in the meta's "import" report (`repairs`).
    Refusals raise an `importer.MeshImportError` subclass (a DexdrakeError) that says why,
    and leave the disk unchanged.
    """
    importer.check_name(name)
    if (store.shipped_root() / name).is_dir():
        raise importer.MeshImportError(f"{name!r} is a shipped object; choose another name")
    folder = store.user_root() / name
    with store.writing(store.user_root(), "the user objects"):
        if folder.exists() and not overwrite:
            raise importer.MeshImportError(f"user object {name!r} already exists ({folder}); pass --overwrite to replace it")
        mesh, report = importer.prepare_mesh(Path(path), scale, up_axis)
        meta = {"name": name, "category": category, "split": "user", "import": report}
        store.write_object_dir(folder, mesh, meta, pieces=None)
    return _info(folder)


def remove_user_object(name: str) -> None:
    """Delete an imported object (shipped objects cannot be removed)."""
    folder = store.user_root() / name
    if not importer.NAME_PATTERN.match(name) or not folder.is_dir():
        raise UnknownNameError("user object", name, [p.name for p in _folders("user")])
    with store.writing(store.user_root(), "the user objects"):
        shutil.rmtree(folder)


def add_object(plant, info: ObjectInfo, name: str | None = None, masses: ObjectMass = ObjectMass()):
    """Parse the object's SDF into `plant` as a free body weighing what `masses` says; returns
    its ModelInstanceIndex.

    `name` overrides the model (and body) name, to add the same object twice. Remember to
    call `exclude_distance_geometry_from_contact(scene_graph)` once the scene is complete.
    """
    from pydrake.multibody.parsing import Parser

    model_name = name or info.name
    if plant.HasModelInstanceNamed(model_name):
        raise DexdrakeError(f"the plant already has a model named {model_name!r}; pass another name")
    (instance,) = Parser(plant).AddModelsFromString(info.sdf_text(model_name, masses), "sdf")
    return instance


def exclude_distance_geometry_from_contact(scene_graph) -> int:
    """Filter every DISTANCE_GEOMETRY_NAME geometry out of contact with all geometries.

    Call after every model is registered (hands, table, objects) and before contexts are
    made. Returns the number of distance geometries filtered.
    """
    from pydrake.geometry import CollisionFilterDeclaration, GeometrySet, Role

    inspector = scene_graph.model_inspector()
    all_ids = inspector.GetAllGeometryIds(Role.kProximity)
    suffix = f"::{DISTANCE_GEOMETRY_NAME}"
    dist = [g for g in all_ids if inspector.GetName(g) == DISTANCE_GEOMETRY_NAME or inspector.GetName(g).endswith(suffix)]
    if dist:
        scene_graph.collision_filter_manager().Apply(
            CollisionFilterDeclaration().ExcludeBetween(GeometrySet(dist), GeometrySet(all_ids))
        )
    return len(dist)
