"""Time per step of full DexRep for the Adroit (n = 22, 1000 voxels, local-geo lookup).

Paths: fast (cached SDF grid + exact closest points), SceneGraph (QueryObject queries) and a
reference that works like the public code (brute-force distances to the 2048 samples, a
shell occupancy from the nearest sample, and a PointNet pass on the world-oriented cloud
every step). Also a GraspEnv control step with and without DexRep observations.

Each timing is the best of `--repeats` blocks of `--steps` calls, as wall time and as this
process's CPU time (the machine may be shared: CPU time is the fairer number, and the
load average is printed). Run: python scripts/bench_dexrep.py [--steps 100] [--repeats 15] [--no-env]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import trimesh
from pydrake.geometry import Mesh, ProximityProperties
from pydrake.math import RigidTransform
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
from pydrake.multibody.tree import SpatialInertia, UnitInertia
from pydrake.systems.framework import DiagramBuilder

from dexdrake.dexrep import features as F
from dexdrake.dexrep.feature_sets import FeatureExtractor
from dexdrake.dexrep.geometry import compute_object_geometry
from dexdrake.dexrep.occupancy import voxel_centres
from dexdrake.dexrep.pointnet import PointNetEncoder, encode_cloud
from dexdrake.hands.description import load_hand


def reference_step(p_W, X_WG, X_WO, geom, encoder):
    """Like the public code: nearest of 2048 samples by brute force + PointNet every step."""
    s_W = geom.samples @ X_WO[:3, :3].T + X_WO[:3, 3]
    d = np.linalg.norm(p_W[:, None] - s_W[None], axis=2)
    j = d.argmin(axis=1)
    c = voxel_centres() @ X_WG[:3, :3].T + X_WG[:3, 3]
    occ = (np.linalg.norm(c[:, None] - s_W[None], axis=2).min(axis=1) <= 0.01).astype(float)
    local, _ = encode_cloud(encoder, s_W)
    n = geom.normals[j] @ X_WO[:3, :3].T
    return np.concatenate([occ, np.column_stack([np.minimum(d[np.arange(len(j)), j], 0.2), n]).ravel(),
                           local[j].ravel()])


def timed(fn, steps: int, repeats: int) -> tuple[float, float]:
    """(best wall ms, best CPU ms) per call over `repeats` blocks of `steps` calls."""
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        for _ in range(steps):
            fn()
        wall.append((time.perf_counter() - w) / steps * 1e3)
        cpu.append((time.process_time() - c) / steps * 1e3)
    return min(wall), min(cpu)


def env_step_times(steps: int, repeats: int) -> dict[str, tuple[float, float]]:
    """GraspEnv control steps (10 plant steps each) with hand-state and DexRep observations."""
    from dexdrake.systems.grasp_env import GraspEnv

    out = {}
    for name, feature_set in (("hand state only", None), ("DexRep", "DexRep")):
        env = GraspEnv(feature_set=feature_set, horizon=10**9)
        env.reset(0)
        hold = env.q_command.copy()
        out[name] = timed(lambda: env.step_positions(hold), steps, repeats)
        out[name + " (observation only)"] = timed(env.observation, steps, repeats)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--no-env", action="store_true", help="skip the GraspEnv step timing")
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    encoder = PointNetEncoder().eval()
    mesh = trimesh.creation.torus(0.06, 0.02, major_sections=96, minor_sections=48)
    geom = compute_object_geometry(mesh, encoder, "torus")
    hand = load_hand("adroit")
    obj = Path(tempfile.mkdtemp()) / "torus.obj"
    mesh.export(obj)
    builder = DiagramBuilder()
    plant, sg = AddMultibodyPlantSceneGraph(builder, 0.002)
    (hi,) = Parser(plant).AddModels(hand.model_path)
    body = plant.AddRigidBody("torus", plant.AddModelInstance("object"),
                              SpatialInertia(0.5, np.zeros(3), UnitInertia.SolidSphere(0.05)))
    gid = plant.RegisterCollisionGeometry(body, RigidTransform(), Mesh(str(obj)), "d", ProximityProperties())
    plant.Finalize()
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    pctx = plant.GetMyMutableContextFromRoot(ctx)
    palm = plant.EvalBodyPoseInWorld(pctx, plant.GetBodyByName(hand.palm.body, hi))
    X_WO = RigidTransform(palm.translation() + [0.0, -0.04, 0.0])
    plant.SetFreeBodyPose(pctx, body, X_WO)
    query = sg.get_query_output_port().Eval(sg.GetMyContextFromRoot(ctx))
    fast = FeatureExtractor(hand, plant, hi, geom, "DexRep", "fast")
    slow = FeatureExtractor(hand, plant, hi, geom, "DexRep", "scenegraph", distance_geometry_id=gid)
    p_W, X_WG, X = fast.hand_points(pctx), fast.grid_pose(pctx), X_WO.GetAsMatrix4()
    occupied = int(fast(pctx, X_WO)[105:1105].sum())
    cp = F.closest_points(p_W, X, geom)
    centred = f"{int(F.occupancy(X_WG, X_WG, geom).sum())} occupied"
    n, r = args.steps, args.repeats
    rows = [
        ("fast path (whole FeatureExtractor)", timed(lambda: fast(pctx, X_WO), n, r)),
        ("  body poses + hand points (FK)", timed(lambda: fast.hand_points(pctx), n, r)),
        ("  occupancy", timed(lambda: F.occupancy(X_WG, X, geom), n, r)),
        (f"  occupancy, torus at the grid centre ({centred})", timed(lambda: F.occupancy(X_WG, X_WG, geom), n, r)),
        ("  closest points (one Open3D call)", timed(lambda: F.closest_points(p_W, X, geom), n, r)),
        ("  local-geo lookup (one cKDTree query)", timed(lambda: geom.nearest_samples(cp.points), n, r)),
        ("SceneGraph path", timed(lambda: slow(pctx, X_WO, query), max(3, n // 50), r)),
        ("reference (public-code style)",
         timed(lambda: reference_step(p_W, X_WG, X, geom, encoder), max(3, n // 50), r)),
    ]
    print(f"Adroit DexRep (n=22, 1000 voxels, {occupied} occupied), one thread; load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; best of {r} blocks, ms per call:")
    print(f"  {'':40s} {'wall':>9s} {'CPU':>9s}")
    for label, (wall, cpu) in rows:
        print(f"  {label:40s} {wall:9.3f} {cpu:9.3f}")
    t_fast, t_slow, t_ref = rows[0][1][1], rows[6][1][1], rows[7][1][1]
    print(f"  ratios (CPU) vs reference: fast {t_ref / t_fast:.0f}x faster, SceneGraph {t_ref / t_slow:.1f}x faster; "
          f"fast vs SceneGraph {t_slow / t_fast:.0f}x")
    if not args.no_env:
        print("GraspEnv (sphere_medium, 20 ms control step = 10 plant steps), ms per call:")
        for label, (wall, cpu) in env_step_times(max(10, n // 10), r).items():
            print(f"  {label:40s} {wall:9.3f} {cpu:9.3f}")


if __name__ == "__main__":
    main()
