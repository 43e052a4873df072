"""rerun view of DexRep over a grasp episode: `dexdrake features show`.

Composes the episode logger (systems/rerun_logger.py: hand, object, joints, rewards) with,
per control step, on the same `step` / `sim_time` time lines:
  world/dexrep/grid            Transform3D X_WG of the occupancy grid
  world/dexrep/grid/voxels     occupied voxels, Boxes3D in the grid frame
  world/dexrep/hand_points     the n DexRep hand points
  world/dexrep/closest_points  their closest object points
  world/dexrep/links           segments hand point -> closest point
  world/dexrep/normals         outward object normals at the closest points (Arrows3D)
  dexrep/distance/<point>      clipped distance of each hand point (scalars)
  dexrep/occupied_voxels       number of occupied voxels (scalar)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr

from dexdrake.dexrep.feature_sets import FeatureExtractor
from dexdrake.dexrep.features import SURFACE_CLIP
from dexdrake.dexrep.geometry import object_geometry
from dexdrake.dexrep.occupancy import voxel_centres

NORMAL_LENGTH = 0.02  # m, drawn length of the normal arrows


class DexRepEpisodeLogger:
    """Episode logger for `GraspEnv.rollout` that adds the DexRep geometry of each step
    (computed by its own fast-path FeatureExtractor on the env's scene)."""

    def __init__(self, path: str | Path | None = None, spawn: bool = False):
        from dexdrake.systems.rerun_logger import RerunEpisodeLogger

        self.episode = RerunEpisodeLogger(path, spawn=spawn, application_id="dexdrake_dexrep")
        self.rec = self.episode.rec
        self._scene = None

    def _extractor_for(self, scene) -> FeatureExtractor:
        if scene is not self._scene:
            geometry = object_geometry(scene.object_info.name)
            self._extractor = FeatureExtractor(scene.hand, scene.plant, scene.hand_instance, geometry, "Occ+Surf")
            self._centres = voxel_centres(scene.hand.occupancy.size, scene.hand.occupancy.resolution)
            self._scene = scene
        return self._extractor

    def log_step(self, env, info: dict | None) -> None:
        """Logs the episode state and the DexRep parts of the env's current state."""
        self.episode.log_step(env, info)  # sets this step's time on the recording
        extractor = self._extractor_for(env.scene)
        snap = extractor.snapshot(env.plant_context, env.scene.object_pose(env.plant_context))
        rec, hand = self.rec, extractor.hand
        X = snap.X_WG
        rec.log("world/dexrep/grid", rr.Transform3D(translation=X[:3, 3], mat3x3=X[:3, :3]))
        half = hand.occupancy.size / hand.occupancy.resolution / 2
        occupied = self._centres[snap.occupancy > 0.5]
        rec.log("world/dexrep/grid/voxels", rr.Boxes3D(centers=occupied, half_sizes=np.full_like(occupied, half),
                                                        colors=[[240, 170, 40, 120]]))
        p, c = snap.hand_points, snap.closest.points
        rec.log("world/dexrep/hand_points", rr.Points3D(p, radii=0.003, colors=[[40, 200, 90]],
                                                        labels=[pt.name for pt in hand.dexrep_points]))
        rec.log("world/dexrep/closest_points", rr.Points3D(c, radii=0.002, colors=[[230, 60, 200]]))
        rec.log("world/dexrep/links", rr.LineStrips3D(np.stack([p, c], axis=1), radii=0.0006, colors=[[150, 150, 150]]))
        rec.log("world/dexrep/normals", rr.Arrows3D(origins=c, vectors=snap.closest.normals * NORMAL_LENGTH,
                                                    colors=[[60, 120, 250]]))
        d = np.clip(snap.closest.distance, 0.0, SURFACE_CLIP)
        for pt, value in zip(hand.dexrep_points, d):
            rec.log(f"dexrep/distance/{pt.name}", rr.Scalars(float(value)))
        rec.log("dexrep/occupied_voxels", rr.Scalars(float(len(occupied))))

    def close(self) -> None:
        self.episode.close()


def show_features(object_name: str, hand: str = "adroit", rrd: str | Path | None = None, seed: int = 0,
                  steps: int = 200, spawn: bool = False):
    """Runs a scripted-grasp episode on `object_name` and logs its DexRep to rerun
    (to `rrd`, or a live viewer with spawn=True). Returns the EpisodeResult."""
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.scene import SceneConfig
    from dexdrake.systems.scripted_grasp import ScriptedGrasp

    env = GraspEnv(SceneConfig(hand=hand, object=object_name), horizon=steps)
    logger = DexRepEpisodeLogger(rrd, spawn=spawn)
    try:
        return env.rollout(ScriptedGrasp, seed, logger=logger)
    finally:
        logger.close()
