"""Demo loaders: plain keypoint arrays (MediaPipe or MANO order) and GRAB sequences.

GRAB needs the optional extra `smplx` (pip install 'dexdrake[grab]') and the licence-gated
MANO model files, which the user supplies; nothing else in dexdrake requires them.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from dexdrake.demos.format import DemoFormatError, DemoMeta, HumanDemo
from dexdrake.errors import DexdrakeError

# mediapipe[i] = mano21[MANO_TO_MEDIAPIPE[i]]; MANO's 16 joints then tips thumb..little
MANO_TO_MEDIAPIPE = np.array([0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7,
                              8, 9, 20])
MANO_TIP_VERTICES = (744, 320, 443, 554, 671)  # thumb, index, middle, ring, little (smplx)
ORDERS = ("mediapipe", "mano")


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


def _read_array(path: Path, key: str | None) -> np.ndarray:
    if path.suffix == ".npy":
        return np.load(path, allow_pickle=False)
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            names = z.files
            k = key or ("keypoints" if "keypoints" in names else names[0] if len(names) == 1
                        else None)
            if k is None or k not in names:
                raise DemoFormatError(f"{path}: name the array with key= (arrays: {names})")
            return z[k]
    if path.suffix in (".pkl", ".pickle"):
        with open(path, "rb") as f:
            obj = pickle.load(f)  # noqa: S301 - the user's own file, loaded on request
        if isinstance(obj, dict):
            k = key or "keypoints"
            if k not in obj:
                raise DemoFormatError(f"{path}: no key {k!r} (keys: {list(obj)})")
            obj = obj[k]
        return np.asarray(obj)
    raise DemoFormatError(f"{path}: unsupported file type (use .npy, .npz or .pkl)")


def load_keypoint_array(path: str | Path, order: str = "mediapipe", fps: float = 30.0,
                        object_name: str = "", object_pos: np.ndarray | None = None,
                        object_quat: np.ndarray | None = None, key: str | None = None,
                        subject: str = "") -> HumanDemo:
    """A demo from a (T, 21, 3) keypoint array in metres, world frame, in `order`.

    The object pose defaults to the identity at the origin for every frame.
    """
    path = Path(path)
    kp = reorder_keypoints(_read_array(path, key), order)
    if kp.ndim != 3:
        raise DemoFormatError(f"{path}: expected (T, 21, 3) keypoints, got {kp.shape}")
    T = kp.shape[0]
    pos = np.zeros((T, 3)) if object_pos is None else np.broadcast_to(object_pos, (T, 3))
    quat = np.tile([1.0, 0, 0, 0], (T, 1)) if object_quat is None else np.broadcast_to(
        object_quat, (T, 4))
    demo = HumanDemo(kp, np.arange(T) / fps, object_name, np.array(pos, float),
                     np.array(quat, float),
                     DemoMeta(subject=subject, fps=fps, source=f"keypoints:{path.name}:{order}"))
    demo.validate()
    return demo


def load_grab_sequence(seq_path: str | Path, mano_model_dir: str | Path,
                       grab_root: str | Path | None = None) -> HumanDemo:
    """A GRAB right-hand sequence (e.g. grab/s1/mug_drink_1.npz) as a demo.

    Runs the MANO right-hand layer (smplx) on GRAB's rhand parameters, takes the 16 joints
    and the 5 fingertip vertices, and reorders them to MediaPipe. mano_model_dir holds
    MANO_RIGHT.pkl; grab_root (default: three levels above seq_path) resolves the
    subject-specific hand template. The demo is untrimmed: pass it to
    dexdrake.demos.trim.trim_demo / canonicalize with the object's mesh.
    """
    try:
        import smplx
        import torch
    except ImportError as e:
        raise DexdrakeError(f"GRAB loading needs the optional package {e.name!r}: "
                            "pip install 'dexdrake[grab]' (smplx) and supply the MANO model "
                            "files (MANO_RIGHT.pkl, licence from mano.is.tue.mpg.de)") from e
    seq_path, mano_model_dir = Path(seq_path), Path(mano_model_dir)
    if not (mano_model_dir / "MANO_RIGHT.pkl").is_file():
        raise DexdrakeError(f"{mano_model_dir}: MANO_RIGHT.pkl not found (the MANO model "
                            "files are licence-gated; download them yourself)")
    seq = np.load(seq_path, allow_pickle=True)
    seq = {k: seq[k].item() if seq[k].dtype == object and seq[k].shape == () else seq[k]
           for k in seq.files}
    rh = seq["rhand"]["params"]
    T = int(seq["n_frames"])
    root = Path(grab_root) if grab_root else seq_path.parents[2]
    vtemp = None
    if seq["rhand"].get("vtemp"):
        import trimesh

        vtemp = trimesh.load(root / str(seq["rhand"]["vtemp"]), process=False).vertices
    layer = smplx.create(str(mano_model_dir), model_type="mano", is_rhand=True,
                         use_pca=False, flat_hand_mean=True, batch_size=T,
                         v_template=vtemp)
    with torch.no_grad():
        out = layer(global_orient=torch.as_tensor(rh["global_orient"], dtype=torch.float32),
                    hand_pose=torch.as_tensor(rh["fullpose"], dtype=torch.float32),
                    transl=torch.as_tensor(rh["transl"], dtype=torch.float32))
    joints, verts = out.joints.numpy()[:, :16], out.vertices.numpy()
    mano21 = np.concatenate([joints, verts[:, list(MANO_TIP_VERTICES)]], axis=1)
    from scipy.spatial.transform import Rotation

    op = seq["object"]["params"]
    quat = Rotation.from_rotvec(op["global_orient"]).as_quat()[:, [3, 0, 1, 2]]
    fps = float(seq.get("framerate", 120.0))
    betas = np.zeros(10)
    pose48 = np.concatenate([rh["global_orient"], rh["fullpose"]], axis=1)
    demo = HumanDemo(
        reorder_keypoints(mano21, "mano"), np.arange(T) / fps,
        Path(str(seq["obj_name"])).stem, np.asarray(op["transl"], float), quat,
        DemoMeta(subject=str(seq.get("sbj_id", "")), fps=fps, source=f"grab:{seq_path.name}"),
        mano_pose=pose48, mano_trans=np.asarray(rh["transl"], float), mano_betas=betas,
    )
    demo.validate()
    return demo
