"""How alike two objects' shapes are: mean surface Chamfer distance, best over yaw.

Both meshes are in their object frames (origin at the centre of mass, z up, resting pose),
so the only free motion between two resting objects is a turn about z. With P and Q points
spread evenly over the two surfaces (N each, fixed seed),

    chamfer(P, Q) = ( mean_p min_q |p - q| + mean_q min_p |q - p| ) / 2        (metres)

and `distance(a, b)` is its minimum over `YAWS` turns of b about z in [0, 2 pi). Zero for
the same shape; a few millimetres for a shape and a slightly scaled copy of it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import trimesh
from scipy.spatial import cKDTree

POINTS = 1024  # surface points per object
YAWS = 36  # turns of the second object tried (10 degrees apart)


def surface_points(mesh: trimesh.Trimesh, n: int = POINTS, seed: int = 0) -> np.ndarray:
    """`n` points spread uniformly by area over the mesh surface, (n, 3), seeded."""
    points, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(points, dtype=float)


def _turned(points: np.ndarray, yaws: int, sign: float) -> np.ndarray:
    """(yaws, n, 3): `points` turned about z by sign * 2 pi k / yaws, k = 0 .. yaws-1."""
    angles = sign * np.linspace(0.0, 2 * np.pi, yaws, endpoint=False)
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    return np.stack([c * x - s * y, s * x + c * y, np.broadcast_to(z, c.shape[:1] + z.shape)], axis=-1)


def distance(p: np.ndarray, q: np.ndarray, yaws: int = YAWS) -> float:
    """The mean surface Chamfer distance (m) of point sets p and q, best over turns of q about z
    (q turned by +a against p is p turned by -a against q: each tree is built once)."""
    d_qp = cKDTree(p).query(_turned(q, yaws, 1.0).reshape(-1, 3))[0].reshape(yaws, -1).mean(1)
    d_pq = cKDTree(q).query(_turned(p, yaws, -1.0).reshape(-1, 3))[0].reshape(yaws, -1).mean(1)
    return float(np.min(0.5 * (d_qp + d_pq)))


def _chamfer(p: np.ndarray, q: np.ndarray) -> float:
    return float(0.5 * (cKDTree(q).query(p)[0].mean() + cKDTree(p).query(q)[0].mean()))


def _radial(points: np.ndarray) -> np.ndarray:
    """(r, z) of each point, r its distance from the z axis: what a turn about z keeps."""
    return np.stack([np.hypot(points[:, 0], points[:, 1]), points[:, 2]], axis=1)


def lower_bound(p: np.ndarray, q: np.ndarray) -> float:
    """A lower bound of `distance(p, q)` without a turn: the Chamfer distance of the points' (r, z).
    |a - b| >= |(r_a, z_a) - (r_b, z_b)| for any a, b (|r_a - r_b| <= the xy distance), and
    (r, z) is the same at every turn, so every turn's Chamfer distance is at least this."""
    return _chamfer(_radial(p), _radial(q))


def nearest(p: np.ndarray, others: Sequence[np.ndarray]) -> tuple[int, float]:
    """(index, distance) of the point set in `others` nearest to `p` by `distance`, exactly:
    candidates in order of `lower_bound`, stopping once the bound reaches the best distance."""
    bounds = np.array([lower_bound(p, q) for q in others])
    best, best_k = np.inf, -1
    for k in np.argsort(bounds):
        if bounds[k] >= best:
            break
        d = distance(p, others[k])
        if d < best:
            best, best_k = d, int(k)
    return best_k, float(best)


def reference_meshes(copies: int, shapes: int) -> dict[str, trimesh.Trimesh]:
    """The training objects, their scaled copies 1..`copies` and procedural shapes 1..`shapes`
    (the augmented split `dexdrake objects augment --copies C --shapes S` makes), built in memory."""
    from dexdrake.objects.augment import copy_name, copy_scales, shape_name
    from dexdrake.objects.library import list_objects
    from dexdrake.objects.meshfile import load_obj
    from dexdrake.objects.procedural import procedural_shape

    out = {}
    for info in list_objects("train"):
        mesh = load_obj(info.mesh_path)
        out[info.name] = mesh
        for k in range(1, copies + 1):
            scaled = mesh.copy()
            scaled.vertices = np.asarray(mesh.vertices) * copy_scales(info.name, k)
            out[copy_name(info.name, k)] = scaled
    for k in range(1, shapes + 1):
        out[shape_name(k)] = procedural_shape(k)[0]
    return out


NOVELTY_SPLITS = ("unseen", "validation", "near")  # the held-out splits `novelty_table` measures


def training_median_nn(points: dict[str, np.ndarray], train: list[str]) -> float:
    """Median over training objects of the distance (m) to the nearest other training object."""
    from tqdm import tqdm

    return float(np.median([nearest(points[n], [points[m] for m in train if m != n])[1]
                            for n in tqdm(train, desc="training neighbours", unit="obj")]))


def novelty_table(copies: int, shapes: int, command: str) -> str:
    """How new the held-out objects are, as markdown naming `command`: each one's nearest
    reference (the training objects, `copies` scaled copies of each, `shapes` procedural
    shapes: the augmented split of `dexdrake objects augment`) by `distance`, and whether it
    lies beyond the threshold, the median training object's distance to its nearest training
    neighbour."""
    from tqdm import tqdm

    from dexdrake.objects.library import list_objects
    from dexdrake.objects.meshfile import load_obj

    refs = reference_meshes(copies, shapes)
    names = list(refs)
    points = {n: surface_points(m) for n, m in refs.items()}
    train = [i.name for i in list_objects("train")]
    threshold = training_median_nn(points, train)
    lines = ["# Held-out objects against the training and augmented objects", "",
             f"- command: `{command}`",
             (f"- {len(names)} reference objects: {len(train)} training objects, {copies} scaled copies of each, "
              f"{shapes} procedural shapes"),
             f"- distance: mean surface Chamfer, best over yaw (dexdrake.objects.similarity, {POINTS} points, {YAWS} turns)",
             ("- threshold: the median training object's distance to its nearest training neighbour, "
              f"{1000 * threshold:.1f} mm"), "",
             "| object | split | category | nearest reference | distance (mm) | beyond the threshold |",
             "|---|---|---|---|---|---|"]
    for split in NOVELTY_SPLITS:
        for info in tqdm(list_objects(split), desc=split, unit="obj"):
            k, d = nearest(surface_points(load_obj(info.mesh_path)), [points[n] for n in names])
            lines.append(f"| {info.name} | {split} | {info.category} | {names[k]} | {1000 * d:.1f} | "
                         f"{'yes' if d > threshold else 'no'} |")
    return "\n".join(lines) + "\n"
