"""CLI: `retarget`, a demo or keypoint file -> robot joint angles (and a rerun recording)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dexdrake import argtypes
from dexdrake.cli.demos import keypoint_flags, load_demo_or_keypoints
from dexdrake.errors import DexdrakeError
from dexdrake.outputs import check_writable

# MediaPipe skeleton: each finger's chain from the wrist
_CHAINS = [[0, 1, 2, 3, 4], [0, 5, 6, 7, 8], [0, 9, 10, 11, 12], [0, 13, 14, 15, 16],
           [0, 17, 18, 19, 20]]


def add_parser(subparsers) -> None:
    """Add `retarget` to an argparse subparsers object."""
    rt = subparsers.add_parser("retarget", help="retarget a human demo or keypoint file to a "
                               "robot hand", description=RETARGET_HELP)
    rt.add_argument("demo", type=Path, help="demo .npz (dexdrake demo format) or a keypoint "
                    "file (.npy/.npz/.pkl/.json/.csv)")
    rt.add_argument("--hand", required=True, help="hand name, e.g. allegro or adroit")
    rt.add_argument("--out", type=argtypes.output_file(".npz"), help="joint trajectory .npz "
                    "(default: <demo>.<hand>.npz)")
    rt.add_argument("--rrd", type=argtypes.output_file(".rrd"),
                    help="write a rerun recording of human vs robot points")
    rt.add_argument("--fixed-wrist", action="store_true", help="keep the arm at its reference "
                    "pose and retarget the fingers only (a hand on a fixed mount)")
    keypoint_flags(rt, "--side")
    rt.set_defaults(func=cmd_retarget)


RETARGET_HELP = """Retarget a demo file, or a keypoint file read as `demos import` reads it,
to a robot hand. Without an object the hand is put into the canonical hand frame and placed
on the robot hand at its reference pose, so the arm starts inside its reach."""


def cmd_retarget(args: argparse.Namespace) -> int:
    from dexdrake.hands.description import load_hand
    from dexdrake.retarget.retargeter import Retargeter

    hand = load_hand(args.hand)
    try:
        out = args.out or check_writable(args.demo.with_suffix(f".{args.hand}.npz"), False)
    except DexdrakeError as e:
        raise DexdrakeError(f"default --out: {e}; pass --out") from None
    notes: list[str] = []
    demo = load_demo_or_keypoints(args.demo, args, notes, demo_files=True)
    r = Retargeter(hand, fixed_wrist=args.fixed_wrist)
    place = args.fixed_wrist or not demo.object_name
    if args.fixed_wrist and demo.object_name:
        notes.append("--fixed-wrist: the object terms are left out")
    Q = r.retarget_sequence(demo, place=place)
    keypoints = r.place(demo.keypoints) if place else demo.keypoints
    res = [r.residuals(keypoints[t], Q[t]) for t in range(demo.num_frames)]
    mean = 1000 * np.mean([x["all"].mean() for x in res])
    thumb = 1000 * np.mean([x["thumb"].mean() for x in res])
    write_npz(out, q=Q, joint_names=np.array(r.joint_names), time=demo.time,
              hand=args.hand, demo=str(args.demo), residual_mm_mean=mean,
              residual_mm_thumb=thumb, fixed_wrist=args.fixed_wrist)
    for n in notes:
        print(f"  {n}")
    print(f"{demo.num_frames} frames -> {out}; key-vector residual {mean:.1f} mm mean, "
          f"{thumb:.1f} mm thumb")
    if args.rrd:
        write_rrd(args.rrd, demo, r, Q, keypoints)
        print(f"rerun recording: {args.rrd}")
    return 0


def write_npz(path: Path, **arrays) -> None:
    """np.savez_compressed to `path` atomically (a temporary sibling renamed into place)."""
    import os
    import tempfile

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".npz")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez_compressed(f, **arrays)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_rrd(path: Path, demo, retargeter, Q: np.ndarray, keypoints: np.ndarray) -> None:
    """A rerun recording: human keypoints + skeleton and the robot's matched points per frame."""
    import rerun as rr

    rec = rr.RecordingStream("dexdrake_retarget")
    path.parent.mkdir(parents=True, exist_ok=True)
    rec.save(str(path))
    for t in range(demo.num_frames):
        rec.set_time("frame", sequence=t)
        rec.set_time("time", duration=float(demo.time[t]))
        kp = keypoints[t]
        rec.log("human/keypoints", rr.Points3D(kp, radii=0.004, colors=[230, 160, 60]))
        rec.log("human/skeleton", rr.LineStrips3D([kp[c] for c in _CHAINS],
                                                  colors=[230, 160, 60]))
        rec.log("robot/points", rr.Points3D(retargeter.robot_points(Q[t]), radii=0.005,
                                            colors=[60, 140, 230]))
        rec.log("object/origin", rr.Points3D(demo.object_pos[t][None], radii=0.008,
                                             colors=[120, 200, 120]))
    rec.flush()
    rec.disconnect()
