"""Object pose from one RGB-D frame: green-screen segmentation, back-projection and
registration of the known CAD mesh to the partial cloud (specs/kinect.md recipe).

    estimator = ObjectPoseEstimator(mesh_path)          # builds or loads the model features
    result = estimator.estimate(frame)                  # never raises on perception failure
    if result.success: X_WO = result.X_WO
    result = estimator.track(next_frame, X_WO)          # cheap: ICP from the last pose

`estimate` is global (RANSAC on FPFH features, then ICP: about 0.6 s); `track` refines the
last pose on the next frame (point-to-plane ICP of the segmented points near it: a few ms)
and reports lost tracking (too few points near the last pose, or too few of them on the
model: occluded, moved too far; or a pose the depth image contradicts) as a failure, for the
caller to fall back to `estimate`.

Registration runs scene -> model (source = segmented scene cloud, target = model cloud), so
`fitness` is the fraction of observed points that lie on the posed model: about 1 for a
correct pose whatever the view, unlike a model -> scene fitness that a partial view caps.
A twin that fits most observed points (a tilted or flipped L) puts model surface where the
camera sees past it, so each try is also checked the other way round, model -> image
(`contradicted_fraction`), and a contradicted one is not chosen.
"""

from __future__ import annotations

import hashlib
import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from pydrake.math import RigidTransform
from scipy.spatial import cKDTree

from dexdrake.errors import DexdrakeError
from dexdrake.hardware.kinect import CameraIntrinsics, FrameError, RgbdFrame, validate_frame
from dexdrake.paths import cache_dir

_reg = o3d.pipelines.registration


# ---------------------------------------------------------------- segmentation

@dataclass(frozen=True)
class GreenScreenConfig:
    """Object = NOT green (OpenCV HSV, H in 0-179) within a depth range (mm); of the not-green
    regions (8-connected) those under `min_component_px` pixels are specks and dropped; a
    region's width does not count, so a thin part a few pixels wide is kept."""

    hsv_low: tuple[int, int, int] = (35, 60, 40)
    hsv_high: tuple[int, int, int] = (85, 255, 255)
    min_component_px: int = 10
    min_depth_mm: int = 250
    max_depth_mm: int = 1500

    def __post_init__(self) -> None:
        if not 0 <= self.min_depth_mm < self.max_depth_mm:
            raise DexdrakeError(f"depth range must satisfy 0 <= min < max, got "
                                f"[{self.min_depth_mm}, {self.max_depth_mm}] mm")
        if self.min_component_px < 0:
            raise DexdrakeError(f"min_component_px must be >= 0, got {self.min_component_px}")


def green_pixels(frame: RgbdFrame, config: GreenScreenConfig = GreenScreenConfig()
                 ) -> np.ndarray:
    """Boolean HxW mask of the green (background) pixels."""
    hsv = cv2.cvtColor(frame.color, cv2.COLOR_RGB2HSV)
    return cv2.inRange(hsv, np.array(config.hsv_low, np.uint8),
                       np.array(config.hsv_high, np.uint8)) > 0


def segment_object(frame: RgbdFrame, config: GreenScreenConfig = GreenScreenConfig()
                   ) -> np.ndarray:
    """Boolean HxW mask of non-green pixels, in regions of at least `min_component_px`
    pixels, with valid depth inside the configured range."""
    not_green = (~green_pixels(frame, config)).astype(np.uint8)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(not_green, connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= config.min_component_px
    keep[0] = False                     # label 0: the green pixels
    depth = frame.depth
    in_range = (depth > 0) & (depth >= config.min_depth_mm) & (depth <= config.max_depth_mm)
    return keep[labels] & in_range


# ---------------------------------------------------------------- back-projection

def backproject(depth_mm: np.ndarray, intrinsics: CameraIntrinsics,
                mask: np.ndarray | None = None) -> np.ndarray:
    """N x 3 points (m) in the camera frame for pixels with depth > 0 (and in `mask`)."""
    if depth_mm.shape != (intrinsics.height, intrinsics.width):
        raise FrameError(
            f"depth {depth_mm.shape} does not match intrinsics "
            f"{intrinsics.width}x{intrinsics.height}")
    valid = depth_mm > 0
    if mask is not None:
        if mask.shape != depth_mm.shape:
            raise FrameError(f"mask {mask.shape} does not match depth {depth_mm.shape}")
        valid &= mask.astype(bool)
    v, u = np.nonzero(valid)
    z = depth_mm[v, u].astype(np.float64) * 1e-3
    x = (u - intrinsics.cx) * z / intrinsics.fx
    y = (v - intrinsics.cy) * z / intrinsics.fy
    return np.column_stack([x, y, z])


def transform_points(X_AB: RigidTransform, p_B: np.ndarray) -> np.ndarray:
    """Points (N x 3) expressed in B -> expressed in A."""
    return (X_AB.rotation().matrix() @ p_B.T).T + X_AB.translation()


# ---------------------------------------------------------------- model features (cached)

@dataclass(frozen=True)
class RegistrationConfig:
    """Tuned recipe from specs/kinect.md; distances are multiples of `voxel` (m)."""

    voxel: float = 0.005
    normal_radius_factor: float = 2.0
    fpfh_radius_factor: float = 5.0
    ransac_distance_factor: float = 1.5
    ransac_n: int = 3
    edge_length_ratio: float = 0.9
    ransac_max_iterations: int = 100_000
    ransac_confidence: float = 0.999
    ransac_runs: int = 5
    good_fitness: float = 0.95    # below it after the runs: try half turns, then extra runs
    try_flips: bool = True
    extra_runs: int = 5
    mutual_filter: bool = False
    icp_distance_factors: tuple[float, ...] = (2.0, 0.4)
    icp_max_iterations: int = 50
    fitness_distance_factor: float = 1.5
    min_points: int = 60
    min_fitness: float = 0.7
    # A try is refused when more than `max_contradicted` of its camera-facing surface is
    # contradicted (`contradicted_fraction`): at every pixel within `free_space_window_factor`
    # voxels (at the object's median depth) of the point's pixel the frame shows green screen
    # or a depth more than `free_space_margin_factor` voxels beyond the point.
    free_space_margin_factor: float = 2.0
    free_space_window_factor: float = 2.0
    max_contradicted: float = 0.03
    model_samples_per_voxel_area: float = 4.0
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.voxel > 0:
            raise DexdrakeError(f"voxel must be positive (m), got {self.voxel}")
        if self.ransac_runs < 1 or self.extra_runs < 0 or self.ransac_n < 3:
            raise DexdrakeError("need ransac_runs >= 1, extra_runs >= 0 and ransac_n >= 3")
        if not 0 <= self.min_fitness <= 1:
            raise DexdrakeError(f"min_fitness must be in [0, 1], got {self.min_fitness}")
        if not 0 <= self.max_contradicted <= 1:
            raise DexdrakeError(f"max_contradicted must be in [0, 1], got {self.max_contradicted}")
        if self.free_space_margin_factor < 0 or self.free_space_window_factor < 0:
            raise DexdrakeError("free_space_margin_factor and free_space_window_factor must be >= 0")


@dataclass(frozen=True)
class TrackingConfig:
    """Frame-to-frame tracking (`ObjectPoseEstimator.track`); distances in m.

    Only segmented points within the model's radius + `crop_margin` of the last pose's
    centre are used (the rest of the scene, e.g. the arm, is not the object); ICP at each of
    `icp_distances` (coarse to fine: the coarse one bounds the motion between frames). The
    track holds while at least `min_points` of them lie within `fitness_distance` of the
    posed model, they are at least `min_fitness` of the cropped points (fingers in front
    of the object lower it, the object lost lowers it to 0), and the depth image contradicts
    no more of the posed model than a global registration may (`RegistrationConfig.
    max_contradicted`: after a fast turn, such as a topple, ICP can settle on a wrong pose
    that fits most of the visible points)."""

    voxel: float = 0.005
    crop_margin: float = 0.04
    icp_distances: tuple[float, ...] = (0.02, 0.0075, 0.004)
    icp_max_iterations: int = 15
    fitness_distance: float = 0.0075
    min_points: int = 40
    min_fitness: float = 0.6

    def __post_init__(self) -> None:
        if not (self.voxel > 0 and self.crop_margin >= 0 and self.fitness_distance > 0
                and self.icp_distances and min(self.icp_distances) > 0):
            raise DexdrakeError("tracking voxel, distances must be positive (m)")
        if not 0 <= self.min_fitness <= 1 or self.min_points < 3:
            raise DexdrakeError("tracking needs min_fitness in [0, 1] and min_points >= 3")


@dataclass(frozen=True)
class ModelCloud:
    """A mesh's surface sampled, voxel-downsampled, with outward normals and FPFH."""

    points: np.ndarray      # N x 3, object frame (m)
    normals: np.ndarray     # N x 3, unit, outward
    fpfh: np.ndarray        # 33 x N
    content_hash: str

    def point_cloud(self) -> o3d.geometry.PointCloud:
        """The cloud as Open3D geometry (with normals)."""
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points))
        pcd.normals = o3d.utility.Vector3dVector(self.normals)
        return pcd

    def feature(self) -> _reg.Feature:
        """The FPFH descriptors as an Open3D Feature."""
        f = _reg.Feature()
        f.data = self.fpfh
        return f


_MODEL_CACHE: dict[str, ModelCloud] = {}


def model_cloud(mesh_path: str | Path, config: RegistrationConfig = RegistrationConfig(),
                use_disk_cache: bool = True) -> ModelCloud:
    """The cached ModelCloud of a mesh file (memory, then cache_dir()/perception, then built).

    The key is the mesh content hash plus every parameter that shapes the cloud."""
    mesh_path = Path(mesh_path)
    if not mesh_path.is_file():
        raise DexdrakeError(f"CAD mesh {mesh_path} does not exist")
    digest = hashlib.sha256(mesh_path.read_bytes()).hexdigest()
    params = (config.voxel, config.normal_radius_factor, config.fpfh_radius_factor,
              config.model_samples_per_voxel_area, config.seed)
    key = hashlib.sha256(f"{digest}{params}".encode()).hexdigest()[:24]
    if key in _MODEL_CACHE:
        return _MODEL_CACHE[key]
    disk = cache_dir() / "perception" / f"model_{key}.npz"
    if use_disk_cache and disk.is_file():
        with np.load(disk) as d:
            model = ModelCloud(d["points"], d["normals"], d["fpfh"], digest)
    else:
        model = _build_model_cloud(mesh_path, config, digest)
        if use_disk_cache:
            disk.parent.mkdir(parents=True, exist_ok=True)
            tmp = disk.with_suffix(".tmp.npz")
            np.savez(tmp, points=model.points, normals=model.normals, fpfh=model.fpfh)
            tmp.replace(disk)
    _MODEL_CACHE[key] = model
    return model


def _build_model_cloud(mesh_path: Path, config: RegistrationConfig, digest: str
                       ) -> ModelCloud:
    import trimesh

    mesh = trimesh.load(mesh_path, force="mesh")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise DexdrakeError(f"{mesh_path} holds no triangle mesh")
    v = config.voxel
    count = int(np.clip(mesh.area / v**2 * config.model_samples_per_voxel_area, 2000, 200_000))
    points, face_idx = trimesh.sample.sample_surface(mesh, count, seed=config.seed)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points)))
    pcd.normals = o3d.utility.Vector3dVector(np.asarray(mesh.face_normals[face_idx]))
    pcd = pcd.voxel_down_sample(v)
    normals = np.asarray(pcd.normals)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    pcd.normals = o3d.utility.Vector3dVector(normals)
    fpfh = _reg.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=config.fpfh_radius_factor * v,
                                                  max_nn=100))
    return ModelCloud(np.asarray(pcd.points).copy(), normals.copy(),
                      np.asarray(fpfh.data).copy(), digest)


# ---------------------------------------------------------------- depth-image check

def free_space_depth(frame: RgbdFrame, background: np.ndarray, window_px: int) -> np.ndarray:
    """HxW float32 (m): per pixel, the nearest depth seen within `window_px` pixels of it; a
    background (green) pixel counts as infinitely far (the screen hides nothing), a pixel
    without depth as 0 (anything may be there)."""
    seen = np.where(background, np.inf, frame.depth * 1e-3).astype(np.float32)
    size = 2 * window_px + 1
    return cv2.erode(seen, np.ones((size, size), np.uint8))


def contradicted_fraction(T_CO: np.ndarray, model: ModelCloud, near_depth: np.ndarray,
                          intrinsics: CameraIntrinsics, margin: float) -> float:
    """The fraction of the posed model's surface that the depth image contradicts.

    Of the model points that face the camera (outward normal toward it) and project into
    the image, a point is contradicted when `near_depth` (`free_space_depth`) at its pixel
    lies more than `margin` (m) beyond it: the camera sees through to something farther, or
    only green screen, where the model says there is surface. A point behind the observed
    depth (hidden by a finger or by the object itself) or near a pixel without depth is not
    contradicted. 1 when no model point faces the camera inside the image."""
    R, t = T_CO[:3, :3], T_CO[:3, 3]
    p = model.points @ R.T + t
    facing = np.einsum("ij,ij->i", model.normals @ R.T, p) < 0
    z = p[:, 2]
    ahead = facing & (z > 1e-6)
    u = np.rint(intrinsics.fx * p[ahead, 0] / z[ahead] + intrinsics.cx).astype(np.int64)
    v = np.rint(intrinsics.fy * p[ahead, 1] / z[ahead] + intrinsics.cy).astype(np.int64)
    inside = (u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height)
    if not inside.any():
        return 1.0
    seen = near_depth[v[inside], u[inside]]
    return float(np.mean(seen > z[ahead][inside] + margin))


# ---------------------------------------------------------------- registration

@dataclass(frozen=True)
class PoseEstimate:
    """Outcome of one pose estimate; `success` False carries a human-readable `reason`."""

    success: bool
    reason: str
    X_CO: RigidTransform | None = None     # object in the camera frame
    X_WO: RigidTransform | None = None     # object in the world (when the frame has X_WC)
    fitness: float = 0.0                   # fraction of scene points on the posed model
    inlier_rmse: float = float("nan")      # m, over those inliers
    num_mask_pixels: int = 0
    num_points: int = 0                    # scene points after voxel downsampling
    elapsed_s: float = 0.0
    run_fitness: tuple[float, ...] = field(default_factory=tuple)  # per ICP-refined try
    contradicted: float = 0.0              # `contradicted_fraction` of the pose


def _cube_axes() -> np.ndarray:
    """Unit directions of a cube's 3 face, 6 edge-diagonal and 4 body-diagonal axes."""
    # One of each +-d pair: the first non-zero component positive.
    dirs = [d for d in itertools.product((-1, 0, 1), repeat=3)
            if any(d) and next(x for x in d if x) > 0]
    return np.array(dirs, float) / np.linalg.norm(dirs, axis=1, keepdims=True)


_HALF_TURN_AXES = _cube_axes()


def _refine(scene: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, T: np.ndarray,
            config: RegistrationConfig) -> tuple[float, float, np.ndarray]:
    """Coarse-to-fine point-to-plane ICP from T; returns (fitness, inlier_rmse, T)."""
    v = config.voxel
    for factor in config.icp_distance_factors:
        T = _reg.registration_icp(
            scene, target, factor * v, T, _reg.TransformationEstimationPointToPlane(),
            _reg.ICPConvergenceCriteria(max_iteration=config.icp_max_iterations),
        ).transformation
    ev = _reg.evaluate_registration(scene, target, config.fitness_distance_factor * v, T)
    return float(ev.fitness), float(ev.inlier_rmse), np.array(T)


_Try = tuple[float, float, np.ndarray, float]   # (fitness, inlier_rmse, T_OC, contradicted)


def _better(best: _Try | None, candidate: _Try) -> _Try:
    """The higher-fitness try (lower RMSE on ties)."""
    if best is None or (candidate[0], -candidate[1]) > (best[0], -best[1]):
        return candidate
    return best


@dataclass(frozen=True)
class Registration:
    """The pose `register_model` chose and how well it fits."""

    T_CO: np.ndarray                 # 4x4, the model in the camera frame
    fitness: float                   # fraction of scene points on the posed model
    inlier_rmse: float               # m, over those inliers
    contradicted: float              # fraction of its surface the frame contradicts (0: unchecked)
    num_points: int                  # scene points after voxel downsampling
    run_fitness: tuple[float, ...]   # fitness of each ICP-refined try


def register_model(points_C: np.ndarray, model: ModelCloud,
                   config: RegistrationConfig = RegistrationConfig(),
                   contradicted: Callable[[np.ndarray], float] | None = None) -> Registration:
    """Register `model` to a partial cloud seen from the camera at the origin.

    Best of `ransac_runs` RANSAC + ICP tries by fitness; below `good_fitness`, half-turn
    variants of the best-fitting try and up to `extra_runs` more RANSAC runs are tried.
    `contradicted` (X_CO 4x4 -> the fraction of the posed model's surface the frame
    contradicts, `contradicted_fraction`), if given, rules out tries above
    `max_contradicted`; when every try is ruled out, the best-fitting one is returned."""
    v = config.voxel
    scene = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_C)).voxel_down_sample(v)
    n = len(scene.points)
    if n < config.min_points:
        return Registration(np.eye(4), 0.0, float("nan"), 0.0, n, ())
    scene.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(
        radius=config.normal_radius_factor * v, max_nn=30))
    scene.orient_normals_towards_camera_location(np.zeros(3))
    scene_fpfh = _reg.compute_fpfh_feature(scene, o3d.geometry.KDTreeSearchParamHybrid(
        radius=config.fpfh_radius_factor * v, max_nn=100))
    target, target_fpfh = model.point_cloud(), model.feature()
    ransac_d = config.ransac_distance_factor * v
    checkers = [_reg.CorrespondenceCheckerBasedOnEdgeLength(config.edge_length_ratio),
                _reg.CorrespondenceCheckerBasedOnDistance(ransac_d)]
    criteria = _reg.RANSACConvergenceCriteria(config.ransac_max_iterations,
                                              config.ransac_confidence)
    best: _Try | None = None   # the best try the frame does not contradict
    top: _Try | None = None    # the best-fitting try of all
    run_fitness: list[float] = []

    def consider(T: np.ndarray) -> _Try:
        nonlocal best, top
        fitness, rmse, T_OC = _refine(scene, target, T, config)
        c = 0.0 if contradicted is None else contradicted(np.linalg.inv(T_OC))
        candidate = (fitness, rmse, T_OC, c)
        run_fitness.append(fitness)
        top = _better(top, candidate)
        if c <= config.max_contradicted:
            best = _better(best, candidate)
        return candidate

    def ransac_run(run: int) -> _Try:
        o3d.utility.random.seed(config.seed + run)
        coarse = _reg.registration_ransac_based_on_feature_matching(
            scene, target, scene_fpfh, target_fpfh, config.mutual_filter, ransac_d,
            _reg.TransformationEstimationPointToPoint(False), config.ransac_n,
            checkers, criteria)
        return consider(coarse.transformation)

    def half_turns(start: np.ndarray) -> None:
        # Man-made shapes often lock onto a near-symmetric twin (a flipped plate, an L turned
        # about its diagonal): try half turns of a pose about the 13 symmetry axes of a
        # cube in the model frame, through the observed centre (cheap: ICP only).
        c = (start @ np.append(np.asarray(scene.points).mean(axis=0), 1.0))[:3]
        for axis in _HALF_TURN_AXES:
            F = np.eye(4)
            F[:3, :3] = 2.0 * np.outer(axis, axis) - np.eye(3)   # rotation by pi
            F[:3, 3] = c - F[:3, :3] @ c
            consider(F @ start)

    def good() -> bool:
        return best is not None and best[0] >= config.good_fitness

    for run in range(config.ransac_runs):
        ransac_run(run)
    if config.try_flips and not good():
        half_turns(top[2])
    for run in range(config.ransac_runs, config.ransac_runs + config.extra_runs):
        if good():
            break
        candidate = ransac_run(run)
        if config.try_flips and (candidate is top or candidate is best) and not good():
            half_turns(candidate[2])
    fitness, rmse, T_OC, c = best if best is not None else top
    return Registration(np.linalg.inv(T_OC), fitness, rmse, c, n, tuple(run_fitness))


def model_symmetries(points: np.ndarray, tolerance: float) -> np.ndarray:
    """The half turns (4x4 in the model frame, about the cloud's centre; the identity first)
    that map the model cloud onto itself: nearest-neighbour distances below `tolerance` on
    average and below twice it for 99 % of the points (a handle is no symmetry): twins that
    registration cannot tell apart (a can upside down)."""
    tree = cKDTree(points)
    c = points.mean(axis=0)
    out = [np.eye(4)]
    for axis in _HALF_TURN_AXES:
        F = np.eye(4)
        F[:3, :3] = 2.0 * np.outer(axis, axis) - np.eye(3)
        F[:3, 3] = c - F[:3, :3] @ c
        d = tree.query(points @ F[:3, :3].T + F[:3, 3])[0]
        if d.mean() < tolerance and np.percentile(d, 99) < 2 * tolerance:
            out.append(F)
    return np.array(out)


def nearest_twin(X_WO: RigidTransform, symmetries: np.ndarray, prior: RigidTransform | None
                 ) -> RigidTransform:
    """Of the poses X_WO * S (S in `symmetries`), the one whose rotation is nearest the
    prior's or, without a prior, the most upright one (object z nearest world z: library
    objects start at rest upright); ties keep the first (X_WO itself)."""
    twins = X_WO.GetAsMatrix4() @ symmetries
    if prior is None:
        score = -twins[:, 2, 2]
    else:
        score = np.linalg.norm(twins[:, :3, :3] - prior.rotation().matrix(), axis=(1, 2))
    return RigidTransform(twins[int(np.argmin(score + 1e-9 * np.arange(len(twins))))])


class ObjectPoseEstimator:
    """Segment -> back-project -> register one known CAD mesh; failures become results.
    Of the model's symmetric twins (`model_symmetries`) the pose nearest a prior is reported
    (`nearest_twin`), so that a symmetric object does not flip between estimates; `track`
    follows a pose from frame to frame."""

    def __init__(self, mesh_path: str | Path,
                 segmentation: GreenScreenConfig = GreenScreenConfig(),
                 registration: RegistrationConfig = RegistrationConfig(),
                 tracking: TrackingConfig = TrackingConfig()):
        self.mesh_path = Path(mesh_path)
        self.segmentation = segmentation
        self.registration = registration
        self.tracking = tracking
        self.model = model_cloud(self.mesh_path, registration)
        self.symmetries = model_symmetries(self.model.points, 0.5 * registration.voxel)
        self._target = self.model.point_cloud()
        self._centre = self.model.points.mean(axis=0)
        self._radius = float(np.linalg.norm(self.model.points - self._centre, axis=1).max())

    def object_points(self, frame: RgbdFrame) -> tuple[np.ndarray, np.ndarray]:
        """(mask, points in the camera frame) of the object's pixels in a validated frame."""
        validate_frame(frame)
        mask = segment_object(frame, self.segmentation)
        return mask, backproject(frame.depth, frame.intrinsics, mask)

    def track(self, frame: RgbdFrame, prior: RigidTransform,
              observed: tuple[np.ndarray, np.ndarray] | None = None) -> PoseEstimate:
        """The object pose in `frame` refined from `prior` (the last pose, in the world;
        `frame` must carry X_WC) by point-to-plane ICP (`tracking`); lost tracking gives
        success=False with the reason. `observed`: the frame's `object_points`, if known."""
        t0, cfg = time.perf_counter(), self.tracking
        try:
            if frame.X_WC is None:
                raise FrameError("tracking needs the camera pose (frame.X_WC)")
            mask, points_C = self.object_points(frame) if observed is None else observed
            T_CO = (frame.X_WC.inverse() @ prior).GetAsMatrix4()
            centre = T_CO[:3, :3] @ self._centre + T_CO[:3, 3]
            near = points_C[np.linalg.norm(points_C - centre, axis=1) < self._radius + cfg.crop_margin]
            scene = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(near)).voxel_down_sample(cfg.voxel)
            n = len(scene.points)
            if n < cfg.min_points:
                return PoseEstimate(False, f"tracking lost: {n} points near the last pose (< "
                                    f"{cfg.min_points})", num_points=n, elapsed_s=time.perf_counter() - t0)
            target = self._target
            T_OC = np.linalg.inv(T_CO)
            for d in cfg.icp_distances:
                T_OC = _reg.registration_icp(
                    scene, target, d, T_OC, _reg.TransformationEstimationPointToPlane(),
                    _reg.ICPConvergenceCriteria(max_iteration=cfg.icp_max_iterations)).transformation
            ev = _reg.evaluate_registration(scene, target, cfg.fitness_distance, T_OC)
            T_CO = np.linalg.inv(T_OC)
            contradicted = self.depth_check(frame, mask)(T_CO)
        except Exception as e:  # noqa: BLE001 - the contract: failures are results
            return PoseEstimate(False, f"perception error: {type(e).__name__}: {e}",
                                elapsed_s=time.perf_counter() - t0)
        fitness, inliers = float(ev.fitness), len(ev.correspondence_set)
        limit, reason = self.registration.max_contradicted, ""
        if fitness < cfg.min_fitness or inliers < cfg.min_points:
            reason = (f"tracking lost: fitness {fitness:.2f} (min {cfg.min_fitness:.2f}), "
                      f"{inliers} points on the model (min {cfg.min_points})")
        elif contradicted > limit:
            reason = (f"tracking lost: the depth image contradicts the tracked pose on "
                      f"{contradicted:.0%} of its visible surface (max {limit:.0%})")
        X_CO = RigidTransform(T_CO)
        return PoseEstimate(not reason, reason, X_CO, frame.X_WC @ X_CO, fitness, float(ev.inlier_rmse),
                            num_points=n, elapsed_s=time.perf_counter() - t0, contradicted=contradicted)

    def depth_check(self, frame: RgbdFrame, mask: np.ndarray | None = None
                    ) -> Callable[[np.ndarray], float]:
        """X_CO (4x4) -> the fraction of the model's surface at that pose that `frame`
        contradicts (`contradicted_fraction` with the `registration` settings; the window
        in pixels at the median depth of `mask`, the frame's object pixels, segmented when
        not given)."""
        cfg = self.registration
        if mask is None:
            mask = segment_object(frame, self.segmentation)
        z = float(np.median(frame.depth[mask])) * 1e-3 if mask.any() else np.inf
        window_px = round(cfg.free_space_window_factor * cfg.voxel * frame.intrinsics.fx / z)
        near = free_space_depth(frame, green_pixels(frame, self.segmentation), window_px)
        margin = cfg.free_space_margin_factor * cfg.voxel
        return lambda T_CO: contradicted_fraction(T_CO, self.model, near, frame.intrinsics, margin)

    def estimate(self, frame: RgbdFrame, prior: RigidTransform | None = None) -> PoseEstimate:
        """The object pose in `frame` (the twin nearest `prior`, a previous pose in the
        world, or the upright one); invalid input, a poor fit or a pose the depth image
        contradicts (`contradicted_fraction`) gives success=False."""
        t0, cfg = time.perf_counter(), self.registration
        try:
            mask, points_C = self.object_points(frame)
            n_mask = int(mask.sum())
            if len(points_C) < cfg.min_points:
                return PoseEstimate(False, f"too few object pixels ({n_mask}) after "
                                    "segmentation", num_mask_pixels=n_mask,
                                    elapsed_s=time.perf_counter() - t0)
            reg = register_model(points_C, self.model, cfg, self.depth_check(frame, mask))
        except Exception as e:  # noqa: BLE001 - the contract: failures are results
            return PoseEstimate(False, f"perception error: {type(e).__name__}: {e}",
                                elapsed_s=time.perf_counter() - t0)
        elapsed = time.perf_counter() - t0
        if reg.num_points < cfg.min_points:
            return PoseEstimate(False, f"too few points after downsampling ({reg.num_points} < "
                                f"{cfg.min_points})", num_mask_pixels=n_mask,
                                num_points=reg.num_points, elapsed_s=elapsed)
        X_CO = RigidTransform(reg.T_CO)
        X_WO = None
        if frame.X_WC is not None:
            X_WO = nearest_twin(frame.X_WC @ X_CO, self.symmetries, prior)
            X_CO = frame.X_WC.inverse() @ X_WO
        reason = ""
        if reg.fitness < cfg.min_fitness:
            reason = f"low fitness {reg.fitness:.2f} < {cfg.min_fitness:.2f}"
        elif reg.contradicted > cfg.max_contradicted:
            reason = (f"the depth image contradicts the pose: {reg.contradicted:.0%} of its visible "
                      f"surface where the camera sees past it (max {cfg.max_contradicted:.0%})")
        return PoseEstimate(not reason, reason, X_CO, X_WO, reg.fitness, reg.inlier_rmse, n_mask,
                            reg.num_points, elapsed, reg.run_fitness, reg.contradicted)
