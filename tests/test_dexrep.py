"""DexRep features: occupancy vs brute force, surface / local-geo, both paths, sizes, CLI."""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle

import numpy as np
import pytest
import torch
import trimesh
from scipy.interpolate import RegularGridInterpolator
from scipy.spatial.transform import Rotation
from rrd_content import logged_rows

from dexdrake.dexrep import features as F
from dexdrake.dexrep.occupancy import FastOccupancy, occupancy_in_frame, occupied_voxels, voxel_centres
from dexdrake.dexrep.geometry import SdfGrid, load_object_geometry
from dexdrake.objects.meshfile import check_mesh
from dexdrake.dexrep.pointnet import PointNetAutoEncoder, PointNetEncoder, chamfer_distance, encode_cloud
from dexdrake.errors import DexdrakeError

R_SPHERE, BOX, TORUS = 0.05, (0.12, 0.06, 0.04), (0.06, 0.02)


def sphere_sd(p):
    return np.linalg.norm(p, axis=-1) - R_SPHERE


def box_sd(p):
    q = np.abs(p) - np.array(BOX) / 2
    return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(axis=-1), 0)


def torus_sd(p):
    ring = np.linalg.norm(p[..., :2], axis=-1) - TORUS[0]
    return np.hypot(ring, p[..., 2]) - TORUS[1]


SHAPES = {
    "sphere": (lambda: trimesh.creation.icosphere(4, R_SPHERE), sphere_sd),
    "box": (lambda: trimesh.creation.box(BOX), box_sd),
    "torus": (lambda: trimesh.creation.torus(*TORUS, major_sections=96, minor_sections=48), torus_sd),
}


@pytest.fixture(scope="module")
def encoder():
    torch.manual_seed(0)
    return PointNetEncoder().eval()


@pytest.fixture(scope="module")
def geometries(encoder, tmp_path_factory):
    # 3 mm SDF grids (production: 2 mm) keep the fixture quick; the rules are the same. Read
    # through the disk cache as the library's objects are: built once, then loaded
    folder = tmp_path_factory.mktemp("meshes")
    out = {}
    for name, (make, _) in SHAPES.items():
        make().export(folder / f"{name}.obj")
        out[name] = load_object_geometry(folder / f"{name}.obj", encoder, grid_spacing=0.003)
    return out


def random_pose(rng, scale=0.05):
    X = np.eye(4)
    X[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
    X[:3, 3] = rng.uniform(-scale, scale, 3)
    return X


def brute_force_occupancy(sd, X_OG, sub=9):
    """Dense sub-sampling of each voxel (sub^3 points incl. faces): min analytic sd per voxel."""
    edge = 0.02
    s = (np.arange(sub) / (sub - 1) - 0.5) * edge
    offs = np.stack(np.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3)
    pts_G = voxel_centres()[:, None, :] + offs
    pts_O = pts_G @ X_OG[:3, :3].T + X_OG[:3, 3]
    return sd(pts_O).min(axis=1)


@pytest.mark.parametrize("shape", ["sphere", "box", "torus"])
def test_occupancy_matches_brute_force(geometries, shape):
    rng = np.random.default_rng(1)
    sd = SHAPES[shape][1]
    for _ in range(3):
        X_WO, X_WG = random_pose(rng), random_pose(rng)
        occ = F.occupancy(X_WG, X_WO, geometries[shape])
        assert occ.shape == (1000,) and set(np.unique(occ)) <= {0.0, 1.0}
        min_sd = brute_force_occupancy(sd, np.linalg.inv(X_WO) @ X_WG)
        ref = min_sd <= 0
        assert ref.sum() > 20  # the object really is in the grid
        wrong = occ.astype(bool) != ref
        # extra voxels: only ones the 2.5 mm sub-sampling can miss itself (<= 2.2 mm)
        assert np.all(min_sd[wrong] < 0.0022), min_sd[wrong]
        # missed voxels: only where the object enters the voxel by less than the grid's
        # interpolation error (the planar rule never misses a convex part)
        assert np.all(min_sd[wrong] > -0.001), min_sd[wrong]
        assert wrong.sum() <= max(3, 0.05 * ref.sum())


def analytic_sd_fn(sd):
    def fn(p, with_gradient):  # no default: the occupancy code always says which it wants
        value = sd(p)
        if not with_gradient:
            return value
        h = 1e-6
        return value, np.stack([(sd(p + h * e) - value) / h for e in np.eye(3)], axis=1)

    return fn


@pytest.mark.parametrize("levels", [1, 2])
def test_fast_occupancy_applies_the_rule_of_occupancy_in_frame(geometries, levels):
    # the fast path (SDF grid, nearest-node pre-classification, batched refinement) equals
    # the plain rule on the exact signed distance up to marginal voxels
    rng = np.random.default_rng(8)
    for _ in range(3):
        X_OG = random_pose(rng, 0.04)
        fast = FastOccupancy(levels=levels)(X_OG, geometries["torus"])
        exact = occupancy_in_frame(analytic_sd_fn(torus_sd), X_OG, levels=levels)
        np.testing.assert_array_equal(F.occupancy(X_OG, np.eye(4), geometries["torus"], levels=levels), fast)
        assert np.sum(fast != exact) <= 2
        assert exact.sum() > 50
    # a grid of another size and resolution
    X_OG = random_pose(rng, 0.02)
    fast = FastOccupancy(0.1, 4, levels)(X_OG, geometries["torus"])
    exact = occupancy_in_frame(analytic_sd_fn(torus_sd), X_OG, 0.1, 4, levels)
    assert fast.shape == (64,) and np.sum(fast != exact) <= 1 and 10 < exact.sum() < 60


def _half_space(normal_F, a: float):
    """sd_fn of the solid n.p <= a (F frame, unit n) that records each call's points and
    whether it asked for gradients."""
    calls = []

    def sd_fn(p, with_gradient):
        calls.append((p.copy(), with_gradient))
        value = p @ normal_F - a
        return (value, np.tile(normal_F, (len(p), 1))) if with_gradient else value

    return sd_fn, calls


def _grid_axis(size: float, resolution: int) -> np.ndarray:
    return np.arange(resolution) * (size / resolution) + size / resolution / 2 - size / 2


def test_fast_occupancy_interpolates_only_the_voxels_the_balls_leave_open(geometries, monkeypatch):
    # nearest-node pass: only voxels whose nearest node's distance lies between the balls
    # give or take that node's error are interpolated (so their true distance lies there give
    # or take twice that error and the mesh's facets), each with its 8 children, in one call
    # per level; the gradient only at the last
    g = geometries["torus"]
    edge, slack, facets = 0.02, 2 * g.sdf.spacing * np.sqrt(3) / 2, 2e-4
    rng = np.random.default_rng(14)
    for levels in (1, 2):
        for _ in range(3):
            queries = _GridQueries(monkeypatch)
            X_OG = random_pose(rng, 0.04)
            FastOccupancy(levels=levels)(X_OG, g)
            (u, sd, with_gradient), *rest = queries.trilinear
            m = len(u) // 9
            assert m > 0 and len(u) == 9 * m and with_gradient == (levels == 1)
            true = torus_sd(u[:m] * g.sdf.spacing + g.sdf.origin)
            assert np.all(true >= edge / 2 - slack - facets) and np.all(true <= edge * np.sqrt(3) / 2 + slack + facets)
            np.testing.assert_allclose(u[m:].reshape(m, 8, 3).mean(axis=1), u[:m], atol=1e-12)
            assert [w for _, _, w in rest] == [True] * (levels - 1)
            if rest:  # the second level: the children of the first level's open children
                open_children = (sd[m:] > edge / 4) & (sd[m:] <= edge / 2 * np.sqrt(3) / 2)
                assert 0 < len(rest[0][0]) <= 8 * open_children.sum()


def _lazy_fast_occupancy(X_OG, geometry, levels, size=0.2, resolution=10):
    """FastOccupancy's nearest-node pass, then the rule by `_refine`, which interpolates only
    the points each step needs (one grid call for the undecided voxels, then per level one
    for the children of the open ones and one with gradients for the last level's open)."""
    from dexdrake.dexrep.occupancy import _SQRT3_2, _refine

    R, t, grid, edge = X_OG[:3, :3], X_OG[:3, 3], geometry.sdf, size / resolution
    M = R.T * (1.0 / grid.spacing)
    U = voxel_centres(size, resolution) @ M + (t - grid.origin) * (1.0 / grid.spacing)
    sd = grid.nearest_node_index_value(U)
    slack = grid.spacing * _SQRT3_2 + 1e-6
    occ = sd <= edge / 2 - slack
    owner = np.flatnonzero(~occ & (sd <= edge * _SQRT3_2 + slack))
    sd = grid.trilinear_index(U[owner])
    occ[owner[sd <= edge / 2]] = True
    keep = (sd > edge / 2) & (sd <= edge * _SQRT3_2)
    _refine(occ, owner[keep], U[owner][keep], grid.trilinear_index, M, R, edge, levels)
    return occ.astype(np.float64)


@pytest.mark.parametrize("levels", [1, 2])
def test_fast_occupancy_equals_the_rule_asking_the_grid_only_what_it_needs(geometries, levels):
    # one grid call per level decides every voxel as the lazy order does, bit for bit
    rng = np.random.default_rng(21)
    occupied = 0
    for name in ("torus", "box", "sphere"):
        for _ in range(6):
            X_OG = random_pose(rng, 0.05)
            fast = FastOccupancy(levels=levels)(X_OG, geometries[name])
            np.testing.assert_array_equal(fast, _lazy_fast_occupancy(X_OG, geometries[name], levels))
            occupied += fast.sum()
    assert occupied > 500


def test_occupancy_of_a_half_space_is_decided_by_the_balls_alone_when_it_can():
    # grid x along F's y; centres 0.45 edge outside the plane are occupied and 1.0 or 1.45
    # edge outside empty in one sd call (the inscribed and circumscribed balls decide them)
    X_FG = np.eye(4)
    X_FG[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    X_FG[:3, 3] = [0.3, 0.0, -0.2]
    for a, size, resolution in ((-0.039, 0.2, 10), (-0.05, 0.2, 10), (0.00125, 0.1, 4)):
        sd_fn, calls = _half_space(np.array([0.0, 1.0, 0.0]), a)
        occ = occupancy_in_frame(sd_fn, X_FG, size, resolution)
        lowest_x = _grid_axis(size, resolution) - size / resolution / 2
        expect = np.repeat(lowest_x <= a, resolution ** 2).astype(float)  # x-major
        np.testing.assert_array_equal(occ, expect)
        assert occ.dtype == np.float64 and [(len(p), g) for p, g in calls] == [(resolution ** 3, False)], a
        centres, half = occupied_voxels(occ, size, resolution)
        np.testing.assert_array_equal(centres, voxel_centres(size, resolution)[expect == 1])
        assert half == size / resolution / 2


@pytest.mark.parametrize("levels", [1, 2])
def test_occupancy_of_a_tilted_half_space_is_exact(levels):
    # a voxel meets the solid n.p <= a iff n.c - a <= (e/2) |n in grid axes|_1: the rule
    # (balls, then the planar test after refining) is exact for a plane, at any pose and grid
    rng = np.random.default_rng(11)
    refined = 0
    for size, resolution in ((0.2, 10), (0.1, 4), (0.2, 10), (0.1, 4)):
        X_FG = random_pose(rng)
        normal = rng.normal(size=3)
        normal /= np.linalg.norm(normal)
        a = rng.uniform(-0.03, 0.03)
        sd_fn, calls = _half_space(normal, a)
        occ = occupancy_in_frame(sd_fn, X_FG, size, resolution, levels)
        axis = _grid_axis(size, resolution)
        c_G = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
        n_G = X_FG[:3, :3].T @ normal
        expect = (c_G @ n_G + X_FG[:3, 3] @ normal - a) <= size / resolution / 2 * np.abs(n_G).sum()
        np.testing.assert_array_equal(occ, expect)
        assert 0 < expect.sum() < len(expect)
        # each level splits only the cubes between its balls; gradients only at the last
        between = []
        for k, (p, with_gradient) in enumerate(calls):
            assert with_gradient == (k == levels + 1) and k <= levels + 1
            e = size / resolution / 2 ** k
            sd = p @ normal - a
            between.append(int(np.sum((sd > e / 2) & (sd <= e * np.sqrt(3) / 2))))
        if len(calls) > 1:
            assert len(calls[1][0]) == 8 * between[0]  # every open voxel, split
        for k in range(1, len(calls) - 1):
            assert len(calls[k + 1][0]) <= (between[k] if k == levels else 8 * between[k])
        refined += len(calls) > 1
    assert refined >= 3  # most grids had voxels between the balls


class _GridQueries:
    """Records the points of every SDF-grid query (and the interpolated values) of FastOccupancy."""

    def __init__(self, monkeypatch):
        self.nearest, self.trilinear = [], []
        nearest, trilinear = SdfGrid.nearest_node_index_value, SdfGrid.trilinear_index

        def nearest_node_index_value(grid, u):
            self.nearest.append(u.copy())
            return nearest(grid, u)

        def trilinear_index(grid, u, with_gradient=False):
            out = trilinear(grid, u, with_gradient)
            self.trilinear.append((u.copy(), out[0] if with_gradient else out, with_gradient))
            return out

        monkeypatch.setattr(SdfGrid, "nearest_node_index_value", nearest_node_index_value)
        monkeypatch.setattr(SdfGrid, "trilinear_index", trilinear_index)


def test_occupancy_cull_keeps_objects_at_the_grid_corner(geometries, monkeypatch):
    g = geometries["sphere"]
    X_WG = np.eye(4)
    corner = np.array([0.1, 0.1, 0.1])
    queries = _GridQueries(monkeypatch)
    for shift, expect_empty in ((corner + 0.049 / np.sqrt(3), False), (corner + 0.051 / np.sqrt(3), True)):
        X_WO = np.eye(4)
        X_WO[:3, 3] = shift  # sphere of radius 5 cm just touching / just missing the corner
        occ = F.occupancy(X_WG, X_WO, g).reshape(10, 10, 10)
        assert (occ.sum() == 0) == expect_empty
        assert (len(queries.nearest) == 0) == expect_empty  # a culled grid asks the SDF nothing
        if not expect_empty:
            assert occ[9, 9, 9] == 1 and occ.sum() == 1
        queries.nearest.clear()
    for shift in ([0.5, 0.0, 0.0], [0.0, 0.0, 0.3]):
        X_WO = np.eye(4)
        X_WO[:3, 3] = shift
        assert F.occupancy(X_WG, X_WO, g).sum() == 0 and not queries.nearest
    # an object whose mesh lies away from its frame's origin: culled by where its mesh is
    d = np.array([0.15, -0.1, 0.05])
    moved = dataclasses.replace(g, vertices=g.vertices + d, sdf=SdfGrid(g.sdf.origin + d, g.sdf.spacing, g.sdf.values))
    X_OG = random_pose(np.random.default_rng(13), 0.03)
    expect = FastOccupancy()(X_OG, g)
    X_OG[:3, 3] += d
    np.testing.assert_array_equal(FastOccupancy()(X_OG, moved), expect)
    assert expect.sum() > 20
    with pytest.raises(DexdrakeError, match="level"):
        FastOccupancy(levels=0)


def test_occupancy_order_is_x_major(geometries):
    # a grid shifted along +x of the grid frame: the object fills low ix only
    X_WG = np.eye(4)
    X_WG[0, 3] = 0.13
    occ = F.occupancy(X_WG, np.eye(4), geometries["sphere"]).reshape(10, 10, 10)
    assert occ[:2].sum() > 0 and occ[5:].sum() == 0
    assert np.array_equal(voxel_centres()[100 * 3 + 10 * 4 + 5], (np.array([3, 4, 5]) + 0.5) * 0.02 - 0.1)
    # the occupied voxels the viewer draws: their centres and half edge
    centres, half = occupied_voxels(occ.ravel(), 0.2, 10)
    np.testing.assert_array_equal(centres, voxel_centres()[occ.ravel() == 1])
    assert half == 0.01 and len(centres) == occ.sum()
    np.testing.assert_array_equal(voxel_centres(0.2, 1), [[0.0, 0.0, 0.0]])  # one voxel: the grid centre
    for size, resolution in ((0.0, 10), (0.2, 0)):
        with pytest.raises(DexdrakeError, match=rf"bad occupancy grid: size {size}, resolution {resolution}"):
            voxel_centres(size, resolution)


def test_surface_on_sphere(geometries):
    g = geometries["sphere"]
    rng = np.random.default_rng(2)
    X_WO = random_pose(rng)
    dirs = rng.normal(size=(22, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radii = np.r_[np.linspace(0.0, 0.04, 6), [R_SPHERE] * 4, np.linspace(0.051, 0.5, 12)]
    p_W = (dirs * radii[:, None]) @ X_WO[:3, :3].T + X_WO[:3, 3]
    cp = F.closest_points(p_W, X_WO, g)
    fs = F.surface_from_closest(cp).reshape(22, 4)
    assert np.all(np.isfinite(fs))
    expect = np.clip(radii - R_SPHERE, 0, 0.2)
    np.testing.assert_allclose(fs[:, 0], expect, atol=2e-4)
    np.testing.assert_allclose(np.linalg.norm(fs[:, 1:], axis=1), 1.0, atol=1e-9)
    n_W = dirs @ X_WO[:3, :3].T
    ok = radii > 0.01  # at the centre every direction is a nearest one
    assert np.all(np.einsum("ij,ij->i", fs[ok, 1:], n_W[ok]) > 0.99)
    # the public code's scaling multiplies the distances only
    np.testing.assert_allclose(F.surface_from_closest(cp, scale=10.0).reshape(22, 4), np.c_[10 * fs[:, 0], fs[:, 1:]])
    with pytest.raises(DexdrakeError, match=r"hand points must be a finite \(n, 3\) array, got shape \(22, 2\)"):
        F.closest_points(p_W[:, :2], X_WO, g)
    # hand-frame normals are the world normals rotated
    R = Rotation.from_euler("z", 0.7).as_matrix()
    np.testing.assert_allclose(F.surface_from_closest(cp, R_WH=R).reshape(22, 4)[:, 1:], fs[:, 1:] @ R, atol=1e-12)


@pytest.mark.parametrize("shape", ["box", "torus"])
def test_closest_points_match_analytic_sd(geometries, shape):
    rng = np.random.default_rng(3)
    p_O = rng.uniform(-0.12, 0.12, (200, 3))
    cp = geometries[shape].closest_points(p_O)
    true = SHAPES[shape][1](p_O)
    np.testing.assert_allclose(cp.distance, true, atol=1e-3)  # torus facets ~0.3 mm
    np.testing.assert_allclose(SHAPES[shape][1](cp.points), 0.0, atol=1e-3)
    # the normal is the signed distance's gradient (at edges and corners too: not the face's)
    g = geometries[shape]
    off = np.abs(true) > 0.01 if shape == "torus" else true > 0.001  # the box's gradient jumps inside
    h = 1e-6
    gradient = np.stack([(SHAPES[shape][1](p_O + h * e) - SHAPES[shape][1](p_O - h * e)) / (2 * h) for e in np.eye(3)], 1)
    np.testing.assert_allclose(cp.normals[off], gradient[off], atol=0.05 if shape == "torus" else 1e-4)  # torus: facets
    assert off.sum() > 50
    with pytest.raises(DexdrakeError, match=r"^closest_points: query points contain NaN or Inf$"):
        g.closest_points([[0.0, np.nan, 0.0]])
    # geometry goes to worker processes pickled, its Open3D scene rebuilt there
    copy = pickle.loads(pickle.dumps(g))
    np.testing.assert_array_equal(copy.closest_points(p_O).distance, cp.distance)
    grid = g.sdf
    band = np.abs(true) < 0.02  # inside the padded grid
    np.testing.assert_allclose(grid.trilinear_index((p_O[band] - grid.origin) / grid.spacing), true[band], atol=1e-3)


def test_sdf_grid_interpolates_trilinearly_and_extrapolates_from_the_border_cell():
    # any node values, against scipy's trilinear interpolation (linear extrapolation outside)
    rng = np.random.default_rng(12)
    values = rng.normal(size=(5, 6, 7)).astype(np.float32)
    grid = SdfGrid(np.array([0.1, -0.2, 0.3]), 0.01, values)
    reference = RegularGridInterpolator([np.arange(n) for n in values.shape], values.astype(float),
                                        bounds_error=False, fill_value=None)
    u = rng.uniform(-2.5, np.array(values.shape) + 1.5, (400, 3))
    np.testing.assert_allclose(grid.trilinear_index(u), reference(u), atol=1e-12)
    sd, grad = grid.trilinear_index(u, with_gradient=True)
    np.testing.assert_array_equal(sd, grid.trilinear_index(u))
    h = 1e-7  # the interpolant is trilinear within each cell: central differences are exact there
    expect = np.stack([(reference(u + h * e) - reference(u - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(grad, expect, atol=1e-6)
    # the nearest node's value; points outside take the nearest border node's
    nearest = np.clip(np.floor(u + 0.5), 0, np.array(values.shape) - 1).astype(int)
    np.testing.assert_array_equal(grid.nearest_node_index_value(u), values[tuple(nearest.T)])


def test_local_geo_is_feature_of_nearest_sample(geometries):
    g = geometries["torus"]
    rng = np.random.default_rng(4)
    X_WO = random_pose(rng)
    p_W = rng.uniform(-0.15, 0.15, (22, 3))
    cp = F.closest_points(p_W, X_WO, g)
    fl = F.local_geo_from_closest(cp, X_WO, g).reshape(22, 64)
    c_W = cp.points
    c_O = (c_W - X_WO[:3, 3]) @ X_WO[:3, :3]
    nearest = np.argmin(np.linalg.norm(g.samples[None] - c_O[:, None], axis=2), axis=1)
    np.testing.assert_array_equal(fl, g.local_features[nearest])
    assert np.all(np.linalg.norm(g.samples[nearest] - c_O, axis=1) < 0.01)


def test_hand_state_layout():
    rng = np.random.default_rng(5)
    q, p_W, X = rng.normal(size=30), rng.normal(size=(22, 3)), random_pose(rng)
    fh = F.hand_state(q, p_W, X)
    assert fh.shape == (105,) == (F.hand_state_size(30, 22),)
    np.testing.assert_array_equal(fh[:30], q)
    np.testing.assert_allclose(fh[30:96].reshape(22, 3) @ X[:3, :3].T + X[:3, 3], p_W, atol=1e-12)
    np.testing.assert_array_equal(fh[96:99], X[:3, 3])
    np.testing.assert_array_equal(fh[99:], np.r_[X[:3, 0], X[:3, 1]])
    with pytest.raises(DexdrakeError, match=r"hand points must be a finite \(n, 3\) array, got shape \(22, 2\)"):
        F.hand_state(q, p_W[:, :2], X)
    with pytest.raises(DexdrakeError, match="hand_state: joint positions contain NaN or Inf"):
        F.hand_state(np.r_[q[:-1], np.nan], p_W, X)
    # the object pose in the PointNet-global (pglo) features: position, then R's first two columns
    np.testing.assert_array_equal(F.pose_6d(X), np.r_[X[:3, 3], X[:3, 0], X[:3, 1]])
    from pydrake.math import RigidTransform

    np.testing.assert_allclose(F.pose_6d(RigidTransform(X)), F.pose_6d(X), atol=1e-12)  # poses as Drake gives them
    for bad, shape in ((X[:3, :3], r"\(3, 3\)"), (np.where(np.eye(4) == 1, np.nan, X), r"\(4, 4\)")):
        with pytest.raises(DexdrakeError, match=rf"expected a finite 4x4 pose, got shape {shape}"):
            F.pose_6d(bad)


def test_bad_meshes_are_refused():
    box = trimesh.creation.box((0.1, 0.1, 0.1))
    one_flipped = box.faces.copy()
    one_flipped[0] = one_flipped[0, ::-1]
    for faces, message in (
            (box.faces[:3], "mesh: has 3 faces; a closed surface needs at least 4"),
            (box.faces[:-1], "mesh: not watertight (open boundary or non-manifold edges); signed distances would be wrong"),
            (one_flipped, "mesh: inconsistent face winding; signed distances would be wrong"),
            (box.faces[:, ::-1], "mesh: faces wound inward (volume -0.001 m^3 <= 0); flip the faces so normals point outward")):
        with pytest.raises(DexdrakeError) as refused:
            check_mesh(trimesh.Trimesh(box.vertices, faces, process=False))
        assert str(refused.value) == message
    with pytest.raises(DexdrakeError, match="^cup.obj: not watertight"):
        check_mesh(trimesh.Trimesh(box.vertices, box.faces[:-1], process=False), "cup.obj")
    check_mesh(box)
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], [[0, 1, 2], [0, 1, 3], [1, 2, 3], [0, 2, 3]],
                           process=False)
    with pytest.raises(DexdrakeError, match="degenerate"):
        check_mesh(flat)


def test_cache_round_trip(tmp_path, monkeypatch, encoder):
    monkeypatch.setenv("DEXDRAKE_CACHE", str(tmp_path))
    path = tmp_path / "box.obj"
    trimesh.creation.box((0.05, 0.04, 0.03)).export(path)
    a = load_object_geometry(path, encoder, grid_spacing=0.004)
    assert len(list((tmp_path / "dexrep").glob("*.npz"))) == 1
    b = load_object_geometry(path, encoder, grid_spacing=0.004)
    assert a.key == b.key
    for f in ("samples", "normals", "local_features", "global_feature"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    np.testing.assert_array_equal(a.sdf.values, b.sdf.values)
    assert a.samples.shape == (2048, 3) and a.local_features.shape == (2048, 64)
    assert a.global_feature.shape == (1024,)
    c = load_object_geometry(path, encoder, seed=1, grid_spacing=0.004)
    assert c.key != a.key and not np.array_equal(c.samples, a.samples)


def test_pointnet_shapes_and_chamfer():
    torch.manual_seed(0)
    ae = PointNetAutoEncoder(num_points=128).eval()
    x = torch.rand(2, 128, 3)
    recon, t = ae(x)
    assert recon.shape == (2, 128, 3) and t.shape == (2, 64, 64)
    assert chamfer_distance(x, x).item() < 1e-6
    assert chamfer_distance(x, x + 0.1).item() > 0.0
    local, glob = encode_cloud(ae.encoder, np.random.default_rng(0).normal(size=(128, 3)))
    assert local.shape == (128, 64) and glob.shape == (1024,)


def test_feature_sizes_and_describe(capsys):
    from dexdrake.cli.features import add_parser
    from dexdrake.dexrep.feature_sets import FEATURE_SETS, observation_blocks
    from dexdrake.hands.description import load_hand

    adroit = load_hand("adroit")
    assert observation_blocks(adroit, "DexRep") == {"hand": 105, "occ_surf": 1088, "local_geo": 1408}
    for name in FEATURE_SETS:
        assert next(iter(observation_blocks(adroit, name))) == "hand"
    assert observation_blocks(load_hand("allegro_z1"), "DexRep")["hand"] == 91
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    args = parser.parse_args(["features", "describe", "--hand", "adroit", "--feature-set", "DexRep"])
    assert args.func(args) == 0
    assert "occ_surf 1088" in capsys.readouterr().out


# --- the SceneGraph path -----------------------------------------------------------------


@pytest.fixture(scope="module")
def hand_scene(tmp_path_factory, geometries):
    """Adroit + a free torus whose watertight mesh has the proximity role."""
    from pydrake.geometry import Mesh, ProximityProperties
    from pydrake.math import RigidTransform
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.multibody.tree import SpatialInertia, UnitInertia
    from pydrake.systems.framework import DiagramBuilder

    from dexdrake.hands.description import load_hand

    hand = load_hand("adroit")
    obj = tmp_path_factory.mktemp("obj") / "torus.obj"
    trimesh.Trimesh(geometries["torus"].vertices, geometries["torus"].faces).export(obj)
    builder = DiagramBuilder()
    plant, sg = AddMultibodyPlantSceneGraph(builder, 0.002)
    (hand_instance,) = Parser(plant).AddModels(hand.model_path)
    obj_instance = plant.AddModelInstance("object")
    body = plant.AddRigidBody("torus", obj_instance, SpatialInertia(0.5, np.zeros(3), UnitInertia.SolidSphere(0.05)))
    gid = plant.RegisterCollisionGeometry(body, RigidTransform(), Mesh(str(obj)), "distance", ProximityProperties())
    plant.Finalize()
    diagram = builder.Build()
    return dict(hand=hand, plant=plant, sg=sg, diagram=diagram, hand_instance=hand_instance,
                obj_instance=obj_instance, body=body, gid=gid)


def _posed_context(s, rng):
    from pydrake.math import RigidTransform, RotationMatrix

    ctx = s["diagram"].CreateDefaultContext()
    plant = s["plant"]
    pctx = plant.GetMyMutableContextFromRoot(ctx)
    lo, hi = s["hand"].joint_limits()
    q = plant.GetPositions(pctx).copy()
    for j, a, b in zip(s["hand"].policy_joints, lo, hi):
        joint = plant.GetJointByName(j, s["hand_instance"])
        q[joint.position_start()] = rng.uniform(max(a, -0.3), min(b, 0.3)) if j.startswith("AR") else rng.uniform(a, b)
    plant.SetPositions(pctx, q)
    palm = plant.EvalBodyPoseInWorld(pctx, plant.GetBodyByName(s["hand"].palm.body, s["hand_instance"]))
    X_WO = RigidTransform(RotationMatrix(Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()),
                          palm.translation() + rng.uniform(-0.05, 0.05, 3))
    plant.SetFreeBodyPose(pctx, s["body"], X_WO)
    return ctx, pctx, X_WO


def test_scenegraph_and_fast_paths_agree(hand_scene, geometries):
    from dexdrake.dexrep.feature_sets import FeatureExtractor

    s = hand_scene
    fast = FeatureExtractor(s["hand"], s["plant"], s["hand_instance"], geometries["torus"], "DexRep", "fast")
    slow = FeatureExtractor(s["hand"], s["plant"], s["hand_instance"], geometries["torus"], "DexRep", "scenegraph",
                            distance_geometry_id=s["gid"])
    rng = np.random.default_rng(6)
    for _ in range(3):
        ctx, pctx, X_WO = _posed_context(s, rng)
        query = s["sg"].get_query_output_port().Eval(s["sg"].GetMyContextFromRoot(ctx))
        a, b = fast(pctx, X_WO), slow(pctx, X_WO, query)
        assert a.shape == b.shape == (105 + 1088 + 1408,)
        assert np.all(np.isfinite(a))
        np.testing.assert_array_equal(a[:105], b[:105])
        occ_a, occ_b = a[105:1105], b[105:1105]
        assert np.sum(occ_a != occ_b) <= max(2, 0.02 * occ_b.sum())  # same rule: marginal voxels only
        fs_a, fs_b = a[1105:1193].reshape(22, 4), b[1105:1193].reshape(22, 4)
        snap = fast.snapshot(pctx, X_WO)  # the viewer's parts are the features' parts
        np.testing.assert_array_equal(snap.occupancy, occ_a)
        np.testing.assert_allclose(np.clip(snap.closest.distance, 0, 0.2), fs_a[:, 0], atol=1e-12)
        np.testing.assert_allclose(snap.closest.normals, fs_a[:, 1:], atol=1e-12)
        np.testing.assert_allclose(fs_a[:, 0], fs_b[:, 0], atol=1e-5)
        assert np.all(np.einsum("ij,ij->i", fs_a[:, 1:], fs_b[:, 1:]) > 0.99)
        # local-geo: the same sample unless two samples are nearly equidistant
        same = np.all(a[1193:].reshape(22, 64) == b[1193:].reshape(22, 64), axis=1)
        assert same.mean() >= 0.9


def test_extractor_gives_the_bits_of_the_features_computed_one_group_at_a_time(hand_scene, geometries,
                                                                             load_script):
    """The per-step kernel (body poses read once, one closest-point query for every group)
    against scripts/bench_features.py's peer, which computes each group on its own from the
    public functions of dexrep.features."""
    from dexdrake.dexrep.feature_sets import FEATURE_SETS, FeatureExtractor

    reference_features = load_script("bench_features").reference_features
    s, g = hand_scene, geometries["torus"]
    rng = np.random.default_rng(17)
    contexts = [_posed_context(s, rng) for _ in range(4)]
    for feature_set in FEATURE_SETS:
        fx = FeatureExtractor(s["hand"], s["plant"], s["hand_instance"], g, feature_set, "fast")
        for _, pctx, X_WO in contexts:
            out, closest = fx.with_closest(pctx, X_WO)
            np.testing.assert_array_equal(
                out, reference_features(s["hand"], s["plant"], s["hand_instance"], g, feature_set, pctx, X_WO))
            if closest is not None:
                X = X_WO.GetAsMatrix4()
                expect = g.closest_points((fx.hand_points(pctx) - X[:3, 3]) @ X[:3, :3])
                for field in ("distance", "points", "normals"):
                    np.testing.assert_array_equal(getattr(closest, field), getattr(expect, field))


def test_dexrep_system_outputs_extractor_features(hand_scene, geometries):
    from dexdrake.systems.dexrep_system import DexRepSystem

    from dexdrake.systems.station import pose_vector

    s = hand_scene
    system = DexRepSystem(s["hand"], s["plant"], s["hand_instance"], geometries["torus"], "Occ+Surf")
    assert system.GetOutputPort("features").size() == 105 + 1088
    ctx, pctx, X_WO = _posed_context(s, np.random.default_rng(7))
    sys_ctx = system.CreateDefaultContext()
    plant, n = s["plant"], s["hand"].num_actuators
    q = [plant.GetPositions(pctx)[plant.GetJointByName(j, s["hand_instance"]).position_start()]
         for j in s["hand"].policy_joints]
    system.GetInputPort("hand_state").FixValue(sys_ctx, np.r_[q, np.zeros(n)])  # measured, in policy order
    system.GetInputPort("object_pose").FixValue(sys_ctx, pose_vector(X_WO))  # perceived
    out = system.GetOutputPort("features").Eval(sys_ctx)
    np.testing.assert_allclose(out, system.extractor(pctx, X_WO), atol=1e-9)


def test_velocity_group_reads_the_policy_joints_velocities_in_both_paths(hand_scene, geometries):
    """DexRep+Vel appends the policy joints' velocities (in policy order) to DexRep; the
    DexRepSystem takes them from its measured hand state [q; v], as the extractor does from
    the plant's state."""
    from dexdrake.dexrep.feature_sets import observation_blocks
    from dexdrake.systems.dexrep_system import DexRepSystem
    from dexdrake.systems.station import pose_vector

    s = hand_scene
    plant, hand, n = s["plant"], s["hand"], s["hand"].num_actuators
    assert list(observation_blocks(hand, "DexRep+Vel").items()) == [*observation_blocks(hand, "DexRep").items(),
                                                                      ("hand_vel", n)]
    ctx, pctx, X_WO = _posed_context(s, np.random.default_rng(11))
    joints = [plant.GetJointByName(j, s["hand_instance"]) for j in hand.policy_joints]
    v_hand = np.random.default_rng(12).normal(size=n)
    v = plant.GetVelocities(pctx).copy()
    v[[j.velocity_start() for j in joints]] = v_hand
    plant.SetVelocities(pctx, v)
    system = DexRepSystem(hand, plant, s["hand_instance"], geometries["torus"], "DexRep+Vel")
    direct = system.extractor(pctx, X_WO)
    np.testing.assert_array_equal(direct[-n:], v_hand)
    sys_ctx = system.CreateDefaultContext()
    q_hand = [plant.GetPositions(pctx)[j.position_start()] for j in joints]
    system.GetInputPort("hand_state").FixValue(sys_ctx, np.r_[q_hand, v_hand])
    system.GetInputPort("object_pose").FixValue(sys_ctx, pose_vector(X_WO))
    np.testing.assert_allclose(system.GetOutputPort("features").Eval(sys_ctx), direct, atol=1e-9)


def test_manifest_of_shipped_encoder():
    from dexdrake.dexrep.pointnet import default_encoder_path, load_encoder

    path = default_encoder_path()
    manifest = json.loads(path.with_suffix(".json").read_text())
    assert {"command", "data", "chamfer_train", "chamfer_unseen", "date", "torch"} <= set(manifest)
    assert isinstance(load_encoder(), PointNetEncoder)


def _last_row(path, entity: str, column: str) -> list:
    """The value of an archetype's component column in the last row logged at `entity`."""
    from rerun.chunk import RrdReader

    chunks = [c for c in RrdReader(path).stream().collect().stream() if c.entity_path == entity]
    batch = chunks[-1].to_record_batch()
    return batch.column(column).to_pylist()[-1]


def test_features_show_logs_dexrep_each_step(tmp_path):
    from dexdrake.cli.features import add_parser
    from dexdrake.dexrep.feature_sets import FeatureExtractor
    from dexdrake.dexrep.geometry import object_geometry
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.rerun_logger import RerunLogger
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.scripted_grasp import ScriptedGrasp

    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    rrd = tmp_path / "show.rrd"
    args = parser.parse_args(["features", "show", "--object", "sphere_medium", "--rrd", str(rrd), "--horizon", "2"])
    assert args.func(args) == 0
    rows = logged_rows(rrd)
    # The reset and each of the 2 steps log the DexRep parts next to the scene.
    for entity in ("/world/dexrep/grid", "/world/dexrep/grid/voxels", "/world/dexrep/hand_points",
                   "/world/dexrep/closest_points", "/world/dexrep/normals",
                   "/dexrep/distance/fftip", "/dexrep/distance/thtip"):
        assert rows[entity] == 3, entity
    assert rows["/reward/total"] == 2 and rows["/world/object/mesh"] == 1

    env = GraspEnv(training_scenario("adroit", "sphere_medium"), horizon=20)  # the hand reaches the object
    logger = RerunLogger(tmp_path / "again.rrd", "sim")
    env.rollout(ScriptedGrasp, 0, logger=logger)
    logger.close()
    extractor = FeatureExtractor(env.scene.hand, env.scene.plant, env.scene.hand_instance,
                                 object_geometry("sphere_medium"), "Occ+Surf")
    snap = extractor.snapshot(env.plant_context, env.scene.object_pose(env.plant_context))
    # the voxel boxes of the last step are the occupied voxels of DexRep's own occupancy
    voxels = _last_row(tmp_path / "again.rrd", "/world/dexrep/grid/voxels", "Boxes3D:centers")
    assert len(voxels) == snap.occupancy.sum() > 0
    points = _last_row(tmp_path / "again.rrd", "/world/dexrep/closest_points", "Points3D:positions")
    np.testing.assert_allclose(points, snap.closest.points, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(snap.closest.normals, axis=1), 1.0, atol=1e-9)
