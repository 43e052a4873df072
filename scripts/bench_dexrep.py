"""Time per step of full DexRep for the Adroit (n = 22, 1000 voxels, local-geo lookup).

Paths: fast (cached SDF grid + exact closest points), SceneGraph (QueryObject queries) and a
reference that works like the public code (brute-force distances to the 2048 samples, a
shell occupancy from the nearest sample, and a PointNet pass on the world-oriented cloud
every step). Prints ms/step and ratios vs the reference. Run: python scripts/bench_dexrep.py
"""

from __future__ import annotations

import argparse
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
from dexdrake.dexrep.pointnet import PointNetEncoder, encode_cloud
from dexdrake.hands.description import load_hand


def reference_step(p_W, X_WG, X_WO, geom, encoder):
    """Like the public code: nearest of 2048 samples by brute force + PointNet every step."""
    s_W = geom.samples @ X_WO[:3, :3].T + X_WO[:3, 3]
    d = np.linalg.norm(p_W[:, None] - s_W[None], axis=2)
    j = d.argmin(axis=1)
    c = F.voxel_centres() @ X_WG[:3, :3].T + X_WG[:3, 3]
    occ = (np.linalg.norm(c[:, None] - s_W[None], axis=2).min(axis=1) <= 0.01).astype(float)
    local, _ = encode_cloud(encoder, s_W)
    n = geom.normals[j] @ X_WO[:3, :3].T
    return np.concatenate([occ, np.column_stack([np.minimum(d[np.arange(len(j)), j], 0.2), n]).ravel(),
                           local[j].ravel()])


def timed(fn, steps):
    fn()
    t = time.perf_counter()
    for _ in range(steps):
        fn()
    return (time.perf_counter() - t) / steps * 1e3


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=50)
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
    t_fast = timed(lambda: fast(pctx, X_WO), args.steps)
    t_occ = timed(lambda: F.occupancy(X_WG, X, geom), args.steps)
    t_cp = timed(lambda: F.closest_points(p_W, X, geom), args.steps)
    t_slow = timed(lambda: slow(pctx, X_WO, query), max(3, args.steps // 10))
    t_ref = timed(lambda: reference_step(p_W, X_WG, X, geom, encoder), max(3, args.steps // 10))
    print(f"Adroit DexRep (n=22, 1000 voxels, {occupied} occupied), torch threads 1, ms/step:")
    print(f"  fast path (whole FeatureExtractor)  {t_fast:8.3f}  (occupancy {t_occ:.3f}, closest points {t_cp:.3f})")
    print(f"  SceneGraph path                     {t_slow:8.3f}")
    print(f"  reference (public-code style)       {t_ref:8.3f}")
    print(f"  ratios vs reference: fast {t_ref / t_fast:.1f}x faster, SceneGraph {t_ref / t_slow:.1f}x faster")


if __name__ == "__main__":
    main()
