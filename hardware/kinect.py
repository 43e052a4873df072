"""Kinect-style RGB-D camera sources: a real Azure Kinect, a recorded sequence, a Drake render.

Every source yields `RgbdFrame`s with one convention:
- `color`: H x W x 3 uint8, **RGB** channel order;
- `depth`: H x W uint16 millimetres **aligned to the colour grid** (0 = no data);
- `intrinsics`: pinhole fx, fy, cx, cy of that grid in pixels, OpenCV/Drake convention
  (pixel (u, v) has its centre at integer coordinates, camera +z forward, +x right, +y down);
- `timestamp` in seconds; `X_WC` the camera pose in the world when known.

Recorded-sequence format (`save_sequence` / `RecordedSequence`): a folder of
`frame_000000.npz`, `frame_000001.npz`, ... (np.savez_compressed), each with keys
`color` (H,W,3 uint8 RGB), `depth` (H,W uint16 mm), `intrinsics` (float64 [fx, fy, cx, cy]),
`timestamp` (float64 scalar, s) and optionally `X_WC` (float64 4x4 homogeneous matrix).
A single `.npz` file of that layout is a one-frame sequence.
"""

from __future__ import annotations

import math
import threading
import time
import zipfile
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydrake.math import RigidTransform

from dexdrake.errors import DexdrakeError, UnknownNameError
from dexdrake.paths import cache_dir


class FrameError(DexdrakeError, ValueError):
    """An RGB-D frame or its intrinsics is malformed (shape, dtype, values)."""


def drake_camera_info(k: "CameraIntrinsics"):
    """Drake's CameraInfo for intrinsics `k`: the principal point moves by half a pixel
    (Drake measures from the top-left corner of pixel (0, 0), OpenCV from its centre).
    Without it a rendered image is back-projected half a pixel off, a ~1.3 mm shift at
    0.6 m on 640x360 (scripts/bench_perception.py --noise none)."""
    from pydrake.systems.sensors import CameraInfo

    return CameraInfo(k.width, k.height, k.fx, k.fy, k.cx + 0.5, k.cy + 0.5)


class EndOfSequence(DexdrakeError):
    """A finite camera source has no more frames."""


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of an image grid in the OpenCV / Azure Kinect convention: pixel
    (u, v) is centred on the coordinates (u, v). Drake's CameraInfo puts the centre of
    pixel (u, v) at (u + 0.5, v + 0.5) (its origin is the image's top-left corner): see
    `drake_camera_info`."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise FrameError(f"image size must be positive, got {self.width}x{self.height}")
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(math.isfinite(v) for v in values):
            raise FrameError(f"intrinsics must be finite, got fx, fy, cx, cy = {values}")
        if self.fx <= 0 or self.fy <= 0:
            raise FrameError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not (0 <= self.cx < self.width and 0 <= self.cy < self.height):
            raise FrameError(
                f"principal point ({self.cx}, {self.cy}) lies outside the "
                f"{self.width}x{self.height} image"
            )

    def scaled(self, width: int, height: int) -> CameraIntrinsics:
        """The same lens on a resized grid (pixel centres kept consistent)."""
        sx, sy = width / self.width, height / self.height
        return CameraIntrinsics(
            width, height, self.fx * sx, self.fy * sy,
            (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5,
        )

    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


#: One real Azure Kinect DK's colour camera at 1280x720 (specs/kinect.md).
KINECT_COLOR_720P = CameraIntrinsics(1280, 720, 611.8, 611.9, 639.3, 365.9)


@dataclass(frozen=True, eq=False)
class RgbdFrame:
    """One validated RGB-D frame (see the module docstring for the conventions)."""

    color: np.ndarray
    depth: np.ndarray
    intrinsics: CameraIntrinsics
    timestamp: float
    X_WC: RigidTransform | None = None

    def __post_init__(self) -> None:
        validate_frame(self)


def validate_frame(frame: RgbdFrame) -> None:
    """Raise FrameError unless shapes, dtypes, intrinsics and timestamp are consistent."""
    if not isinstance(frame, RgbdFrame):
        raise FrameError(f"expected an RgbdFrame, got {type(frame).__name__}")
    color, depth, k = frame.color, frame.depth, frame.intrinsics
    if not isinstance(color, np.ndarray) or color.dtype != np.uint8 or color.ndim != 3 \
            or color.shape[2] != 3:
        raise FrameError(
            f"color must be an HxWx3 uint8 array, got {_describe(color)}"
        )
    if not isinstance(depth, np.ndarray) or depth.dtype != np.uint16 or depth.ndim != 2:
        raise FrameError(f"depth must be an HxW uint16 array (mm), got {_describe(depth)}")
    if depth.shape != color.shape[:2]:
        raise FrameError(
            f"depth {depth.shape} is not aligned to the colour grid {color.shape[:2]}"
        )
    if not isinstance(k, CameraIntrinsics):
        raise FrameError(f"intrinsics must be CameraIntrinsics, got {type(k).__name__}")
    if (k.height, k.width) != depth.shape:
        raise FrameError(
            f"intrinsics are for {k.width}x{k.height} but the images are "
            f"{depth.shape[1]}x{depth.shape[0]}"
        )
    if not isinstance(frame.timestamp, (int, float)) or not math.isfinite(frame.timestamp):
        raise FrameError(f"timestamp must be a finite number, got {frame.timestamp!r}")
    if frame.X_WC is not None and not isinstance(frame.X_WC, RigidTransform):
        raise FrameError(f"X_WC must be a RigidTransform or None, got {type(frame.X_WC)}")


def _describe(a: object) -> str:
    if isinstance(a, np.ndarray):
        return f"shape {a.shape} dtype {a.dtype}"
    return type(a).__name__


class CameraSource(ABC):
    """A source of RgbdFrames; iterate it or call `read()`; use as a context manager."""

    @abstractmethod
    def read(self) -> RgbdFrame:
        """The next frame; raises EndOfSequence when a finite source is exhausted."""

    def close(self) -> None:
        """Release the device or files (no-op by default)."""

    def __iter__(self) -> Iterator[RgbdFrame]:
        while True:
            try:
                yield self.read()
            except EndOfSequence:
                return

    def __enter__(self) -> CameraSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------- recorded sequences

def save_frame(frame: RgbdFrame, path: str | Path) -> Path:
    """Write one frame as a compressed .npz in the recorded-sequence layout."""
    k = frame.intrinsics
    arrays: dict[str, np.ndarray] = {
        "color": frame.color,
        "depth": frame.depth,
        "intrinsics": np.array([k.fx, k.fy, k.cx, k.cy], dtype=np.float64),
        "timestamp": np.float64(frame.timestamp),
    }
    if frame.X_WC is not None:
        arrays["X_WC"] = frame.X_WC.GetAsMatrix4()
    path = Path(path)
    np.savez_compressed(path, **arrays)
    return path


def load_frame(path: str | Path) -> RgbdFrame:
    """Read and validate one frame written by `save_frame`."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = {"color", "depth", "intrinsics", "timestamp"} - set(data.files)
            if missing:
                raise FrameError(f"{path}: missing arrays {sorted(missing)}")
            color, depth = data["color"], data["depth"]
            fx, fy, cx, cy = (float(v) for v in data["intrinsics"].reshape(4))
            X_WC = RigidTransform(data["X_WC"]) if "X_WC" in data.files else None
            timestamp = float(data["timestamp"])
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as e:
        if isinstance(e, FrameError):
            raise
        raise FrameError(f"{path}: not a readable RGB-D frame ({e})") from e
    if depth.ndim != 2:
        raise FrameError(f"{path}: depth must be 2-D, got shape {depth.shape}")
    k = CameraIntrinsics(depth.shape[1], depth.shape[0], fx, fy, cx, cy)
    return RgbdFrame(color, depth, k, timestamp, X_WC)


def save_sequence(frames: Iterable[RgbdFrame], folder: str | Path) -> int:
    """Write frames as folder/frame_%06d.npz; returns how many were written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    n = 0
    for n, frame in enumerate(frames, start=1):
        save_frame(frame, folder / f"frame_{n - 1:06d}.npz")
    return n


class RecordedSequence(CameraSource):
    """Plays back a folder (or single file) written by `save_sequence` / `save_frame`."""

    def __init__(self, path: str | Path, loop: bool = False):
        path = Path(path)
        if path.is_dir():
            self.files = sorted(path.glob("frame_*.npz"))
        elif path.is_file():
            self.files = [path]
        else:
            raise DexdrakeError(f"recorded sequence {path} does not exist")
        if not self.files:
            raise DexdrakeError(f"recorded sequence {path} holds no frame_*.npz files")
        self.loop = loop
        self._next = 0

    def __len__(self) -> int:
        return len(self.files)

    def read(self) -> RgbdFrame:
        """The next recorded frame (validated on load)."""
        if self._next >= len(self.files):
            if not self.loop:
                raise EndOfSequence(f"all {len(self.files)} recorded frames were read")
            self._next = 0
        frame = load_frame(self.files[self._next])
        self._next += 1
        return frame


# ---------------------------------------------------------------- Azure Kinect device

class K4ADevice(CameraSource):
    """An Azure Kinect DK through pyk4a: BGRA colour -> RGB, `transformed_depth` on the
    colour grid, colour intrinsics read from the device calibration."""

    def __init__(
        self,
        device_id: int = 0,
        color_resolution: str = "RES_720P",
        depth_mode: str = "NFOV_UNBINNED",
        X_WC: RigidTransform | None = None,
        warmup_frames: int = 30,
        timeout_ms: int = 1000,
    ):
        try:
            import pyk4a
        except ImportError as e:
            raise DexdrakeError(
                "K4ADevice needs the `pyk4a` package and Microsoft's Azure Kinect SDK "
                "(libk4a); install both, or use RecordedSequence / DrakeRenderedCamera"
            ) from e
        self._pyk4a = pyk4a
        try:
            resolution = getattr(pyk4a.ColorResolution, color_resolution)
            mode = getattr(pyk4a.DepthMode, depth_mode)
        except AttributeError as e:
            raise DexdrakeError(f"unknown pyk4a colour resolution or depth mode: {e}") from e
        config = pyk4a.Config(
            color_resolution=resolution,
            depth_mode=mode,
            color_format=pyk4a.ImageFormat.COLOR_BGRA32,
            synchronized_images_only=True,
        )
        self._k4a = pyk4a.PyK4A(config, device_id=device_id)
        self._k4a.start()
        self._timeout_ms = timeout_ms
        self.X_WC = X_WC
        self.intrinsics: CameraIntrinsics | None = None
        try:
            self._K = np.asarray(
                self._k4a.calibration.get_camera_matrix(pyk4a.CalibrationType.COLOR))
            for _ in range(warmup_frames):  # the depth sensor needs a warm-up (specs/kinect.md)
                self._k4a.get_capture(timeout=timeout_ms)
        except BaseException:
            self._k4a.stop()
            raise

    def read(self) -> RgbdFrame:
        """Capture one synchronised frame; raises FrameError on a malformed capture."""
        cap = self._k4a.get_capture(timeout=self._timeout_ms)
        bgra, depth = cap.color, cap.transformed_depth
        if bgra is None or depth is None:
            raise FrameError("capture lacks colour or transformed depth")
        bgra = np.asarray(bgra)
        if bgra.ndim != 3 or bgra.shape[2] != 4:
            raise FrameError(f"expected BGRA colour, got {_describe(bgra)}")
        if self.intrinsics is None:
            K = self._K
            self.intrinsics = CameraIntrinsics(
                bgra.shape[1], bgra.shape[0], float(K[0, 0]), float(K[1, 1]),
                float(K[0, 2]), float(K[1, 2]),
            )
        rgb = np.ascontiguousarray(bgra[:, :, 2::-1])
        return RgbdFrame(
            rgb, np.asarray(depth), self.intrinsics,
            cap.color_timestamp_usec * 1e-6, self.X_WC,
        )

    def close(self) -> None:
        """Stop the device."""
        self._k4a.stop()


class LatestFrame(CameraSource):
    """A live source read continuously in a thread, keeping its newest frame: `read()` returns
    it at once (a K4A capture otherwise blocks its caller, a control loop, up to a frame
    period), the same frame again until a newer one arrives. Watchdog: FrameError when the
    newest frame is older than `timeout_s` (a stalled or unplugged camera; the thread's
    last error, if it had one); before the first frame `read()` waits up to `timeout_s`."""

    def __init__(self, source: CameraSource, timeout_s: float = 0.5):
        if not timeout_s > 0:
            raise DexdrakeError(f"timeout_s must be positive, got {timeout_s}")
        self._source, self._timeout = source, timeout_s
        self._cond = threading.Condition()
        self._frame: RgbdFrame | None = None
        self._received = time.monotonic()  # when the newest frame (or the start) came
        self._error: Exception | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="camera-reader", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                frame, error = self._source.read(), None
            except Exception as err:  # noqa: BLE001 - reported by read() when frames stop
                frame, error = None, err
            with self._cond:
                self._error = error
                if frame is not None:
                    self._frame, self._received = frame, time.monotonic()
                    self._cond.notify_all()
            if error is not None:
                self._stop.wait(0.01)

    def read(self) -> RgbdFrame:
        """The newest frame; FrameError when it is older than `timeout_s`."""
        with self._cond:
            if self._frame is None:
                self._cond.wait_for(lambda: self._frame is not None, self._timeout)
            age = time.monotonic() - self._received
            if self._frame is None or age > self._timeout:
                why = f" (last error: {self._error})" if self._error is not None else ""
                raise FrameError(f"no camera frame for {age:.2f} s (timeout {self._timeout} s){why}")
            return self._frame

    def close(self) -> None:
        """Stop the reading thread, then the source."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self._source.close()


# ---------------------------------------------------------------- Drake rendering

@dataclass(frozen=True)
class DepthNoiseModel:
    """Kinect-like depth noise (specs/kinect.md: systematic < 11 mm + 0.1 % of distance,
    random sigma <= 17 mm), applied in millimetres to a rendered depth image.

    depth_out = d + bias_mm + bias_fraction * d + N(0, sigma(d)),
    sigma(d) = min(sigma0_mm + sigma2_mm_per_m2 * d_m**2, sigma_max_mm);
    then each valid pixel is dropped (set to 0) with probability `dropout`, pixels at depth
    edges (3x3 depth spread above `edge_jump_mm`) are dropped, and depths outside
    [min_range_m, max_range_m] are 0.
    """

    bias_mm: float = 2.0
    bias_fraction: float = 0.001
    sigma0_mm: float = 1.0
    sigma2_mm_per_m2: float = 1.5
    sigma_max_mm: float = 17.0
    dropout: float = 0.01
    edge_jump_mm: float = 30.0
    min_range_m: float = 0.25
    max_range_m: float = 3.86

    def __post_init__(self) -> None:
        if not 0 <= self.dropout <= 1:
            raise DexdrakeError(f"dropout must be a probability, got {self.dropout}")
        if self.sigma0_mm < 0 or self.sigma2_mm_per_m2 < 0 or self.sigma_max_mm < 0:
            raise DexdrakeError("noise sigmas must be >= 0")
        if not 0 <= self.min_range_m < self.max_range_m:
            raise DexdrakeError("need 0 <= min_range_m < max_range_m")

    def apply(self, depth_m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Noisy uint16 millimetre depth from a float depth in metres (inf/nan/0 = none)."""
        d = np.where(np.isfinite(depth_m), depth_m, 0.0).astype(np.float64)
        valid = (d >= self.min_range_m) & (d <= self.max_range_m)
        mm = d * 1000.0
        sigma = np.minimum(self.sigma0_mm + self.sigma2_mm_per_m2 * d**2, self.sigma_max_mm)
        noisy = mm + self.bias_mm + self.bias_fraction * mm + rng.normal(size=d.shape) * sigma
        valid &= rng.random(d.shape) >= self.dropout
        if self.edge_jump_mm > 0:
            valid &= _local_spread(np.where(d > 0, mm, 0.0)) <= self.edge_jump_mm
        out = np.where(valid, np.clip(np.rint(noisy), 1, 65535), 0)
        return out.astype(np.uint16)


def _local_spread(mm: np.ndarray) -> np.ndarray:
    """Max minus min over each pixel's 3x3 neighbourhood (edge-replicated)."""
    import cv2

    kernel = np.ones((3, 3), np.uint8)
    img = mm.astype(np.float32)
    return cv2.dilate(img, kernel) - cv2.erode(img, kernel)


def depth_m_to_mm(depth_m: np.ndarray) -> np.ndarray:
    """Exact (noise-free) conversion: metres float -> uint16 mm, non-finite/<=0 -> 0."""
    d = np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, 0.0)
    return np.clip(np.rint(d * 1000.0), 0, 65535).astype(np.uint16)


@dataclass(frozen=True)
class GreenScreenScene:
    """The rendered set: a green table top at z = 0 and a green wall behind it."""

    table_size: tuple[float, float] = (1.2, 2.4)  # wide enough to fill the frame's far corners
    wall_distance: float = 0.6     # wall plane at x = +wall_distance, facing -x
    wall_height: float = 1.2
    green_rgba: tuple[float, float, float, float] = (0.15, 0.65, 0.2, 1.0)


def renderable_mesh(mesh_path: Path) -> Path:
    """`mesh_path` itself if it is an OBJ with normals, else a cached copy with vertex
    normals (Drake's VTK renderer refuses OBJ files without normals)."""
    import hashlib

    import trimesh

    data = mesh_path.read_bytes()
    if mesh_path.suffix.lower() == ".obj" and b"\nvn " in data:
        return mesh_path
    out = cache_dir() / "render_meshes" / f"{hashlib.sha256(data).hexdigest()[:24]}.obj"
    if not out.is_file():
        mesh = trimesh.load(mesh_path, force="mesh")
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(".tmp.obj")
        tmp.write_text(trimesh.exchange.obj.export_obj(mesh, include_normals=True))
        tmp.replace(out)
    return out


class DrakeRenderedCamera(CameraSource):
    """A Drake RgbdSensor (RenderEngineVtk, EGL, headless) looking at a green-screen scene
    with mesh objects whose poses you set; Kinect colour intrinsics scaled to (width, height)
    and a seeded `DepthNoiseModel` (None = exact depth)."""

    def __init__(
        self,
        X_WC: RigidTransform,
        objects: Mapping[str, str | Path],
        width: int = 640,
        height: int = 360,
        noise: DepthNoiseModel | None = DepthNoiseModel(),
        seed: int = 0,
        scene: GreenScreenScene = GreenScreenScene(),
        object_rgba: tuple[float, float, float, float] = (0.75, 0.3, 0.2, 1.0),
        backend: str = "EGL",
    ):
        from pydrake.geometry import (
            Box, ClippingRange, ColorRenderCamera, DepthRange, DepthRenderCamera,
            MakeRenderEngineVtk, Mesh, RenderCameraCore, RenderEngineVtkParams,
        )
        from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
        from pydrake.multibody.tree import SpatialInertia
        from pydrake.systems.framework import DiagramBuilder
        from pydrake.systems.sensors import RgbdSensor

        if not isinstance(X_WC, RigidTransform):
            raise DexdrakeError(f"X_WC must be a RigidTransform, got {type(X_WC).__name__}")
        self.intrinsics = KINECT_COLOR_720P.scaled(width, height)
        self.X_WC = X_WC
        self.noise = noise
        self._rng = np.random.default_rng(seed)
        self._time = 0.0

        builder = DiagramBuilder()
        plant, scene_graph = AddMultibodyPlantSceneGraph(builder, 0.0)
        params = RenderEngineVtkParams()
        params.backend = backend
        params.default_clear_color = np.array([0.0, 0.0, 0.0])
        scene_graph.AddRenderer("vtk", MakeRenderEngineVtk(params))
        green = np.array(scene.green_rgba)
        sx, sy = scene.table_size
        world = plant.world_body()
        plant.RegisterVisualGeometry(
            world, RigidTransform([0, 0, -0.01]), Box(sx, sy, 0.02), "table", green)
        plant.RegisterVisualGeometry(
            world, RigidTransform([scene.wall_distance + 0.01, 0, scene.wall_height / 2]),
            Box(0.02, sy, scene.wall_height), "wall", green)
        self._objects: dict[str, object] = {}  # name -> RigidBody
        for name, mesh_path in objects.items():
            mesh_path = Path(mesh_path)
            if not mesh_path.is_file():
                raise DexdrakeError(f"object {name!r}: mesh {mesh_path} does not exist")
            body = plant.AddRigidBody(name, SpatialInertia.SolidSphereWithMass(0.5, 0.05))
            plant.RegisterVisualGeometry(
                body, RigidTransform(), Mesh(str(renderable_mesh(mesh_path))), name,
                np.array(object_rgba))
            self._objects[name] = body
        plant.Finalize()

        core = RenderCameraCore("vtk", drake_camera_info(self.intrinsics),
                                ClippingRange(0.05, 10.0), RigidTransform())
        self._sensor = builder.AddSystem(RgbdSensor(
            scene_graph.world_frame_id(), X_WC, ColorRenderCamera(core, False),
            DepthRenderCamera(core, DepthRange(0.1, 9.0))))
        builder.Connect(scene_graph.get_query_output_port(),
                        self._sensor.query_object_input_port())
        self._plant = plant
        self._diagram = builder.Build()
        self._context = self._diagram.CreateDefaultContext()
        self._plant_context = plant.GetMyContextFromRoot(self._context)
        self._sensor_context = self._sensor.GetMyContextFromRoot(self._context)
        for name in self._objects:  # park every object far below the table
            self.hide_object(name)

    def set_object_pose(self, name: str, X_WO: RigidTransform) -> None:
        """Place object `name` (its mesh frame) at X_WO in the world."""
        if name not in self._objects:
            raise UnknownNameError("rendered object", name, self._objects)
        self._plant.SetFreeBodyPose(self._plant_context, self._objects[name], X_WO)

    def hide_object(self, name: str) -> None:
        """Move object `name` out of view."""
        self.set_object_pose(name, RigidTransform([0, 0, -50.0]))

    def render_depth_m(self) -> np.ndarray:
        """The exact rendered depth in metres (H x W float32; inf = nothing)."""
        img = self._sensor.depth_image_32F_output_port().Eval(self._sensor_context)
        return np.array(img.data)[:, :, 0]

    def warm_up(self) -> None:
        """Render colour and depth once at the current object poses, drawing no noise: VTK
        sets itself up on the first render (0.5-1 s that holds the interpreter)."""
        self._sensor.color_image_output_port().Eval(self._sensor_context)
        self.render_depth_m()

    def read(self) -> RgbdFrame:
        """Render one frame at the current object poses (timestamps advance by 1/30 s)."""
        rgba = self._sensor.color_image_output_port().Eval(self._sensor_context)
        color = np.ascontiguousarray(np.array(rgba.data)[:, :, :3])
        depth_m = self.render_depth_m()
        if self.noise is None:
            depth = depth_m_to_mm(depth_m)
        else:
            depth = self.noise.apply(depth_m, self._rng)
        frame = RgbdFrame(color, depth, self.intrinsics, self._time, self.X_WC)
        self._time += 1.0 / 30.0
        return frame


def look_at(eye: Iterable[float], target: Iterable[float],
            up: Iterable[float] = (0.0, 0.0, 1.0)) -> RigidTransform:
    """Camera pose X_WC (camera +z toward target, +y image-down) from an eye point."""
    from pydrake.math import RotationMatrix

    eye_v, target_v, up_v = (np.asarray(v, dtype=float) for v in (eye, target, up))
    z = target_v - eye_v
    if np.linalg.norm(z) < 1e-9:
        raise DexdrakeError("look_at: eye and target coincide")
    z /= np.linalg.norm(z)
    x = np.cross(z, up_v)
    if np.linalg.norm(x) < 1e-9:
        raise DexdrakeError("look_at: viewing direction is parallel to `up`")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return RigidTransform(RotationMatrix(np.column_stack([x, y, z])), eye_v)
