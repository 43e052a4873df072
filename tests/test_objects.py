"""Tests of the object library: shipped meshes, convex pieces, SDFs, import and CLI."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from dexdrake.errors import DexdrakeError, UnknownNameError
from dexdrake.cli import objects as commands
from dexdrake.objects import convex, importer, shapes, store
from dexdrake.objects.library import (
    DISTANCE_GEOMETRY_NAME,
    add_object,
    exclude_distance_geometry_from_contact,
    get_object,
    import_mesh,
    list_objects,
    remove_user_object,
)
from dexdrake.objects.meshfile import check_mesh, content_hash, is_stable_rest, load_obj, obj_bytes
from dexdrake.objects.support import SPHERE_RADIUS, support_centres

SHIPPED = shapes.recipe_names()  # test_counts_and_splits_match_recipes checks this is the shipped set


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    """Every test gets an empty private cache (user objects, SDFs, CoACD pieces)."""
    monkeypatch.setenv("DEXDRAKE_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("DEXDRAKE_DATA", str(tmp_path / "data"))


@pytest.fixture
def no_coacd(monkeypatch):
    """Fail if a test would run CoACD (shipped objects must use their shipped pieces)."""

    def refuse(mesh):
        raise AssertionError("CoACD should not run for shipped objects")

    monkeypatch.setattr(convex, "decompose", refuse)


def _box_mesh(size=(0.05, 0.04, 0.03), offset=(0.3, -0.2, 0.1)) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=size)
    mesh.apply_translation(offset)
    return mesh


def _is_convex(mesh: trimesh.Trimesh) -> bool:
    """Closed and (up to the files' 1 micron rounding) equal to its own convex hull."""
    return mesh.convex_hull.volume <= mesh.volume * (1 + 1e-4)


def _user_entries():
    root = store.user_root()
    return sorted(p.name for p in root.iterdir()) if root.exists() else []


# ------------------------------------------------------------------ shipped set
def test_counts_and_splits_match_recipes():
    splits = {s: list_objects(s) for s in shapes.SPLITS}
    assert len(splits["train"]) >= 40 and len(splits["unseen"]) >= 8 and len(splits["validation"]) >= 4
    assert len(splits["near"]) == 13  # the earlier unseen set, kept to reproduce its tables
    every = [i for infos in splits.values() for i in infos]
    assert sorted(i.name for i in every) == shapes.recipe_names()
    for split, infos in splits.items():
        assert {i.name for i in infos} == set(shapes.recipe_names(split))
    assert all(i.mass() == 0.5 and i.friction == 1.0 for i in every)


def test_an_object_weighs_its_volume_at_the_density_within_the_bounds_or_the_papers_half_kilo():
    from dexdrake.hands.description import load_hand
    from dexdrake.objects.mass import PAPER_MASS, ObjectMass

    model = load_hand("allegro_z1").object_mass
    assert model == ObjectMass(density=500.0, min_kg=0.05, max_kg=0.5)
    assert load_hand("adroit").object_mass == ObjectMass()
    for name in ("bottle_water", "knife_small", "teapot", "sphere_medium"):
        info = get_object(name)
        volume = load_obj(info.mesh_path).volume
        assert info.mass(model) == pytest.approx(min(max(500.0 * volume, 0.05), 0.5))
        assert info.mass() == PAPER_MASS
    assert get_object("knife_small").mass(model) == 0.05 and get_object("teapot").mass(model) == 0.5
    assert 0.05 < get_object("bottle_water").mass(model) < 0.5
    for bad in ({"density": 0.0}, {"min_kg": 0.6}, {"min_kg": -1.0}):
        with pytest.raises(DexdrakeError, match="object_mass"):
            ObjectMass(**bad)
    from dexdrake.hands.description import _object_mass

    for bad in ({"density": "heavy"}, {"weight": 1.0}, [500]):
        with pytest.raises(DexdrakeError, match="hand 'h': object_mass takes the numbers"):
            _object_mass({"name": "h", "object_mass": bad})


def test_unseen_and_validation_objects_share_no_builder_or_category_with_training_or_each_other():
    recipes = {s: [shapes.get_recipe(n) for n in shapes.recipe_names(s)] for s in shapes.SPLITS}
    builders = {s: {r.builder for r in rs} for s, rs in recipes.items()}
    categories = {s: {r.category for r in rs} for s, rs in recipes.items()}
    trained = categories["train"] | {"procedural"}  # the augmented split: scaled copies and procedural shapes
    for split in ("unseen", "validation"):
        assert not builders[split] & (builders["train"] | builders["near"]), split
        assert not categories[split] & (trained | categories["near"]), split
    assert not builders["unseen"] & builders["validation"] and not categories["unseen"] & categories["validation"]


SHIPPED_AUGMENT = (4, 100)  # the augmented split the shipped Adroit policy trained on: --copies 4 --shapes 100


@pytest.mark.slow
def test_each_unseen_object_is_farther_from_all_training_and_augmented_objects_than_the_median_training_neighbour():
    from dexdrake.objects import similarity

    manifest = json.loads((Path(__file__).resolve().parents[1] / "models/weights/adroit_dexrep_policy.json").read_text())
    copies, n_shapes = SHIPPED_AUGMENT
    assert f"dexdrake objects augment --copies {copies} --shapes {n_shapes}" in [c["command"] for c in manifest["commands"]]
    refs = similarity.reference_meshes(copies, n_shapes)
    points = {n: similarity.surface_points(m) for n, m in refs.items()}
    train = shapes.recipe_names("train")
    nn = [similarity.nearest(points[n], [points[m] for m in train if m != n])[1] for n in train]
    threshold = float(np.median(nn))
    assert 0.004 < threshold < 0.012  # millimetres apart, as measured (`dexdrake objects novelty`)
    names = list(points)
    for name in shapes.recipe_names("unseen"):
        k, d = similarity.nearest(similarity.surface_points(load_obj(get_object(name).mesh_path)), list(points.values()))
        assert d > threshold, f"{name} is {1000 * d:.1f} mm from {names[k]}, within {1000 * threshold:.1f} mm"


def test_objects_novelty_writes_the_table_it_prints_naming_each_held_out_objects_nearest_reference(
        tmp_path, capsys, monkeypatch):
    from dexdrake.cli import main
    from dexdrake.objects import library

    few = {"train": {"sphere_small", "sphere_medium", "box_cube"}, "unseen": {"star"}, "validation": set(),
           "near": set()}  # a small library: the command's work is that of every object
    every = library.list_objects
    monkeypatch.setattr(library, "list_objects", lambda split=None: [o for o in every(split) if o.name in few[split]])
    out = tmp_path / "novelty.md"
    assert main(["objects", "novelty", "--copies", "1", "--shapes", "0", "--out", str(out)]) == 0
    text = out.read_text()
    assert text in capsys.readouterr().out
    assert f"- command: `dexdrake objects novelty --copies 1 --shapes 0 --out {out}`" in text
    assert "- 6 reference objects: 3 training objects, 1 scaled copies of each, 0 procedural shapes" in text
    (row,) = [line for line in text.splitlines() if line.startswith("| star |")]
    _, name, split, category, nearest, distance, beyond, _ = (cell.strip() for cell in row.split("|"))
    assert (split, category) == ("unseen", "star") and nearest in {"sphere_small", "sphere_medium", "box_cube",
                                                                    "sphere_small_s1", "sphere_medium_s1", "box_cube_s1"}
    threshold = float(text.split("nearest training neighbour, ")[1].split(" mm")[0])
    assert beyond == ("yes" if float(distance) > threshold else "no")


def test_chamfer_distance_is_zero_for_a_turned_copy_and_grows_with_scale():
    from dexdrake.objects import similarity

    mesh = shapes.build_mesh("l_block")
    turned = mesh.copy()
    turned.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0, 0, 1)))
    p, q = similarity.surface_points(mesh), similarity.surface_points(turned)
    assert similarity.distance(p, q) < 1e-9  # a turn of 90 degrees is one of the tried yaws
    scaled = [similarity.surface_points(mesh.copy().apply_scale(f)) for f in (1.1, 1.3)]
    assert 0 < similarity.distance(p, scaled[0]) < similarity.distance(p, scaled[1])
    assert similarity.nearest(p, [scaled[1], q, scaled[0]]) == (1, similarity.distance(p, q))


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_mesh_is_a_valid_object_frame_solid(name):
    info = get_object(name)
    mesh = load_obj(info.mesh_path)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0, "inward-wound mesh"
    assert 0.05 <= max(mesh.extents) <= 0.25
    assert len(mesh.faces) <= 3000
    np.testing.assert_allclose(mesh.center_mass, 0.0, atol=1e-5)
    assert info.rest_height == pytest.approx(-mesh.bounds[0][2], abs=1e-6)
    np.testing.assert_allclose(info.extents, mesh.extents, atol=1e-6)
    assert is_stable_rest(mesh), "identity must be a stable resting pose"
    meta = store.read_meta(info.mesh_path.parent)
    assert meta["content_hash"] == info.content_hash == content_hash(info.mesh_path.read_bytes())
    assert meta["recipe"]["builder"] == shapes.get_recipe(name).builder.__name__


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_convex_pieces_are_convex_and_cover_the_mesh(name, no_coacd):
    info = get_object(name)
    pieces = info.convex_pieces()
    assert pieces and all(p.parent == info.mesh_path.parent / "convex" for p in pieces)
    mesh = load_obj(info.mesh_path)
    lo, hi = mesh.bounds
    total = 0.0
    for path in pieces:
        piece = load_obj(path)
        assert piece.is_watertight and piece.volume > 0 and _is_convex(piece)
        assert np.all(piece.bounds[0] >= lo - 0.005) and np.all(piece.bounds[1] <= hi + 0.005)
        total += piece.volume
    assert total >= 0.9 * mesh.volume
    if mesh.volume >= convex.CONVEX_RATIO * mesh.convex_hull.volume:
        assert len(pieces) == 1


def test_shipped_sdfs_parse_with_mass_inertia_and_geometry(no_coacd):
    from pydrake.geometry import Role
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.systems.framework import DiagramBuilder

    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, 0.002)
    infos = [i for i in list_objects() if i.split != "user"]
    instances = {i.name: add_object(plant, i) for i in infos}
    plant.Finalize()
    inspector = scene_graph.model_inspector()
    for info in infos:
        body = plant.GetBodyByName(info.name, instances[info.name])
        assert body.default_mass() == pytest.approx(0.5)
        inertia = body.default_spatial_inertia().CalcRotationalInertia().CopyToFullMatrix3()
        assert np.all(np.linalg.eigvalsh(inertia) > 0)
        ids = plant.GetCollisionGeometriesForBody(body)
        names = [inspector.GetName(g) for g in ids]
        supports = sum(len(support_centres(p)) for p in info.convex_pieces())
        assert supports >= 4 and sum("::support_" in n for n in names) == supports
        assert len(ids) == len(info.convex_pieces()) + supports + 1
        assert sum(n.endswith(DISTANCE_GEOMETRY_NAME) for n in names) == 1
        props = inspector.GetProperties(ids[0], Role.kProximity)
        friction = props.GetProperty("material", "coulomb_friction")
        assert friction.static_friction() == 1.0 and friction.dynamic_friction() == 1.0
    assert info.sdf_text().count("drake:declare_convex") == len(info.convex_pieces())


def test_support_spheres_sit_in_a_box_pieces_corners_and_none_fits_a_sliver(tmp_path):
    box, sliver = tmp_path / "box.obj", tmp_path / "sliver.obj"
    box.write_text(trimesh.creation.box((0.08, 0.06, 0.01)).export(file_type="obj"))
    sliver.write_text(trimesh.creation.box((0.08, 0.06, SPHERE_RADIUS)).export(file_type="obj"))
    centres = support_centres(box)
    corners = np.array([[x, y, z] for x in (-0.04, 0.04) for y in (-0.03, 0.03) for z in (-0.005, 0.005)])
    inset = corners - SPHERE_RADIUS * np.sign(corners)
    assert len(centres) == 8
    np.testing.assert_allclose(np.sort(centres, axis=0), np.sort(inset, axis=0), atol=1e-9)
    assert centres[0][2] < 0  # sampling starts at the lowest vertex
    assert support_centres(sliver).shape == (0, 3)


def _scene(names):
    from pydrake.geometry import Box
    from pydrake.math import RigidTransform
    from pydrake.multibody.plant import AddMultibodyPlant, CoulombFriction, MultibodyPlantConfig
    from pydrake.systems.framework import DiagramBuilder

    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(
        MultibodyPlantConfig(time_step=0.002, discrete_contact_approximation="sap"), builder
    )
    for k, name in enumerate(names):
        add_object(plant, get_object(name))
    plant.RegisterCollisionGeometry(
        plant.world_body(), RigidTransform([0, 0, -0.05]), Box(2, 2, 0.1), "table", CoulombFriction(1.0, 1.0)
    )
    assert exclude_distance_geometry_from_contact(scene_graph) == len(names)
    plant.Finalize()
    return builder.Build(), plant, scene_graph


@pytest.mark.parametrize("name", ["mug", "sphere_small", "toothbrush", "banana", "phone", "knife_chef", "box_cube"])
def test_object_dropped_on_table_rests_at_rest_height(name, no_coacd):
    from pydrake.math import RigidTransform
    from pydrake.systems.analysis import Simulator

    diagram, plant, _ = _scene([name])
    context = diagram.CreateDefaultContext()
    plant_context = plant.GetMyMutableContextFromRoot(context)
    body = plant.GetBodyByName(name)
    info = get_object(name)
    plant.SetFreeBodyPose(plant_context, body, RigidTransform([0.0, 0.0, info.rest_height + 0.01]))
    Simulator(diagram, context).AdvanceTo(0.6)
    pose = plant.GetFreeBodyPose(plant_context, body)
    assert pose.translation()[2] == pytest.approx(info.rest_height, abs=0.002)
    assert np.linalg.norm(pose.rotation().matrix() - np.eye(3)) < 0.05


def test_distance_geometry_gives_true_distances_and_is_out_of_contact(no_coacd):
    diagram, plant, scene_graph = _scene(["torus_thin", "sphere_medium"])
    context = diagram.CreateDefaultContext()
    query = scene_graph.get_query_output_port().Eval(scene_graph.GetMyContextFromRoot(context))
    inspector = query.inspector()
    # both objects sit at the world origin by default
    by_name = {inspector.GetName(r.id_G): r.distance for r in query.ComputeSignedDistanceToPoint(np.zeros(3), 1.0)}
    assert by_name[f"sphere_medium::{DISTANCE_GEOMETRY_NAME}"] == pytest.approx(-0.045, abs=1e-3)  # faceted sphere
    # the torus hole: true distance from the centre is major - minor, the hull would say < 0
    assert by_name[f"torus_thin::{DISTANCE_GEOMETRY_NAME}"] == pytest.approx(0.06 - 0.015, abs=1e-3)
    ids = {inspector.GetName(g): g for g in inspector.GetAllGeometryIds()}
    dist, piece, table = ids[f"torus_thin::{DISTANCE_GEOMETRY_NAME}"], ids["torus_thin::convex_00"], ids["table"]
    assert inspector.CollisionFiltered(dist, table) and inspector.CollisionFiltered(dist, piece)
    assert not inspector.CollisionFiltered(piece, table)


def test_unknown_name_lists_valid_names():
    with pytest.raises(UnknownNameError) as err:
        get_object("no_such_thing")
    assert "unknown object 'no_such_thing'" in str(err.value) and "mug" in str(err.value)
    with pytest.raises(UnknownNameError):
        get_object("../objects/mug")
    with pytest.raises(UnknownNameError):
        list_objects("testing")


def test_recipes_are_deterministic_and_shipped_meshes_current():
    for name in ("mug", "banana", "elephant", "wine_glass"):
        first, second = obj_bytes(shapes.build_mesh(name)), obj_bytes(shapes.build_mesh(name))
        assert first == second
        assert content_hash(first) == get_object(name).content_hash, f"rerun scripts/build_objects.py ({name})"


# ------------------------------------------------------------------ import
def test_import_accepts_a_good_stl(tmp_path):
    path = tmp_path / "brick.stl"
    _box_mesh().export(path)
    info = import_mesh(path, "brick", category="toy")
    assert (info.split, info.category, info.name) == ("user", "toy", "brick")
    mesh = load_obj(info.mesh_path)
    np.testing.assert_allclose(mesh.center_mass, 0.0, atol=1e-6)
    np.testing.assert_allclose(sorted(info.extents), [0.03, 0.04, 0.05], atol=1e-6)
    assert info.rest_height == pytest.approx(0.015, abs=1e-6)
    assert [i.name for i in list_objects("user")] == ["brick"] and get_object("brick") == info
    assert len(info.convex_pieces()) == 1  # a box is convex: one piece, its hull
    assert info.sdf_text().count("drake:declare_convex") == 1
    with pytest.raises(DexdrakeError, match="already exists"):
        import_mesh(path, "brick")
    assert import_mesh(path, "brick", overwrite=True).content_hash == info.content_hash
    remove_user_object("brick")
    assert list_objects("user") == [] and _user_entries() == []
    with pytest.raises(UnknownNameError):
        remove_user_object("mug")  # shipped objects cannot be removed


def test_import_scales_millimetres_and_repairs_inverted_winding(tmp_path):
    mesh = _box_mesh(size=(60.0, 50.0, 40.0), offset=(0, 0, 0))
    mesh.invert()  # inward-wound input
    path = tmp_path / "mm.ply"
    mesh.export(path)
    info = import_mesh(path, "mm_box", scale=0.001)
    fixed = load_obj(info.mesh_path)
    assert fixed.volume == pytest.approx(0.06 * 0.05 * 0.04, rel=1e-4)


@pytest.mark.parametrize(
    ("mesh_fn", "error", "message"),
    [
        (lambda: trimesh.Trimesh(*_open_tube()), importer.OpenMeshError, "open surface"),
        (lambda: trimesh.Trimesh(*_flat_tetrahedron()), importer.DegenerateMeshError, "degenerate"),
        (lambda: _box_mesh(size=(50.0, 20.0, 10.0)), importer.ImplausibleScaleError, "largest extent 50 m"),
        (lambda: trimesh.util.concatenate([_box_mesh(), _box_mesh(offset=(0.5, 0, 0))]), importer.DisjointBodiesError, "2 disjoint bodies"),
    ],
    ids=["open", "degenerate", "50m", "disjoint"],
)
def test_import_refuses_bad_meshes_and_leaves_no_files(tmp_path, mesh_fn, error, message):
    path = tmp_path / "bad.stl"
    mesh_fn().export(path)
    before = _user_entries()
    with pytest.raises(error, match=message) as err:
        import_mesh(path, "bad")
    assert isinstance(err.value, DexdrakeError)
    assert _user_entries() == before == []
    if error is importer.ImplausibleScaleError:
        assert "millimetres" in str(err.value) and "scale=0.001" in str(err.value)


def _open_tube():
    tube = trimesh.creation.cylinder(radius=0.03, height=0.1, sections=24)
    keep = np.abs(tube.face_normals[:, 2]) < 0.5  # drop both caps: two 24-edge holes
    return tube.vertices, tube.faces[keep]


def _flat_tetrahedron():
    vertices = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0.05, 0.05, 0]], dtype=float)
    return vertices, np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])


def test_import_rejects_bad_names_and_shipped_names(tmp_path):
    path = tmp_path / "b.obj"
    _box_mesh().export(path)
    with pytest.raises(DexdrakeError, match="invalid object name"):
        import_mesh(path, "Bad Name")
    with pytest.raises(DexdrakeError, match="shipped object"):
        import_mesh(path, "mug")
    (tmp_path / "x.fbx").write_text("not a mesh")
    with pytest.raises(DexdrakeError, match="unsupported mesh format"):
        import_mesh(tmp_path / "x.fbx", "x")


def test_import_simplifies_dense_meshes(tmp_path):
    path = tmp_path / "dense.stl"
    trimesh.creation.icosphere(subdivisions=6, radius=0.04).export(path)  # 81920 faces
    info = import_mesh(path, "dense_ball")
    mesh = load_obj(info.mesh_path)
    assert len(mesh.faces) <= importer.MAX_FACES and mesh.is_watertight
    assert json.loads((info.mesh_path.parent / "meta.json").read_text())["import"]["simplified_to"] <= importer.MAX_FACES


def test_import_reorients_an_unstable_pose(tmp_path):
    mesh = _box_mesh(size=(0.1, 0.04, 0.02), offset=(0, 0, 0))
    mesh.apply_transform(trimesh.transformations.rotation_matrix(0.6, [1, 0, 0]))  # tipped
    path = tmp_path / "tipped.obj"
    mesh.export(path)
    info = import_mesh(path, "tipped")
    assert is_stable_rest(load_obj(info.mesh_path))
    assert info.rest_height == pytest.approx(0.01, abs=1e-4)  # lies on its largest face


# ------------------------------------------------------------------ CLI
def _cli(argv):
    parser = argparse.ArgumentParser()
    commands.add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_splits_match_library():
    from dexdrake.objects.library import SPLITS

    assert commands.SPLITS == SPLITS
    assert commands.UP_AXES == importer.UP_AXES


def test_cli_list_and_import(tmp_path, capsys):
    assert _cli(["objects", "list", "--split", "unseen"]) == 0
    out = capsys.readouterr().out
    assert "jack" in out and "camera" not in out and "cup_tall" not in out and f"{len(list_objects('unseen'))} objects" in out
    good, bad = tmp_path / "good.stl", tmp_path / "huge.stl"
    _box_mesh().export(good)
    _box_mesh(size=(50.0, 1.0, 1.0)).export(bad)
    assert _cli(["objects", "import", str(good), "--name", "cli_box"]) == 0
    assert "imported cli_box" in capsys.readouterr().out
    from dexdrake.cli import main

    assert main(["objects", "import", str(bad), "--name", "huge"]) == 2
    assert "dexdrake objects import: error: implausible size" in capsys.readouterr().err
    assert _cli(["objects", "list", "--split", "user"]) == 0
    assert "cli_box" in capsys.readouterr().out


def test_imported_non_convex_mesh_gets_cached_coacd_pieces(tmp_path, monkeypatch):
    path = tmp_path / "ell.obj"
    shapes.to_trimesh(shapes.l_block(0.12, 0.03, 0.03)).export(path)
    info = import_mesh(path, "ell")
    pieces = info.convex_pieces()
    assert len(pieces) >= 2 and all(_is_convex(load_obj(p)) for p in pieces)
    from dexdrake.paths import cache_dir

    assert pieces[0].parent.parent == cache_dir() / "convex"
    assert pieces[0].parent.name == convex.pieces_key(info.content_hash)
    monkeypatch.setattr(convex, "decompose", lambda mesh: pytest.fail("cache miss"))
    assert get_object("ell").convex_pieces() == pieces


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".glb"])
def test_import_reads_other_formats(tmp_path, suffix):
    path = tmp_path / f"box{suffix}"
    _box_mesh().export(path)
    info = import_mesh(path, f"box{suffix[1:]}")
    assert load_obj(info.mesh_path).volume == pytest.approx(0.05 * 0.04 * 0.03, rel=1e-4)


def test_import_fills_a_small_hole(tmp_path):
    mesh = _box_mesh()
    holed = trimesh.Trimesh(mesh.vertices, mesh.faces[1:], process=False)  # one triangle missing
    assert not holed.is_watertight
    path = tmp_path / "holed.stl"
    holed.export(path)
    info = import_mesh(path, "holed")
    repaired = load_obj(info.mesh_path)
    assert repaired.is_watertight and repaired.volume == pytest.approx(0.05 * 0.04 * 0.03, rel=1e-4)


def test_add_object_twice_under_another_name(no_coacd):
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.systems.framework import DiagramBuilder

    plant, _ = AddMultibodyPlantSceneGraph(DiagramBuilder(), 0.002)
    mug = get_object("mug")
    first, second = add_object(plant, mug), add_object(plant, mug, name="mug_2")
    assert plant.GetModelInstanceName(first) == "mug" and plant.GetModelInstanceName(second) == "mug_2"
    with pytest.raises(DexdrakeError, match="already has a model named 'mug'"):
        add_object(plant, mug)


# ------------------------------------------------------------------ scans as users hold them
def test_user_objects_live_in_the_data_folder_not_the_cache(tmp_path, monkeypatch):
    path = tmp_path / "b.stl"
    _box_mesh().export(path)
    info = import_mesh(path, "kept")
    assert info.mesh_path.is_relative_to(tmp_path / "data" / "objects")
    import shutil

    shutil.rmtree(tmp_path / "cache", ignore_errors=True)  # clearing the cache keeps the user's objects
    assert get_object("kept").name == "kept"
    monkeypatch.delenv("DEXDRAKE_DATA")
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    assert store.user_root() == tmp_path / "xdg" / "dexdrake" / "objects"


def _cereal_box_yup() -> trimesh.Trimesh:
    """A 7 x 21 x 16 cm box standing 21 cm tall in a y-up file (as glTF stores it)."""
    return _box_mesh(size=(0.07, 0.21, 0.16), offset=(0, 0.105, 0))


def test_gltf_is_turned_y_up_to_z_up_and_up_axis_overrides(tmp_path):
    glb, stl = tmp_path / "cereal.glb", tmp_path / "cereal.stl"
    _cereal_box_yup().export(glb)
    _cereal_box_yup().export(stl)
    info = import_mesh(glb, "cereal")
    assert info.extents[2] == pytest.approx(0.21, abs=1e-6)  # standing, as scanned
    report = json.loads((info.mesh_path.parent / "meta.json").read_text())["import"]
    assert report["up_axis"] == "y" and "turned y up to z up (glTF convention)" in report["repairs"]
    assert import_mesh(stl, "cereal_stl", up_axis="y").extents[2] == pytest.approx(0.21, abs=1e-6)
    lying = import_mesh(glb, "cereal_z", up_axis="z")  # 21 cm along z no more: on its side
    assert lying.extents[2] < 0.2
    with pytest.raises(DexdrakeError, match="unknown up axis"):
        import_mesh(glb, "bad_axis", up_axis="w")


def test_zero_area_fragments_are_dropped_and_reported(tmp_path):
    body = _box_mesh(offset=(0, 0, 0))
    sliver = trimesh.Trimesh([[0.2, 0, 0], [0.21, 0, 0], [0.22, 0, 0]], [[0, 1, 2]],
                             process=False)  # zero area, three distinct vertices
    sheet = trimesh.Trimesh([[0.3, 0, 0], [0.31, 0, 0], [0.3, 0.01, 0]], [[0, 1, 2]],
                            process=False)  # a lone triangle: encloses no volume
    path = tmp_path / "scan.ply"
    trimesh.util.concatenate([body, sliver, sheet]).export(path)
    info = import_mesh(path, "scan")
    assert sorted(info.extents) == pytest.approx([0.03, 0.04, 0.05], abs=1e-6)
    repairs = json.loads((info.mesh_path.parent / "meta.json").read_text())["import"]["repairs"]
    assert any("fragments" in r or "degenerate" in r for r in repairs), repairs


def test_import_prints_every_repair_and_remove(tmp_path, capsys):
    from dexdrake.cli import main

    mesh = _box_mesh(size=(60.0, 50.0, 40.0))
    holed = trimesh.Trimesh(mesh.vertices, mesh.faces[1:], process=False)
    holed.export(tmp_path / "h.stl")
    assert main(["objects", "import", str(tmp_path / "h.stl"), "--name", "h", "--scale",
                 "0.001"]) == 0
    out = capsys.readouterr().out
    assert "rescaled by 0.001" in out and "filled holes" in out
    assert main(["objects", "import", str(tmp_path / "h.stl"), "--name", "h"]) == 2
    assert "pass --overwrite" in capsys.readouterr().err
    assert main(["objects", "remove", "h"]) == 0 and list_objects("user") == []
    assert main(["objects", "remove", "h"]) == 2
    assert "unknown user object 'h'" in capsys.readouterr().err


def test_broken_user_object_is_skipped_with_a_warning(tmp_path, capsys):
    from dexdrake.cli import main
    from dexdrake.objects.library import BrokenObjectWarning

    path = tmp_path / "b.stl"
    _box_mesh().export(path)
    import_mesh(path, "good")
    broken = store.user_root() / "broken"
    broken.mkdir()
    (broken / "meta.json").write_text("{not json")
    with pytest.warns(BrokenObjectWarning, match="broken"):
        assert [i.name for i in list_objects("user")] == ["good"]
    with pytest.warns(BrokenObjectWarning), pytest.raises(UnknownNameError, match="good"):
        get_object("nothing")
    assert main(["objects", "list", "--split", "user"]) == 0
    captured = capsys.readouterr()
    assert "good" in captured.out and "1 objects" in captured.out
    assert main(["objects", "remove", "broken"]) == 0 and not broken.exists()


# ------------------------------------------------------------------ scaled copies (augmentation)
def test_scaled_copies_scale_mesh_and_pieces_and_are_a_training_split(no_coacd, capsys):
    from dexdrake.cli import main
    from dexdrake.objects import augment
    from dexdrake.objects.library import resolve_objects

    with pytest.raises(DexdrakeError, match="make them with `dexdrake objects augment`"):
        resolve_objects("train+augmented")
    names = augment.build_augmented(2, 0, ["cup_short", "box_bar"])
    assert names == ["box_bar_s1", "box_bar_s2", "cup_short_s1", "cup_short_s2"]
    base, copy = get_object("cup_short"), get_object("cup_short_s2")
    scales = augment.copy_scales("cup_short", 2)
    assert np.all((scales >= 0.8) & (scales <= 1.25)) and not np.allclose(scales, augment.copy_scales("cup_short", 1))
    assert (copy.split, copy.category, copy.derived_from) == ("augmented", "cup", "cup_short")
    np.testing.assert_allclose(copy.extents, np.asarray(base.extents) * scales, atol=2e-6)
    assert copy.rest_height == pytest.approx(base.rest_height * scales[2], abs=2e-6)
    mesh = load_obj(copy.mesh_path)
    assert np.abs(mesh.center_mass).max() < 1e-5 and is_stable_rest(mesh)  # still an object frame
    pieces = copy.convex_pieces()  # the scaled pieces, no CoACD (no_coacd)
    assert len(pieces) == len(base.convex_pieces()) and all(_is_convex(load_obj(p)) for p in pieces)
    assert sum(load_obj(p).volume for p in pieces) == pytest.approx(
        np.prod(scales) * sum(load_obj(p).volume for p in base.convex_pieces()), rel=1e-4)
    label, train = resolve_objects("train+augmented")
    assert label == "selected" and train[-4:] == names and len(train) == len(list_objects("train")) + 4
    with pytest.raises(UnknownNameError) as err:  # copies are not offered as evaluation names
        get_object("no_such_thing")
    assert "cup_short_s1" not in str(err.value)
    with pytest.raises(DexdrakeError, match="only training objects"):
        augment.build_augmented(1, 0, ["mug"])
    kept = get_object("cup_short_s1").mesh_path.stat().st_mtime_ns
    assert augment.build_augmented(1, 0, ["cup_short"]) == ["cup_short_s1"]  # fewer copies: the rest removed
    assert [i.name for i in list_objects("augmented")] == ["cup_short_s1"] and not copy.mesh_path.exists()
    assert get_object("cup_short_s1").mesh_path.stat().st_mtime_ns == kept  # up to date: not rewritten
    meta_path = get_object("cup_short_s1").mesh_path.parent / store.META_FILE
    meta_path.write_text(meta_path.read_text().replace('"scales": [', '"scales": [9, '))  # made at other scales
    augment.build_augmented(1, 0, ["cup_short"])
    assert store.read_meta(meta_path.parent)["scales"] == [round(float(s), 6) for s in augment.copy_scales("cup_short", 1)]
    assert main(["objects", "augment", "--copies", "1"]) == 0
    assert f"{len(list_objects('train'))} scaled copies" in capsys.readouterr().out


def test_procedural_shapes_are_stable_convex_part_solids_grasped_as_their_nearest_training_object(no_coacd, capsys):
    from dexdrake.cli import main
    from dexdrake.objects import augment
    from dexdrake.objects.procedural import procedural_shape

    names = augment.build_augmented(1, 3, ["cup_short"])
    assert names == ["cup_short_s1", "shape_001", "shape_002", "shape_003"]
    train = list_objects("train")
    for name in names[1:]:
        info = get_object(name)
        assert (info.split, info.category) == ("augmented", "procedural")
        assert info.derived_from == augment.nearest_training_object(info.extents, train)
        mesh = load_obj(info.mesh_path)
        check_mesh(mesh, name)  # as written: watertight, no face degenerate at the file's rounding
        assert np.abs(mesh.center_mass).max() < 1e-5 and is_stable_rest(mesh) and max(info.extents) <= 0.2
        pieces = [load_obj(p) for p in info.convex_pieces()]  # its parts, no CoACD (no_coacd)
        assert pieces and all(_is_convex(p) for p in pieces)
        assert sum(p.volume for p in pieces) >= mesh.volume * (1 - 1e-3)  # the parts cover the solid
    mesh, parts = procedural_shape(2)
    again, _ = procedural_shape(2)
    np.testing.assert_array_equal(mesh.vertices, again.vertices)  # a name fixes a shape
    assert not np.allclose(mesh.extents, procedural_shape(3)[0].extents)
    assert {len(procedural_shape(k)[1]) for k in range(1, 21)} == {1, 2, 3}  # single and compound shapes
    assert augment.nearest_training_object(get_object("sphere_medium").extents, train) == "sphere_medium"
    assert augment.build_augmented(1, 1, ["cup_short"]) == ["cup_short_s1", "shape_001"]  # fewer: the rest removed
    assert [i.name for i in list_objects("augmented")] == ["cup_short_s1", "shape_001"]
    assert main(["objects", "augment", "--copies", "1", "--shapes", "2"]) == 0
    assert "2 procedural shapes" in capsys.readouterr().out and len(list_objects("augmented")) == len(train) + 2


def test_augment_command_names_the_command_that_makes_a_runs_augmented_objects():
    from dexdrake.objects.augment import augment_command, build_augmented

    names = ["cup_short", "box_bar"] + build_augmented(3, 2, ["cup_short"])  # cup_short_s1..s3, shape_001..002
    assert augment_command(names) == "dexdrake objects augment --copies 3 --shapes 2"
    assert augment_command(["box_bar", "cup_short_s2", "shape_017"]) == "dexdrake objects augment --copies 2 --shapes 17"
    assert augment_command(["cup_short", "box_bar", "mug_s1"]) is None  # training objects only (mug is unseen)
