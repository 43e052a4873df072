"""One hand's MediaPipe Holistic landmarks from `.pose` files as a dexdrake keypoint file.

Reads `.pose` files (the binary format of the pose-format package, as written for MediaPipe
Holistic), takes the named hand's 21 landmarks (MediaPipe order) in every frame where the hand
was tracked, and writes the files' frames one after another as a (T, 21, 3) float32 .npy in
metres, for `scripts/bench_retarget.py --keypoints` or `dexdrake demos import`.

Real captures (`--lexicon LANG`): the fingerspelling lexicon of the PyPI package
spoken-to-signed 0.4.0 (the `captures` extra: pip install -e '.[captures]'),
`spoken_to_signed/assets/fingerspelling_lexicon/LANG/*.pose` in the order of its `data.csv`
(one clip per letter; LANG a signed-language code: ase American, gsg German, cse Czech, ...),
written to `$DEXDRAKE_CACHE/captures/fingerspelling_LANG_HAND.npy` (`lexicon_capture`).
They are MediaPipe Holistic landmarks of real signers filmed by one camera; the packager
trimmed each clip to the signing, normalised it by the shoulders, resampled it so that a
letter lasts about one second (the motion replays up to a few times faster than signed) and
replaced the body's appearance by a mean one (hand landmarks untouched). Consecutive clips
join with a jump. Licence: the package's, MIT (Copyright (c) 2026 ZurichNLP); it names no
separate licence for the lexicon, whose file names (`fs-sts...`) suggest the source videos
come from SpreadTheSign, whose terms are not stated there. So dexdrake ships none of it:
the keypoint files are made on the user's machine from the installed package.

Units: pose-format keeps x and y in pixels but z as MediaPipe gives it, relative to the wrist
in units of the image width, and a normalised file no longer records that width. So z is
multiplied by the depth scale that keeps the 20 bone lengths most constant over the frames
(`depth_scale`: the variance of log bone length within each file, pooled), or by
--depth-scale W. All files are then scaled by one factor so that the median total bone length
equals that of dexdrake's adult hand (`human_hand.open_hand_keypoints`); the motion keeps its
proportions. A left hand is mirrored to a right one (`hand_frame.mirror`).

    python scripts/pose_to_keypoints.py --lexicon ase [--hand right|left]   # prints the path
    python scripts/pose_to_keypoints.py A.pose [B.pose ...] --out F.npy [--hand right|left]
        [--depth-scale auto|W]
"""

from __future__ import annotations

import argparse
import csv
import sys
from importlib.resources import files
from pathlib import Path

import numpy as np

from dexdrake.demos.hand_frame import mirror
from dexdrake.demos.human_hand import open_hand_keypoints
from dexdrake.paths import cache_dir

# MediaPipe skeleton: the parent keypoint of each keypoint 1..20
PARENT = np.array([0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19])
DEPTH_SCALES = np.geomspace(10.0, 10000.0, 301)  # candidate image widths (pixels)


def hand_landmarks(path: Path, hand: str) -> np.ndarray:
    """(T, 21, 3) landmarks of `hand` ("right"/"left") in the frames of the .pose file at
    `path` where all 21 were tracked, as stored (x, y in pixels, z in image widths); T may
    be 0."""
    try:
        from pose_format import Pose
    except ImportError:
        raise SystemExit("pose_to_keypoints needs pose-format: pip install pose-format") from None
    name = f"{hand.upper()}_HAND_LANDMARKS"
    pose = Pose.read(path.read_bytes())
    names = [c.name for c in pose.header.components]
    if name not in names:
        raise SystemExit(f"{path}: no {name} component (not a MediaPipe Holistic file)")
    i = sum(len(c.points) for c in pose.header.components[:names.index(name)])
    conf = np.asarray(pose.body.confidence)[:, 0, i:i + 21]
    data = np.asarray(pose.body.data)[:, 0, i:i + 21].astype(float)
    return data[(conf > 0).all(axis=1)]


def _with_depth(clip: np.ndarray, scale: float) -> np.ndarray:
    out = clip.copy()
    out[..., 2] = (clip[..., 2] - clip[:, :1, 2]) * scale
    return out


def _log_bones(kp: np.ndarray) -> np.ndarray:
    return np.log(np.linalg.norm(kp[:, 1:] - kp[:, PARENT], axis=2))


def depth_scale(clips: list[np.ndarray]) -> float:
    """The factor on z (from `DEPTH_SCALES`) that makes each bone's length most constant
    over the frames: the least within-file variance of log bone length, pooled over files."""
    frames = sum(len(c) for c in clips)
    cost = [sum(_log_bones(_with_depth(c, s)).var(axis=0).sum() * len(c) for c in clips)
            / frames for s in DEPTH_SCALES]
    return float(DEPTH_SCALES[int(np.argmin(cost))])


def to_metres(clips: list[np.ndarray], scale: float) -> np.ndarray:
    """The clips, z relative to the wrist multiplied by `scale`, one after another, all
    scaled by one factor so that the median total bone length is the adult hand's
    (`open_hand_keypoints`)."""
    kp = np.concatenate([_with_depth(c, scale) for c in clips])
    adult = open_hand_keypoints()
    total = np.linalg.norm(adult[1:] - adult[PARENT], axis=1).sum()
    size = np.median(np.exp(_log_bones(kp)).sum(axis=1))
    return kp * (total / size)


def convert(paths: list[Path], hand: str, scale: float | None = None
            ) -> tuple[np.ndarray, float, list[tuple[Path, int]]]:
    """(keypoints (T, 21, 3) in metres as a right hand, the depth scale used, (file, first
    frame) of each file that tracks `hand`) for the .pose files `paths`, in their order;
    scale None: `depth_scale`."""
    clips, kept = [], []
    for f in paths:
        clip = hand_landmarks(f, hand)
        if len(clip):
            kept.append((f, sum(len(c) for c in clips)))
            clips.append(clip)
        else:
            print(f"skipped {f}: the {hand} hand is never tracked", file=sys.stderr)
    if not clips:
        raise SystemExit(f"no file tracks the {hand} hand; try --hand "
                         f"{'left' if hand == 'right' else 'right'}")
    scale = depth_scale(clips) if scale is None else scale
    kp = to_metres(clips, scale)
    return (mirror(kp) if hand == "left" else kp), scale, kept


def lexicon_files(language: str) -> list[Path]:
    """The .pose files of `language` (a signed-language code) in spoken-to-signed's
    fingerspelling lexicon, in the order of its data.csv."""
    try:
        root = Path(str(files("spoken_to_signed") / "assets" / "fingerspelling_lexicon"))
    except ModuleNotFoundError:
        raise SystemExit("real captures need spoken-to-signed: pip install -e '.[captures]'"
                         ) from None
    with open(root / "data.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    paths = [root / r["path"] for r in rows if r["signed_language"] == language]
    if not paths:
        known = sorted({r["signed_language"] for r in rows})
        raise SystemExit(f"no fingerspelling lexicon for {language!r}; known: {', '.join(known)}")
    return paths


def lexicon_capture(language: str, hand: str = "right") -> Path:
    """`$DEXDRAKE_CACHE/captures/fingerspelling_{language}_{hand}.npy`, converted from the
    installed lexicon (`lexicon_files`) unless already there."""
    out = cache_dir() / "captures" / f"fingerspelling_{language}_{hand}.npy"
    if not out.exists():
        kp, _, _ = convert(lexicon_files(language), hand)
        out.parent.mkdir(exist_ok=True)
        tmp = out.with_suffix(".tmp.npy")
        np.save(tmp, kp.astype(np.float32))
        tmp.replace(out)  # atomic: a concurrent conversion writes the same file
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", type=Path, nargs="*", help=".pose files, in the order to write")
    ap.add_argument("--lexicon", metavar="LANG",
                    help="convert spoken-to-signed's fingerspelling lexicon of LANG instead")
    ap.add_argument("--out", type=Path, help="the keypoint file to write (.npy)")
    ap.add_argument("--hand", choices=("right", "left"), default="right")
    ap.add_argument("--depth-scale", default="auto",
                    help="factor on z (the source video's width in pixels), or auto")
    args = ap.parse_args()
    if args.lexicon:
        if args.files or args.out or args.depth_scale != "auto":
            raise SystemExit("--lexicon takes no .pose files, --out or --depth-scale")
        print(lexicon_capture(args.lexicon, args.hand))
        return
    if not args.files or args.out is None:
        raise SystemExit("give .pose files and --out F.npy, or --lexicon LANG")
    if args.out.suffix != ".npy":
        raise SystemExit(f"--out {args.out}: write a .npy file")
    scale = None
    if args.depth_scale != "auto":
        try:
            scale = float(args.depth_scale)
        except ValueError:
            scale = float("nan")
        if not (np.isfinite(scale) and scale > 0):
            raise SystemExit(f"--depth-scale must be auto or a positive number, "
                             f"got {args.depth_scale!r}")
    kp, scale, kept = convert(args.files, args.hand, scale)
    np.save(args.out, kp.astype(np.float32))
    print(f"wrote {args.out}: {len(kp)} frames, depth scale {scale:.0f}; first frame of each "
          f"file: " + ", ".join(f"{f.name} {s}" for f, s in kept))


if __name__ == "__main__":
    main()
