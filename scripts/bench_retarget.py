"""Benchmark the CasADi retargeter on synthetic 21-keypoint sequences (one core).

Prints ms per frame and the key-vector residual ||v^R - k v^H|| (mm; mean over the
wrist->tip/base and tip->tip vectors, and over the thumb's vectors) for Allegro and Adroit,
beside the reference numbers of dex-retargeting 0.5 from specs/retargeting.md (measured
there on a real 621-frame MediaPipe trajectory on a 2-core CPU, so the comparison is
indicative, not like for like).

    OMP_NUM_THREADS=1 python scripts/bench_retarget.py [--demos 6] [--seed 0]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from dexdrake.demos.synthetic import synthesize_demo  # noqa: E402
from dexdrake.retarget.retargeter import Retargeter  # noqa: E402

REFERENCE = {  # dex-retargeting 0.5 (specs/retargeting.md): ms/frame, residual mm mean, thumb
    "allegro": ("DexPilot 10.2 ms/frame (vector 11.7)", "vector mode 44 mm mean, thumb 61 mm"),
    "adroit": ("Shadow (24 DoF) DexPilot 18.9 ms/frame", "n/a"),
}
TARGET_MS = {"allegro": 2.0, "adroit": 4.0}


def _objects():
    return [("box", trimesh.creation.box((0.06, 0.06, 0.12))),
            ("cylinder", trimesh.creation.cylinder(0.035, 0.15)),
            ("sphere", trimesh.creation.icosphere(3, 0.03))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--demos", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    demos = []
    for i in range(args.demos):
        name, mesh = _objects()[i % 3]
        grasp = ("top", "side", "pinch")[i % 3]
        demos.append((synthesize_demo(mesh, name, grasp, seed=args.seed + i), mesh))
    frames = sum(d.num_frames for d, _ in demos)
    print(f"{len(demos)} synthetic demos, {frames} frames (trimmed, 60 fps); one thread; "
          f"ms/frame in CPU time (load average {os.getloadavg()[0]:.1f})")
    print(f"{'hand':8s} {'DoF':>4s} {'ms/frame':>9s} {'target':>7s} {'resid mean':>11s} "
          f"{'thumb':>7s} {'wrist':>7s} {'finger':>7s}   reference (dex-retargeting 0.5)")
    for hand in ("allegro", "adroit"):
        r = Retargeter(hand)
        r.retarget_sequence(demos[0][0], object_mesh=demos[0][1], progress=False)  # warm-up
        elapsed, res = 0.0, []
        for demo, mesh in demos:
            t = time.process_time()  # CPU time: wall time on a shared machine is inflated by others
            Q = r.retarget_sequence(demo, object_mesh=mesh, progress=False)
            elapsed += time.process_time() - t
            res += [r.residuals(demo.keypoints[k], Q[k]) for k in range(demo.num_frames)]
        ms = 1000 * elapsed / frames
        mm = {k: 1000 * np.mean([x[k].mean() for x in res]) for k in ("all", "thumb", "wrist",
                                                                      "finger")}
        ref_ms, ref_mm = REFERENCE[hand]
        print(f"{hand:8s} {r.num_joints:4d} {ms:9.2f} {TARGET_MS[hand]:7.1f} {mm['all']:11.1f} "
              f"{mm['thumb']:7.1f} {mm['wrist']:7.1f} {mm['finger']:7.1f}   {ref_ms}; {ref_mm}")
        print(f"{'':8s} speed-up vs reference: {10.2 / ms if hand == 'allegro' else 18.9 / ms:.1f}x"
              " (ms/frame includes the object closest-point queries)")


if __name__ == "__main__":
    main()
