"""CLI: `demos synth` (synthetic human grasps), `demos replay` (see replay_commands) and
`retarget` (demo -> robot joint angles)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

# MediaPipe skeleton: each finger's chain from the wrist
_CHAINS = [[0, 1, 2, 3, 4], [0, 5, 6, 7, 8], [0, 9, 10, 11, 12], [0, 13, 14, 15, 16],
           [0, 17, 18, 19, 20]]


def add_parser(subparsers) -> None:
    """Add `demos synth ...`, `demos replay ...` and `retarget ...` to an argparse subparsers object."""
    demos = subparsers.add_parser("demos", help="human grasp demonstrations")
    sub = demos.add_subparsers(dest="demos_command", required=True)
    synth = sub.add_parser("synth", help="generate synthetic human grasp demos")
    synth.add_argument("--objects", required=True,
                       help="'train', 'unseen' or comma-separated object names")
    synth.add_argument("--out", required=True, type=Path, help="output folder")
    synth.add_argument("--per-object", type=int, default=3, help="demos per object")
    synth.add_argument("--seed", type=int, default=0)
    synth.set_defaults(func=cmd_synth)
    from dexdrake.demos import replay_commands

    replay_commands.add_parser(sub)

    rt = subparsers.add_parser("retarget", help="retarget a human demo to a robot hand")
    rt.add_argument("demo", type=Path, help="demo .npz (dexdrake demo format)")
    rt.add_argument("--hand", required=True, help="hand name, e.g. allegro or adroit")
    rt.add_argument("--out", type=Path, help="joint trajectory .npz "
                    "(default: <demo>.<hand>.npz)")
    rt.add_argument("--rrd", type=Path, help="write a rerun recording of human vs robot points")
    rt.set_defaults(func=cmd_retarget)


def _object_names(spec: str) -> list[str]:
    if spec in ("train", "unseen"):
        from dexdrake.objects.library import list_objects

        return [o.name for o in list_objects(spec)]
    return [s for s in spec.split(",") if s]


def cmd_synth(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from dexdrake.demos.format import save_demo
    from dexdrake.demos.synthetic import synthesize_object_demos

    if args.per_object < 1:
        raise SystemExit("--per-object must be at least 1")
    names = _object_names(args.objects)
    written = 0
    for i, name in enumerate(tqdm(names, desc="synthesize", unit="object")):
        for k, demo in enumerate(synthesize_object_demos(name, args.per_object,
                                                         seed=args.seed * 100003 + i)):
            save_demo(demo, args.out / f"{name}_{k:02d}_{demo.meta.extra['grasp']}.npz")
            written += 1
    print(f"wrote {written} demos to {args.out}")
    return 0


def cmd_retarget(args: argparse.Namespace) -> int:
    from dexdrake.demos.format import load_demo
    from dexdrake.retarget.retargeter import Retargeter

    demo = load_demo(args.demo)
    r = Retargeter(args.hand)
    Q = r.retarget_sequence(demo)
    res = [r.residuals(demo.keypoints[t], Q[t]) for t in range(demo.num_frames)]
    mean = 1000 * np.mean([x["all"].mean() for x in res])
    thumb = 1000 * np.mean([x["thumb"].mean() for x in res])
    out = args.out or args.demo.with_suffix(f".{args.hand}.npz")
    np.savez_compressed(out, q=Q, joint_names=np.array(r.joint_names), time=demo.time,
                        hand=args.hand, demo=str(args.demo), residual_mm_mean=mean,
                        residual_mm_thumb=thumb)
    print(f"{demo.num_frames} frames -> {out}; key-vector residual {mean:.1f} mm mean, "
          f"{thumb:.1f} mm thumb")
    if args.rrd:
        write_rrd(args.rrd, demo, r, Q)
        print(f"rerun recording: {args.rrd}")
    return 0


def write_rrd(path: Path, demo, retargeter, Q: np.ndarray) -> None:
    """A rerun recording: human keypoints + skeleton and the robot's matched points per frame."""
    import rerun as rr

    rec = rr.RecordingStream("dexdrake_retarget")
    rec.save(str(path))
    for t in range(demo.num_frames):
        rec.set_time("frame", sequence=t)
        rec.set_time("time", duration=float(demo.time[t]))
        kp = demo.keypoints[t]
        rec.log("human/keypoints", rr.Points3D(kp, radii=0.004, colors=[230, 160, 60]))
        rec.log("human/skeleton", rr.LineStrips3D([kp[c] for c in _CHAINS],
                                                  colors=[230, 160, 60]))
        rec.log("robot/points", rr.Points3D(retargeter.robot_points(Q[t]), radii=0.005,
                                            colors=[60, 140, 230]))
        rec.log("object/origin", rr.Points3D(demo.object_pos[t][None], radii=0.008,
                                             colors=[120, 200, 120]))
    rec.flush()
    rec.disconnect()
