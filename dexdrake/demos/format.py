"""The human grasp demonstration format (version 1), stored as one .npz per demo.

Arrays (T = number of frames):
    format_version  int scalar, currently 1
    keypoints       (T, 21, 3) float  right-hand keypoints, MediaPipe order, metres, world frame
                    (0 wrist; 1-4 thumb CMC, MCP, IP, tip; 5-8 index MCP, PIP, DIP, tip;
                    9-12 middle; 13-16 ring; 17-20 little)
    time            (T,) float        seconds, strictly increasing
    object_name     str scalar        name in the object library ("" if unknown)
    object_pos      (T, 3) float      object frame origin in the world, metres
    object_quat     (T, 4) float      object orientation in the world, unit quaternion w, x, y, z
    meta            str scalar        JSON: subject, fps, source, trim (see DemoMeta)
Optional MANO parameters (all three or none):
    mano_pose       (T, 48)  global orientation (3) + 15 joint axis-angles (45)
    mano_trans      (T, 3)
    mano_betas      (10,)
The world frame is z-up with the table top at z = 0.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from dexdrake.errors import DexdrakeError
from dexdrake.npz import open_npz

FORMAT_VERSION = 1
NUM_KEYPOINTS = 21
_REQUIRED = ("format_version", "keypoints", "time", "object_name", "object_pos", "object_quat",
             "meta")
_MANO = ("mano_pose", "mano_trans", "mano_betas")


class DemoFormatError(DexdrakeError):
    """A demo file or array set that does not follow the demo format."""


@dataclass
class TrimInfo:
    """Which frames of the source sequence were kept, and why."""

    start_frame: int = 0  # first kept frame in the source sequence
    end_frame: int = -1  # last kept frame (inclusive); -1 = untrimmed
    source_frames: int = 0  # frames in the source sequence
    rule: str = ""  # e.g. "hand 0.10 m from object .. object lifted 0.04 m"


@dataclass
class DemoMeta:
    subject: str = ""
    fps: float = 30.0
    source: str = ""  # "synthetic", "grab", "keypoints:<file>", ...
    trim: TrimInfo = field(default_factory=TrimInfo)
    extra: dict = field(default_factory=dict)  # free-form (e.g. grasp type, seed)


@dataclass
class HumanDemo:
    keypoints: np.ndarray
    time: np.ndarray
    object_name: str
    object_pos: np.ndarray
    object_quat: np.ndarray
    meta: DemoMeta = field(default_factory=DemoMeta)
    mano_pose: np.ndarray | None = None
    mano_trans: np.ndarray | None = None
    mano_betas: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        return int(self.keypoints.shape[0])

    def validate(self) -> None:
        """Raise DemoFormatError naming the first problem found."""
        T = self.keypoints.shape[0] if np.ndim(self.keypoints) == 3 else -1
        _shape("keypoints", self.keypoints, (T, NUM_KEYPOINTS, 3))
        if T < 1:
            raise DemoFormatError("keypoints: a demo needs at least one frame")
        _shape("time", self.time, (T,))
        _shape("object_pos", self.object_pos, (T, 3))
        _shape("object_quat", self.object_quat, (T, 4))
        for name in ("keypoints", "time", "object_pos", "object_quat"):
            _finite(name, getattr(self, name))
        if T > 1 and not np.all(np.diff(self.time) > 0):
            i = int(np.argmin(np.diff(self.time) > 0))
            raise DemoFormatError(f"time: not strictly increasing at frame {i + 1}")
        norms = np.linalg.norm(self.object_quat, axis=1)
        if np.any(np.abs(norms - 1) > 1e-3):
            raise DemoFormatError(f"object_quat: not unit quaternions (norm {norms.min():.4f}"
                                  f"..{norms.max():.4f})")
        if not isinstance(self.object_name, str):
            raise DemoFormatError("object_name: must be a string")
        mano = [getattr(self, k) is not None for k in _MANO]
        if any(mano) and not all(mano):
            raise DemoFormatError("mano_*: give mano_pose, mano_trans and mano_betas together")
        if all(mano):
            _shape("mano_pose", self.mano_pose, (T, 48))
            _shape("mano_trans", self.mano_trans, (T, 3))
            _shape("mano_betas", self.mano_betas, (10,))
            for k in _MANO:
                _finite(k, getattr(self, k))
        if not self.meta.fps > 0:
            raise DemoFormatError(f"meta.fps: must be positive, got {self.meta.fps}")


def _shape(name: str, a, shape: tuple[int, ...]) -> None:
    a = np.asarray(a)
    if a.shape != shape or not np.issubdtype(a.dtype, np.number):
        raise DemoFormatError(f"{name}: expected a numeric array of shape {shape}, got "
                              f"{a.dtype} {a.shape}")


def _finite(name: str, a) -> None:
    bad = ~np.isfinite(np.asarray(a, float))
    if bad.any():
        raise DemoFormatError(f"{name}: {int(bad.sum())} NaN/Inf values "
                              f"(first at index {tuple(int(i) for i in np.argwhere(bad)[0])})")


def save_demo(demo: HumanDemo, path: str | Path) -> Path:
    """Validate `demo` and write it to `path` (.npz). Returns the path written."""
    demo.validate()
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_suffix(".npz")
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = dict(
        format_version=np.int64(FORMAT_VERSION),
        keypoints=np.asarray(demo.keypoints, np.float64),
        time=np.asarray(demo.time, np.float64),
        object_name=np.str_(demo.object_name),
        object_pos=np.asarray(demo.object_pos, np.float64),
        object_quat=np.asarray(demo.object_quat, np.float64),
        meta=np.str_(json.dumps(asdict(demo.meta))),
    )
    if demo.mano_pose is not None:
        arrays.update(mano_pose=demo.mano_pose, mano_trans=demo.mano_trans,
                      mano_betas=demo.mano_betas)
    np.savez_compressed(path, **arrays)
    return path


def is_demo_file(path: str | Path) -> bool:
    """True if `path` is an .npz archive with a `format_version` entry (a demo file)."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            return "format_version.npy" in z.namelist()
    except (OSError, zipfile.BadZipFile):
        return False


def load_demo(path: str | Path) -> HumanDemo:
    """Read and validate a demo file; raises DemoFormatError naming what is wrong."""
    path = Path(path)
    try:
        with open_npz(path) as data:
            demo = _read_demo(path, data)
    except DemoFormatError:
        raise
    except DexdrakeError as e:  # missing, damaged or truncated
        raise DemoFormatError(str(e)) from e
    try:
        demo.validate()
    except DemoFormatError as e:
        raise DemoFormatError(f"{path}: {e}") from None
    return demo


def _read_demo(path: Path, data) -> HumanDemo:
    missing = [k for k in _REQUIRED if k not in data.files]
    if missing:
        raise DemoFormatError(f"{path}: missing keys {missing}")
    version = data["format_version"]
    if version.shape != () or int(version) != FORMAT_VERSION:
        raise DemoFormatError(f"{path}: unknown format_version {version!r} "
                              f"(this dexdrake reads version {FORMAT_VERSION})")
    try:
        m = json.loads(str(data["meta"]))
        trim = TrimInfo(**m.pop("trim", {}))
        meta = DemoMeta(trim=trim, **m)
    except (ValueError, TypeError) as e:
        raise DemoFormatError(f"{path}: malformed meta ({e})") from e
    return HumanDemo(
        keypoints=data["keypoints"], time=data["time"],
        object_name=str(data["object_name"]), object_pos=data["object_pos"],
        object_quat=data["object_quat"], meta=meta,
        **{k: data[k] for k in _MANO if k in data.files},
    )
