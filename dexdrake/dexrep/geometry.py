"""Per-object DexRep precomputation and the fast distance structures built on it.

For one watertight, outward-wound mesh (object frame, metres) this computes once and caches
on disk under cache_dir()/dexrep/<sha256 of mesh bytes + parameters + encoder weights>.npz:
  - `samples` (2048, 3) surface points (seeded area-weighted sampling) and their outward
    face `normals`;
  - `local_features` (2048, 64) and `global_feature` (1024,) of the frozen PointNet encoder
    on those samples, in the object frame (normalised by centroid and max radius);
  - a dense signed-distance grid (`sdf`, negative inside) with trilinear interpolation,
    padded by SDF_PAD around the bounding box, used for occupancy.
At load it also builds an exact closest-point structure (Open3D RaycastingScene, float32)
for the hand points and a KD-tree on the samples for the local-geo lookup.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from dataclasses import dataclass, field
from functools import cache, cached_property
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from dexdrake.dexrep.pointnet import NUM_POINTS, PointNetEncoder, default_encoder_path, encode_cloud, load_encoder
from dexdrake.errors import DexdrakeError
from dexdrake.objects.meshfile import check_mesh
from dexdrake.paths import cache_dir

SDF_PAD = 0.03  # grid margin (m); > the 2 cm voxel half-diagonal, so outside = empty
MAX_GRID_NODES = 160  # per axis
FAR = 1.0e3  # signed distance reported for points known to be far from the object
CACHE_VERSION = 1


@dataclass(frozen=True)
class SdfGrid:
    """Signed distances (m) at nodes origin + spacing * (i, j, k); negative inside."""

    origin: np.ndarray  # (3,)
    spacing: float
    values: np.ndarray  # (nx, ny, nz) float32

    def trilinear_index(self, u: np.ndarray, with_gradient: bool = False):
        """Trilinear sd at (m, 3) points in index coordinates u = (p - origin) / spacing
        (inside the grid; outside it extrapolates linearly from the border cell). The gradient,
        if asked, is per index step (multiply by 1/spacing for per metre)."""
        i0 = np.floor(u)
        np.maximum(i0, 0.0, out=i0)
        np.minimum(i0, self._max_index, out=i0)
        fx, fy, fz = (u - i0).T
        # (8, m): corner rows ordered by (z, y, x) bits, so each axis halves the rows
        c = self._flat[self._corner_offsets + self._flat_index(i0)].astype(np.float64)
        dz = c[4:] - c[:4]  # (4, m): x0y0 x1y0 x0y1 x1y1
        cz = c[:4] + dz * fz
        dy = cz[2:] - cz[:2]  # (2, m): x0 x1
        cy = cz[:2] + dy * fy
        gx = cy[1] - cy[0]
        sd = cy[0] + gx * fx
        if not with_gradient:
            return sd
        gy = dy[0] + (dy[1] - dy[0]) * fx
        dzy = dz[:2] + (dz[2:] - dz[:2]) * fy
        gz = dzy[0] + (dzy[1] - dzy[0]) * fx
        return sd, np.array([gx, gy, gz]).T.copy()  # (m, 3) C order, cheaper than np.stack

    def nearest_node_index_value(self, u: np.ndarray) -> np.ndarray:
        """Signed distance at the grid node nearest to each (m, 3) index-coordinate point.
        Error <= spacing * sqrt(3) / 2 inside the grid; points outside clamp to border
        nodes, whose values are >= SDF_PAD (the object is never near them)."""
        i = np.floor(u + 0.5)
        np.maximum(i, 0.0, out=i)
        np.minimum(i, self._max_node, out=i)
        return self._flat[self._flat_index(i)].astype(np.float64)

    def _flat_index(self, i: np.ndarray) -> np.ndarray:
        """Flat indices of (m, 3) whole-number node indices held as floats (a float matmul:
        exact below 2^53, and BLAS where an integer matmul is a slow loop)."""
        return (i @ self._strides).astype(np.intp)

    @cached_property
    def _flat(self) -> np.ndarray:
        """The values as stored (float32: half the memory a gather touches), cast after it."""
        return np.ascontiguousarray(self.values).ravel()

    @cached_property
    def _strides(self) -> np.ndarray:
        """Flat-index strides of the node axes, as floats (see `_flat_index`)."""
        nx, ny, nz = self.values.shape
        return np.array([ny * nz, nz, 1], dtype=np.float64)

    @cached_property
    def _max_index(self) -> np.ndarray:
        """The largest cell index per axis (the last node's index - 1), as floats."""
        return np.array(self.values.shape, dtype=np.float64) - 2

    @cached_property
    def _max_node(self) -> np.ndarray:
        """The last node's index per axis, as floats."""
        return self._max_index + 1

    @cached_property
    def _corner_offsets(self) -> np.ndarray:
        """(8, 1) flat-index offsets of a cell's corners, corner k = (z, y, x) bits of k."""
        bits = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=np.float64)
        return (bits @ self._strides).astype(np.intp)[:, None]


@dataclass(frozen=True)
class ClosestPoints:
    """Per query point: signed distance (m, negative inside), closest surface point and the
    outward unit normal there (the signed-distance gradient), all in the object frame."""

    distance: np.ndarray  # (m,)
    points: np.ndarray  # (m, 3)
    normals: np.ndarray  # (m, 3)


@dataclass
class ObjectGeometry:
    key: str
    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    samples: np.ndarray  # (2048, 3)
    normals: np.ndarray  # (2048, 3)
    local_features: np.ndarray  # (2048, 64) float32
    global_feature: np.ndarray  # (1024,) float32
    sdf: SdfGrid
    _scene: object = field(default=None, init=False, repr=False)
    _tree: cKDTree | None = field(default=None, init=False, repr=False)

    def __getstate__(self) -> dict:  # the Open3D scene does not pickle; rebuilt lazily
        state = dict(self.__dict__)
        state["_scene"] = None
        return state

    @property
    def sample_tree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.samples)
        return self._tree

    def _raycasting_scene(self):
        if self._scene is None:
            import open3d as o3d

            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(
                o3d.core.Tensor(self.vertices.astype(np.float32)),
                o3d.core.Tensor(self.faces.astype(np.uint32)),
            )
            self._scene = scene
        return self._scene

    def prepare_queries(self) -> None:
        """Build the closest-point query structure now (Open3D's import and ray-casting
        scene: a second or more of the interpreter on first use), not in the first query,
        which may come in a control loop whose driver processes expect the interpreter's
        heartbeat."""
        self._raycasting_scene()

    def closest_points(self, p_O: np.ndarray) -> ClosestPoints:
        """Exact closest surface points, signed distances and outward normals (one Open3D
        query for all points)."""
        import open3d as o3d

        p = np.asarray(p_O, dtype=np.float64).reshape(-1, 3)
        if not np.isfinite(p).all():
            raise DexdrakeError("closest_points: query points contain NaN or Inf")
        res = self._raycasting_scene().compute_closest_points(
            o3d.core.Tensor.from_numpy(p.astype(np.float32)), nthreads=1)
        c = res["points"].numpy().astype(np.float64)
        face_n = self.face_normals[res["primitive_ids"].numpy()]
        delta = p - c
        dist = np.sqrt(np.einsum("ij,ij->i", delta, delta))
        # Sign: the grid is reliable away from the surface; near it use the face normal.
        grid = self.sdf
        sd_grid = grid.nearest_node_index_value((p - grid.origin) * (1.0 / grid.spacing))
        near = np.abs(sd_grid) < 2.0 * grid.spacing
        inside = np.where(near, np.einsum("ij,ij->i", delta, face_n) < 0.0, sd_grid < 0.0)
        sd = np.where(inside, -dist, dist)
        apart = dist > 1e-6
        normals = np.where(apart[:, None], delta / np.where(apart, sd, 1.0)[:, None], face_n)
        return ClosestPoints(sd, c, normals)

    @cached_property
    def face_normals(self) -> np.ndarray:
        """(F, 3) outward unit face normals."""
        n = np.cross(self.vertices[self.faces[:, 1]] - self.vertices[self.faces[:, 0]],
                     self.vertices[self.faces[:, 2]] - self.vertices[self.faces[:, 0]])
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    @cached_property
    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """(centre, radius) of a sphere holding the object: bounding-box centre, max radius."""
        centre = (self.vertices.min(axis=0) + self.vertices.max(axis=0)) / 2
        return centre, float(np.linalg.norm(self.vertices - centre, axis=1).max()) + 1e-9

    def nearest_samples(self, p_O: np.ndarray) -> np.ndarray:
        """Indices of the sampled surface points nearest to (m, 3) object-frame points."""
        return self.sample_tree.query(np.asarray(p_O, dtype=np.float64).reshape(-1, 3))[1]


def load_checked_mesh(mesh_path: Path) -> trimesh.Trimesh:
    """Loads a mesh and refuses one that cannot serve signed-distance queries."""
    mesh_path = Path(mesh_path)
    if not mesh_path.exists():
        raise DexdrakeError(f"mesh file not found: {mesh_path}")
    try:
        mesh = trimesh.load(mesh_path, force="mesh", process=True)
    except Exception as e:  # trimesh raises many types on bad files
        raise DexdrakeError(f"cannot read mesh {mesh_path}: {e}") from e
    check_mesh(mesh, str(mesh_path))
    return mesh


def _encoder_digest(encoder: PointNetEncoder) -> str:
    h = hashlib.sha256()
    for name, t in sorted(encoder.state_dict().items()):
        h.update(name.encode())
        h.update(t.detach().cpu().numpy().tobytes())
    return h.hexdigest()


def _sdf_grid(mesh: trimesh.Trimesh, spacing: float) -> SdfGrid:
    import open3d as o3d

    lo = mesh.bounds[0] - SDF_PAD
    hi = mesh.bounds[1] + SDF_PAD
    spacing = max(spacing, float(np.max(hi - lo)) / (MAX_GRID_NODES - 1))
    counts = np.ceil((hi - lo) / spacing).astype(int) + 1
    axes = [lo[i] + spacing * np.arange(counts[i]) for i in range(3)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).astype(np.float32)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    sd = scene.compute_signed_distance(o3d.core.Tensor(nodes), nsamples=3).numpy()
    return SdfGrid(lo.astype(np.float64), float(spacing), sd.astype(np.float32))


def compute_object_geometry(mesh: trimesh.Trimesh, encoder: PointNetEncoder, key: str = "",
                            num_samples: int = NUM_POINTS, seed: int = 0,
                            grid_spacing: float = 0.002) -> ObjectGeometry:
    """Computes everything for a checked mesh (no caching)."""
    check_mesh(mesh)
    samples, face_idx = trimesh.sample.sample_surface(mesh, num_samples, seed=seed)
    normals = mesh.face_normals[face_idx]
    local, glob = encode_cloud(encoder, samples)
    return ObjectGeometry(
        key=key,
        vertices=np.asarray(mesh.vertices, dtype=np.float64),
        faces=np.asarray(mesh.faces, dtype=np.int64),
        samples=np.asarray(samples, dtype=np.float64),
        normals=np.asarray(normals, dtype=np.float64),
        local_features=local,
        global_feature=glob,
        sdf=_sdf_grid(mesh, grid_spacing),
    )


def _shipped_encoder_digest() -> str:
    """`_encoder_digest` of the shipped encoder, read once per process while its file is unchanged."""
    path = default_encoder_path()
    if not path.is_file():
        load_encoder(path)  # its error names the missing weights
    stat = path.stat()
    return _file_encoder_digest(str(path), stat.st_mtime_ns, stat.st_size)


@cache
def _file_encoder_digest(path: str, mtime_ns: int, size: int) -> str:
    return _encoder_digest(load_encoder(Path(path)))


def load_object_geometry(mesh_path: Path | str, encoder: PointNetEncoder | None = None, *,
                         num_samples: int = NUM_POINTS, seed: int = 0, grid_spacing: float = 0.002,
                         use_cache: bool = True) -> ObjectGeometry:
    """The ObjectGeometry of a mesh file, from the disk cache when present.

    `encoder` defaults to the shipped frozen PointNet encoder (loaded only to compute a
    geometry); its weights are part of the cache key, as are the mesh bytes and the parameters.
    """
    mesh_path = Path(mesh_path)
    mesh = load_checked_mesh(mesh_path)
    params = dict(v=CACHE_VERSION, n=num_samples, seed=seed, spacing=grid_spacing, pad=SDF_PAD,
                  max_nodes=MAX_GRID_NODES)
    h = hashlib.sha256(mesh_path.read_bytes())
    h.update(json.dumps(params, sort_keys=True).encode())
    h.update((_encoder_digest(encoder) if encoder is not None else _shipped_encoder_digest()).encode())
    key = h.hexdigest()[:32]
    path = cache_dir() / "dexrep" / f"{key}.npz"
    if use_cache and path.exists():
        with np.load(path) as z:
            return ObjectGeometry(
                key=key, vertices=z["vertices"], faces=z["faces"], samples=z["samples"],
                normals=z["normals"], local_features=z["local_features"],
                global_feature=z["global_feature"],
                sdf=SdfGrid(z["sdf_origin"], float(z["sdf_spacing"]), z["sdf_values"]),
            )
    geom = compute_object_geometry(mesh, encoder if encoder is not None else load_encoder(), key, num_samples, seed,
                                   grid_spacing)
    if use_cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        buf = io.BytesIO()
        np.savez_compressed(
            buf, vertices=geom.vertices, faces=geom.faces, samples=geom.samples, normals=geom.normals,
            local_features=geom.local_features, global_feature=geom.global_feature,
            sdf_origin=geom.sdf.origin, sdf_spacing=geom.sdf.spacing, sdf_values=geom.sdf.values,
        )
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_bytes(buf.getvalue())
        tmp.replace(path)  # atomic: parallel workers never read a half-written file
    return geom


@cache
def object_geometry(name: str) -> ObjectGeometry:
    """The ObjectGeometry of a library object (see dexdrake.objects.library)."""
    from dexdrake.objects.library import get_object

    return load_object_geometry(get_object(name).mesh_path)
