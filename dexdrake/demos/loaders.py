"""Demo loaders: keypoint files (MediaPipe or MANO order; .npy/.npz/.pkl/.json/.csv)."""

from __future__ import annotations

import json
import pickle
import zipfile
from pathlib import Path

import numpy as np

from dexdrake.demos.format import DemoFormatError, DemoMeta, HumanDemo
from dexdrake.errors import DexdrakeError

# mediapipe[i] = mano21[MANO_TO_MEDIAPIPE[i]]; MANO's 16 joints then tips thumb..little
MANO_TO_MEDIAPIPE = np.array([0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7,
                              8, 9, 20])
ORDERS = ("mediapipe", "mano")
UNITS = ("auto", "m", "mm")
HANDS = ("right", "left")
KEYPOINT_SUFFIXES = (".npy", ".npz", ".pkl", ".pickle", ".json", ".csv")
# MediaPipe skeleton: the parent keypoint of each keypoint (the wrist is its own parent)
_PARENT = np.array([0, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19])


def _adult_bones() -> np.ndarray:
    """(20,) bone lengths (m) of keypoints 1..20 from their parents, for the adult hand of
    `human_hand` (skeletal means)."""
    from dexdrake.demos.human_hand import open_hand_keypoints

    kp = open_hand_keypoints()
    return np.linalg.norm(kp[1:] - kp[_PARENT[1:]], axis=1)


_ADULT_BONES = _adult_bones()


def reorder_keypoints(keypoints: np.ndarray, order: str) -> np.ndarray:
    """(..., 21, 3) keypoints in `order` ("mediapipe" or "mano") -> MediaPipe order."""
    kp = np.asarray(keypoints, float)
    if kp.shape[-2:] != (21, 3):
        raise DemoFormatError(f"keypoints: expected (..., 21, 3), got {kp.shape}")
    if order == "mediapipe":
        return kp
    if order == "mano":
        return kp[..., MANO_TO_MEDIAPIPE, :]
    raise DexdrakeError(f"unknown keypoint order {order!r}; valid: {', '.join(ORDERS)}")


class _ArrayUnpickler(pickle.Unpickler):
    """Loads only plain data from a pickle: numpy arrays and scalars, lists, tuples, dicts,
    numbers and strings. Any other class is refused, so a keypoint .pkl cannot run code."""

    ALLOWED = {("numpy", "ndarray"), ("numpy", "dtype"), ("_codecs", "encode"),
               ("collections", "OrderedDict")} | {
        (m, n) for m in ("numpy.core.multiarray", "numpy._core.multiarray")
        for n in ("_reconstruct", "scalar")}

    def find_class(self, module: str, name: str):
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"refused to load {module}.{name}")
        return super().find_class(module, name)


def _pick(path: Path, names: list[str], key: str | None) -> str:
    """The keypoint entry among `names` (key, 'keypoints', or the only entry)."""
    k = key or ("keypoints" if "keypoints" in names else names[0] if len(names) == 1 else None)
    if k is None or k not in names:
        raise DemoFormatError(f"{path}: name the keypoint array with --key (entries: {names})")
    return k


def _entry(path: Path, obj, key: str | None):
    return obj[_pick(path, list(obj), key)] if isinstance(obj, dict) else obj


def _json_array(obj) -> np.ndarray:
    """Nested lists, or frames of 21 {x, y, z} mappings (as many MediaPipe exporters write)."""
    if isinstance(obj, list) and obj and isinstance(obj[0], dict):
        obj = [obj]
    if isinstance(obj, list) and obj and isinstance(obj[0], list) and obj[0] \
            and isinstance(obj[0][0], dict):
        obj = [[[p.get("x"), p.get("y"), p.get("z")] for p in frame] for frame in obj]
    return np.asarray(obj, dtype=float)


def read_keypoints(path: str | Path, key: str | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """(keypoints (T, 21, 3) as stored, times (T,) or None) from a .npy, .npz, .pkl, .json
    or .csv file. CSV: one row per frame with 63 values (x, y, z of each keypoint), or 64
    with the time in seconds first; a header row is skipped. Pickles are loaded with an
    unpickler that accepts plain arrays, lists and dicts only."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in KEYPOINT_SUFFIXES:
        raise DemoFormatError(f"{path}: unsupported keypoint file type {suffix!r} "
                              f"(use {', '.join(KEYPOINT_SUFFIXES)})")
    if not path.is_file():
        raise DemoFormatError(f"{path}: no such file")
    times = None
    try:
        if suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                if not z.files:
                    raise DemoFormatError(f"{path}: the .npz archive holds no arrays")
                arr = z[_pick(path, z.files, key)]
                times = z["time"] if "time" in z.files else None
        elif suffix in (".pkl", ".pickle"):
            with open(path, "rb") as f:
                arr = _entry(path, _ArrayUnpickler(f).load(), key)
        elif suffix == ".json":
            arr = _json_array(_entry(path, json.loads(path.read_text()), key))
        else:
            arr, times = _read_csv(path)
    except DemoFormatError:
        raise
    except pickle.UnpicklingError as e:
        raise DemoFormatError(f"{path}: {e}: a keypoint pickle may hold only arrays, lists and "
                              "dicts; save the keypoints with numpy.save instead") from None
    except ValueError as e:
        if "Object arrays" in str(e):
            raise DemoFormatError(f"{path}: the keypoints are stored as Python objects, which "
                                  "dexdrake does not unpickle; save a numeric (T, 21, 3) "
                                  "array") from None
        raise DemoFormatError(f"{path}: cannot read keypoints ({e}); is the file complete? "
                              "(re-export it)") from None
    except (OSError, EOFError, zipfile.BadZipFile, TypeError, KeyError) as e:
        raise DemoFormatError(f"{path}: cannot read keypoints ({type(e).__name__}: {e}); is "
                              "the file complete? (re-export it)") from None
    arr = np.asarray(arr)
    if arr.dtype == object or not np.issubdtype(arr.dtype, np.number):
        raise DemoFormatError(f"{path}: keypoints must be numbers, got an array of {arr.dtype}; "
                              "save a numeric (T, 21, 3) array")
    if arr.shape[-2:] != (21, 3) and arr.ndim in (1, 2) and arr.shape[-1] == 63:
        arr = arr.reshape(*arr.shape[:-1], 21, 3)
    if arr.ndim == 2 and arr.shape == (21, 3):
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[1:] != (21, 3):
        raise DemoFormatError(f"{path}: expected keypoints of shape (T, 21, 3) or (T, 63), "
                              f"got {arr.shape}")
    if arr.shape[0] == 0:
        raise DemoFormatError(f"{path}: the keypoint array is empty (0 frames)")
    if times is not None and np.shape(times) != (arr.shape[0],):
        times = None
    return arr.astype(float), times


def _read_csv(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    if lines and not _numeric_row(lines[0]):
        lines = lines[1:]
    if not lines:
        raise DemoFormatError(f"{path}: the CSV file has no data rows")
    rows = np.array([[float(x) for x in ln.split(",")] for ln in lines])
    if rows.ndim != 2 or rows.shape[1] not in (63, 64):
        raise DemoFormatError(f"{path}: each CSV row needs 63 values (x, y, z of 21 keypoints) "
                              f"or 64 (time first), got {rows.shape[-1]}")
    if rows.shape[1] == 64:
        return rows[:, 1:], rows[:, 0]
    return rows, None


def _numeric_row(line: str) -> bool:
    try:
        [float(x) for x in line.split(",")]
    except ValueError:
        return False
    return True


def _hand_size(kp: np.ndarray) -> np.ndarray:
    """(T,) wrist -> middle-finger MCP distance per frame (about 0.09 m for adults)."""
    return np.linalg.norm(kp[:, 9] - kp[:, 0], axis=1)


def _bone_name(i: int) -> str:
    finger = ("thumb", "index", "middle", "ring", "little")[(i - 1) // 4]
    return f"{finger} bone {(i - 1) % 4 + 1} (keypoints {_PARENT[i]}->{i})"


def clean_keypoints(kp: np.ndarray, units: str = "auto") -> tuple[np.ndarray, list[str],
                                                                  np.ndarray]:
    """Check and convert raw (T, 21, 3) keypoints (MediaPipe order) to metres.

    Returns (keypoints in metres, notes on what was done, indices of the kept frames).
    Frames with no hand (all zeros or all NaN, as trackers write when they lose the hand)
    are dropped; every other problem raises DemoFormatError naming the fix: all frames
    empty, partial NaN, a collapsed hand, units that are neither metres nor millimetres,
    impossible bone lengths (usually a wrong --order)."""
    if units not in UNITS:
        raise DexdrakeError(f"unknown units {units!r}; valid: {', '.join(UNITS)}")
    kp = np.asarray(kp, float)
    empty = np.all((kp == 0) | np.isnan(kp), axis=(1, 2))
    notes = []
    if empty.all():
        raise DemoFormatError("every frame is empty (all keypoints zero or NaN): no hand was "
                              "tracked; check the export")
    keep = np.flatnonzero(~empty)
    if empty.any():
        notes.append(f"dropped {int(empty.sum())} of {len(kp)} frames with no hand (all zero/NaN)")
        kp = kp[keep]
    bad = ~np.isfinite(kp)
    if bad.any():
        t, j = (int(x) for x in np.argwhere(bad)[0][:2])
        raise DemoFormatError(f"{int(bad.any(axis=(1, 2)).sum())} frames have NaN/Inf keypoints "
                              f"(first: frame {keep[t]}, keypoint {j}); fill or remove those frames")
    size = _hand_size(kp)
    median = float(np.median(size))
    if median == 0.0:
        raise DemoFormatError("the wrist and the middle-finger MCP coincide in most frames: the "
                              "hand is collapsed to a point; check the export and --order")
    looks = "m" if 0.03 <= median <= 0.3 else "mm" if 30 <= median <= 300 else None
    if units == "auto":
        if looks is None:
            raise DemoFormatError(
                f"cannot tell the units: the wrist -> middle MCP distance is {median:.4g} (an "
                "adult hand: about 0.09 m or 90 mm); convert the keypoints to metres, or pass "
                "--units m or --units mm if the hand is really that size")
        units = looks
        notes.append(f"units: {'millimetres' if units == 'mm' else 'metres'} (detected)")
    elif looks is not None and looks != units:
        raise DemoFormatError(
            f"--units {units} does not fit the data: the wrist -> middle MCP distance is "
            f"{median:.4g}, which looks like {'millimetres' if looks == 'mm' else 'metres'}; "
            f"pass --units {looks} (or --units auto)")
    if units == "mm":
        kp, size, median = kp / 1000.0, size / 1000.0, median / 1000.0
    collapsed = np.flatnonzero(size < 0.25 * median)
    if len(collapsed):
        raise DemoFormatError(
            f"{len(collapsed)} frames have a collapsed hand (wrist -> middle MCP under a quarter "
            f"of its median {1000 * median:.0f} mm; first: frame {keep[collapsed[0]]}); remove "
            "those frames")
    bones = np.median(np.linalg.norm(kp[:, 1:] - kp[:, _PARENT[1:]], axis=2), axis=0)
    ratio = bones / _ADULT_BONES
    rel = ratio / np.median(ratio)
    worst = int(np.argmax(np.abs(np.log(np.maximum(rel, 1e-9)))))
    if not 0.4 <= rel[worst] <= 2.5:
        raise DemoFormatError(
            f"impossible bone lengths: {_bone_name(worst + 1)} is {1000 * bones[worst]:.0f} mm "
            f"in a hand whose other bones are {np.median(ratio):.2f}x adult size (expected about "
            f"{1000 * _ADULT_BONES[worst] * np.median(ratio):.0f} mm); is --order right "
            f"({' or '.join(ORDERS)})?")
    return kp, notes, keep


def parse_pose(spec: str) -> np.ndarray:
    """An object pose "x,y,z" or "x,y,z,qw,qx,qy,qz" (metres, unit quaternion w first), or
    a .npy/.csv file of (T, 7) or (T, 3) poses -> (7,) or (T, 7)."""
    p = Path(spec)
    if p.suffix.lower() in (".npy", ".csv") and p.is_file():
        arr = np.load(p, allow_pickle=False) if p.suffix.lower() == ".npy" else \
            np.loadtxt(p, delimiter=",", ndmin=2)
    else:
        try:
            arr = np.array([float(x) for x in spec.split(",")])
        except ValueError:
            raise DemoFormatError(f"--object-pose {spec!r}: expected x,y,z[,qw,qx,qy,qz] "
                                  "numbers or a .npy/.csv file of poses") from None
    arr = np.asarray(arr, float)
    if arr.shape[-1] == 3:
        arr = np.concatenate([arr, np.broadcast_to([1.0, 0, 0, 0], (*arr.shape[:-1], 4))], -1)
    if arr.shape[-1] != 7 or arr.ndim > 2 or not np.all(np.isfinite(arr)):
        raise DemoFormatError(f"--object-pose {spec!r}: expected 3 or 7 finite numbers per pose")
    q = arr[..., 3:]
    if np.any(np.abs(np.linalg.norm(q, axis=-1) - 1) > 1e-3):
        raise DemoFormatError(f"--object-pose {spec!r}: the quaternion (qw,qx,qy,qz) must "
                              "have unit length")
    return arr


def load_keypoint_array(path: str | Path, order: str = "mediapipe", fps: float = 30.0,
                        object_name: str = "", object_pos: np.ndarray | None = None,
                        object_quat: np.ndarray | None = None, key: str | None = None,
                        subject: str = "", units: str = "auto", hand: str = "right",
                        notes: list[str] | None = None) -> HumanDemo:
    """A demo from a keypoint file (`read_keypoints`) in `order`, checked and converted to
    metres (`clean_keypoints`); a left hand is mirrored to a right one (`hand_frame.mirror`).

    Without an object the keypoints are put into the canonical hand frame (see
    `hand_frame`); with one they stay in the capture frame, which must then be the object's
    world frame (z up, table at z = 0); the object pose defaults to the identity. `notes`
    (if given) receives one line per conversion made."""
    from dexdrake.demos.hand_frame import canonical, mirror

    if not (np.isfinite(fps) and fps > 0):
        raise DexdrakeError(f"--fps must be a positive number, got {fps}")
    if hand not in HANDS:
        raise DexdrakeError(f"unknown hand side {hand!r}; valid: {', '.join(HANDS)}")
    path = Path(path)
    raw, times = read_keypoints(path, key)
    kp, done, keep = clean_keypoints(reorder_keypoints(raw, order), units)
    t = times[keep] if times is not None else keep / fps
    if hand == "left":
        kp = mirror(kp)
        done.append("mirrored the left hand to a right hand")
    n = len(raw)
    pos = np.broadcast_to(np.zeros(3) if object_pos is None else object_pos, (n, 3))[keep]
    quat = np.broadcast_to([1.0, 0, 0, 0] if object_quat is None else object_quat,
                           (n, 4))[keep]
    if hand == "left" and object_name:
        pos, quat = mirror(pos), quat * np.array([1.0, 1.0, -1.0, -1.0])
        done.append("mirrored the object pose too (exact for mirror-symmetric objects)")
    if not object_name:
        kp = canonical(kp)
        done.append("put into the canonical hand frame (wrist at the origin, "
                    "see dexdrake/demos/hand_frame.py)")
    extra = {"hand": hand, "frame": "world" if object_name else "hand"}
    demo = HumanDemo(kp, np.asarray(t, float), object_name, np.array(pos, float),
                     np.array(quat, float),
                     DemoMeta(subject=subject, fps=fps, source=f"keypoints:{path.name}:{order}",
                              extra=extra))
    demo.validate()
    if notes is not None:
        notes.extend(done)
    return demo

