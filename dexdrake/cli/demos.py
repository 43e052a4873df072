"""CLI: `demos synth` (synthetic human grasps), `demos import` (keypoint files -> demo files)
and `demos replay` (see cli/replay.py); the keypoint-file flags `retarget` shares."""

from __future__ import annotations

import argparse
from pathlib import Path

from dexdrake import argtypes
from dexdrake.cli import replay


def keypoint_flags(p: argparse.ArgumentParser, *side: str) -> None:
    """Flags that say how to read a raw keypoint file (demos import, retarget); `side`: the
    flag names of the hand side (retarget's --hand names the robot hand)."""
    from dexdrake.demos.loaders import HANDS, ORDERS, UNITS

    p.add_argument("--order", choices=ORDERS, default="mediapipe",
                   help="keypoint order in the file (default: mediapipe)")
    p.add_argument("--fps", type=argtypes.positive, default=30.0,
                   help="frame rate when the file has no times (default: 30)")
    p.add_argument("--units", choices=UNITS, default="auto",
                   help="units of the file (default: auto, from the hand's size)")
    p.add_argument(*side, dest="side", choices=HANDS, default="right",
                   help="which hand the keypoints are of; a left hand is mirrored")
    p.add_argument("--key", help="the array's name inside a .npz/.pkl/.json mapping")
    p.add_argument("--object", default="", help="library object held in the demo (the "
                   "keypoints are then in its world frame: z up, table at z = 0)")
    p.add_argument("--object-pose", help="object pose x,y,z[,qw,qx,qy,qz] or a .npy/.csv "
                   "file of (T, 7) poses (default: identity)")


def add_parser(subparsers) -> None:
    """Add `demos synth|import|replay ...` to an argparse subparsers object."""
    demos = subparsers.add_parser("demos", help="human grasp demonstrations")
    sub = demos.add_subparsers(dest="demos_command", required=True)
    synth = sub.add_parser("synth", help="generate synthetic human grasp demos")
    synth.add_argument("--objects", required=True,
                       help="'train', 'unseen' or comma-separated object names")
    synth.add_argument("--out", required=True, type=argtypes.output_folder, help="output folder")
    synth.add_argument("--demos-per-object", type=argtypes.episodes, default=3, metavar="N",
                       help=f"demos made per object (demonstrations, not episodes; at most {argtypes.MAX_EPISODES}) "
                            "(default: 3)")
    synth.add_argument("--seed", type=argtypes.seed, default=0)
    synth.set_defaults(func=cmd_synth)
    imp = sub.add_parser("import", help="convert a keypoint file (.npy/.npz/.pkl/.json/.csv) "
                         "to a demo file", description=IMPORT_HELP)
    imp.add_argument("file", type=Path, help="keypoint file, (T, 21, 3) or (T, 63)")
    imp.add_argument("--out", required=True, type=argtypes.output_file(".npz"),
                     help="demo file to write (.npz)")
    keypoint_flags(imp, "--hand", "--side")
    imp.set_defaults(func=cmd_import)
    replay.add_parser(sub)


IMPORT_HELP = """Convert hand keypoints to a dexdrake demo file. The file holds (T, 21, 3)
keypoints (or (T, 63) rows; CSV: 63 values per row, or 64 with the time first). Units are
detected from the hand's size (or given with --units); frames with no hand are dropped;
NaN, a collapsed hand or impossible bone lengths are refused with the fix. Without
--object the keypoints are stored in the canonical hand frame (wrist at the origin, see
dexdrake/demos/hand_frame.py); with --object they stay in the object's world frame."""

def load_demo_or_keypoints(path: Path, args: argparse.Namespace, notes: list[str],
                            demo_files: bool):
    """The demo at `path`: a dexdrake demo file (if `demo_files`), else a keypoint file read
    with the keypoint flags of `args`."""
    from dexdrake.demos.format import DemoFormatError, is_demo_file, load_demo
    from dexdrake.demos.loaders import KEYPOINT_SUFFIXES, load_keypoint_array, parse_pose

    if path.is_dir():
        raise DemoFormatError(f"{path} is a folder; give a demo or keypoint file")
    if not path.is_file():
        raise DemoFormatError(f"{path}: no such file")
    if path.suffix.lower() not in KEYPOINT_SUFFIXES:
        raise DemoFormatError(f"{path}: not a demo or keypoint file (use a dexdrake demo .npz "
                              f"or keypoints as {', '.join(KEYPOINT_SUFFIXES)})")
    if demo_files and is_demo_file(path):
        return load_demo(path)
    pos = quat = None
    if args.object:
        from dexdrake.objects.library import get_object

        get_object(args.object)
        if args.object_pose:
            pose = parse_pose(args.object_pose)
            pos, quat = pose[..., :3], pose[..., 3:]
    elif args.object_pose:
        raise DemoFormatError("--object-pose needs --object NAME")
    return load_keypoint_array(path, order=args.order, fps=args.fps, object_name=args.object,
                               object_pos=pos, object_quat=quat, key=args.key,
                               units=args.units, hand=args.side, notes=notes)


def cmd_import(args: argparse.Namespace) -> int:
    from dexdrake.demos.format import save_demo

    notes: list[str] = []
    demo = load_demo_or_keypoints(args.file, args, notes, demo_files=False)
    if demo.object_name:
        from dexdrake.objects.library import get_object

        get_object(demo.object_name)  # refused here, not at replay
    out = save_demo(demo, args.out)
    for n in notes:
        print(f"  {n}")
    print(f"{demo.num_frames} frames ({demo.time[-1] - demo.time[0]:.2f} s) -> {out}")
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from dexdrake.demos.format import save_demo
    from dexdrake.demos.synthetic import synthesize_object_demos
    from dexdrake.eval.seeds import check_training_seeds
    from dexdrake.objects.library import resolve_objects
    from dexdrake.systems.scene import ObjectPlacement

    names = resolve_objects(args.objects)[1]
    check_training_seeds([(args.seed * 100003 + len(names) - 1) * 1000 + args.demos_per_object - 1],
                         "demo episode seeds ((seed * 100003 + object index) * 1000 + k)")
    written = 0
    for i, name in enumerate(tqdm(names, desc="synthesize", unit="object")):
        for k, demo in enumerate(synthesize_object_demos(
                name, args.demos_per_object, seed=args.seed * 100003 + i,
                placement_yaw=lambda s: ObjectPlacement.from_seed(s).yaw)):
            save_demo(demo, args.out / f"{name}_{k:02d}_{demo.meta.extra['grasp']}.npz")
            written += 1
    print(f"wrote {written} demos to {args.out}")
    return 0
