"""Procedural training shapes: superquadrics and compounds of them, for shape variety.

Shape k is drawn from a seed made of k alone, so its name fixes its geometry: a base
superquadric resting on z = 0 (from a box through a cylinder to an ellipsoid or a diamond)
with zero, one or two smaller superquadrics attached on its top or sides. Every part is a
convex hull, so the parts are the object's contact pieces as they are (no CoACD run). A draw
is kept only when its parts form one solid that rests stably (the centre of mass above its
footprint) and survives the mesh file's rounding, else the next draw from the same seed is taken.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import trimesh

from dexdrake.errors import DexdrakeError
from dexdrake.objects.meshfile import check_mesh, is_stable_rest
from dexdrake.objects.shapes import Solid, _hull, _union, to_trimesh

GENERATOR = "superquadrics/2"  # recorded in each shape's meta.json: a changed generator remakes the shapes
PARTS_P = (0.3, 0.45, 0.25)  # probabilities of 1, 2 and 3 parts
BASE_AXES = ((0.015, 0.09), (0.015, 0.05), (0.012, 0.07))  # semi-axes a, b, c of the base (m)
PART_AXES = (0.008, 0.035)  # semi-axes of an attached part (m)
EXPONENTS = (0.1, 1.6)  # superquadric shape exponents: ~0.1 box-like, 1 round, 1.6 diamond-like
BASE_E1_MAX = 0.6  # the base's vertical exponent at most this: a flat-ish bottom to rest on
MAX_EXTENT = 0.2  # no side longer (m): a hand-sized object
FOOTPRINT_MARGIN = 0.004  # the centre of mass at least this far inside the footprint (m)


@dataclass(frozen=True)
class Superquadric:
    """Semi-axes (a, b, c), exponents e1 (along z) and e2 (around z), centre and yaw."""

    axes: tuple[float, float, float]
    e1: float
    e2: float
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw: float = 0.0

    def points(self, n_eta: int = 17, n_omega: int = 32) -> np.ndarray:
        """Points on the surface (world frame), dense enough for a faithful hull."""
        eta = np.linspace(-np.pi / 2, np.pi / 2, n_eta)[:, None]
        omega = np.linspace(-np.pi, np.pi, n_omega, endpoint=False)[None, :]

        def f(x: np.ndarray, e: float) -> np.ndarray:
            return np.sign(x) * np.abs(x) ** e

        a, b, c = self.axes
        local = np.stack([a * f(np.cos(eta), self.e1) * f(np.cos(omega), self.e2),
                          b * f(np.cos(eta), self.e1) * f(np.sin(omega), self.e2),
                          c * f(np.sin(eta), self.e1) * np.ones_like(omega)], axis=-1).reshape(-1, 3)
        cy, sy = np.cos(self.yaw), np.sin(self.yaw)
        return local @ np.array([[cy, sy, 0.0], [-sy, cy, 0.0], [0.0, 0.0, 1.0]]) + np.asarray(self.centre)

    def solid(self) -> Solid:
        return _hull(self.points())


def shape_seed(k: int) -> int:
    """The random seed of shape `k` (a hash of k, so shapes do not depend on one another)."""
    return int.from_bytes(hashlib.sha256(f"procedural:{k}".encode()).digest()[:8], "little")


def _draw_parts(rng: np.random.Generator) -> list[Superquadric]:
    """A base resting on z = 0 and up to two parts attached to it (PARTS_P)."""
    a, b, c = (rng.uniform(*r) for r in BASE_AXES)
    e1 = rng.uniform(EXPONENTS[0], BASE_E1_MAX)
    parts = [Superquadric((a, b, c), e1, rng.uniform(*EXPONENTS), (0.0, 0.0, c), rng.uniform(0, np.pi))]
    n_parts = 1 + rng.choice(len(PARTS_P), p=PARTS_P)
    for _ in range(n_parts - 1):
        size = tuple(rng.uniform(*PART_AXES, 3))
        base = parts[0]
        if rng.random() < 0.5:  # on top, near the centre, half of it sunk into the base
            xy = rng.uniform(-0.5, 0.5, 2) * np.array(base.axes[:2])
            centre = (xy[0], xy[1], 2 * base.axes[2])
        else:  # on a side, across one of the base's axes, a quarter of it sunk in
            side = rng.integers(4)
            axis, sign = side % 2, 1.0 if side < 2 else -1.0
            offset = np.zeros(2)
            offset[axis] = sign * (base.axes[axis] + 0.5 * size[axis])
            cy, sy = np.cos(base.yaw), np.sin(base.yaw)
            xy = np.array([[cy, -sy], [sy, cy]]) @ offset
            z = max(size[2], rng.uniform(0.5, 1.5) * base.axes[2])
            centre = (xy[0], xy[1], z)
        parts.append(Superquadric(size, rng.uniform(*EXPONENTS), rng.uniform(*EXPONENTS), centre, rng.uniform(0, np.pi)))
    return parts


def _well_formed(mesh: trimesh.Trimesh) -> bool:
    """`check_mesh` passes on the mesh as its file will hold it (vertices rounded to 1 micron)."""
    try:
        check_mesh(trimesh.Trimesh(np.round(np.asarray(mesh.vertices), 6), np.asarray(mesh.faces), process=False))
    except DexdrakeError:
        return False
    return True


def procedural_shape(k: int) -> tuple[trimesh.Trimesh, list[trimesh.Trimesh]]:
    """Shape `k`: its mesh and convex parts, in the object frame (origin at the centre of
    mass, z up, resting on its base)."""
    rng = np.random.default_rng(shape_seed(k))
    while True:
        parts = _draw_parts(rng)
        solids = [p.solid() for p in parts]
        union = _union(solids)
        if len(union.decompose()) != 1:
            continue
        mesh = to_trimesh(union)
        if np.max(mesh.extents) > MAX_EXTENT or not is_stable_rest(mesh, margin=FOOTPRINT_MARGIN):
            continue
        shift = -np.asarray(mesh.center_mass)
        mesh.apply_translation(shift)
        pieces = [to_trimesh(s) for s in solids]
        for p in pieces:
            p.apply_translation(shift)
        if _well_formed(mesh) and all(map(_well_formed, pieces)):
            return mesh, pieces
