"""rerun logging of grasp episodes: geometry, poses, joints, commands, reward terms.

Entity layout (all under `world/`):
  world/hand/<body>            Transform3D per step; its collision shapes logged once
  world/object                 Transform3D per step; its watertight mesh logged once
  world/table                  the table box
  joints/q/<joint>, joints/cmd/<joint>   scalars per control step
  reward/{r_d,r_g,r_t,total}, task/lift, task/success   scalars per control step
Time lines: `step` (control steps) and `sim_time` (seconds).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr
import trimesh
from pydrake.geometry import Box, Capsule, Convex, Cylinder, Mesh, Role, Sphere
from pydrake.math import RigidTransform

from dexdrake.systems.scene import TABLE_SIZE, GraspScene


def _quat_xyzw(X: RigidTransform) -> list[float]:
    q = X.rotation().ToQuaternion()
    return [q.x(), q.y(), q.z(), q.w()]


def _transform(X: RigidTransform) -> rr.Transform3D:
    return rr.Transform3D(translation=X.translation(), quaternion=rr.Quaternion(xyzw=_quat_xyzw(X)))


class RerunEpisodeLogger:
    """Records episodes of a `GraspEnv` to an .rrd file (or a live viewer with spawn=True)."""

    def __init__(self, path: str | Path | None = None, spawn: bool = False, application_id: str = "dexdrake"):
        self.rec = rr.RecordingStream(application_id)
        if path is not None:
            self.rec.save(str(path))
        elif spawn:
            self.rec.spawn()
        self._scene: GraspScene | None = None
        self._step = 0

    def _log_static_scene(self, scene: GraspScene) -> None:
        rec = self.rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        half = np.array(TABLE_SIZE) / 2
        rec.log("world/table", rr.Boxes3D(half_sizes=[half], centers=[[0, 0, -half[2]]], colors=[[115, 90, 64]]), static=True)
        mesh = trimesh.load(scene.object_info.mesh_path, force="mesh")
        rec.log(
            "world/object/mesh",
            rr.Mesh3D(vertex_positions=mesh.vertices, triangle_indices=mesh.faces, vertex_normals=mesh.vertex_normals,
                      albedo_factor=[60, 140, 220, 255]),
            static=True,
        )
        plant, inspector = scene.plant, scene.scene_graph.model_inspector()
        for index in plant.GetBodyIndices(scene.hand_instance):
            body = plant.get_body(index)
            frame_id = plant.GetBodyFrameIdIfExists(index)
            if frame_id is None:
                continue
            for k, g in enumerate(inspector.GetGeometries(frame_id, Role.kProximity)):
                archetype = _shape_archetype(inspector.GetShape(g), inspector.GetPoseInFrame(g))
                if archetype is not None:
                    rec.log(f"world/hand/{body.name()}/geom{k}", archetype, static=True)

    def log_step(self, env, info: dict | None) -> None:
        """Logs the env's current state; `info` is the step's info dict (None at reset)."""
        scene = env.scene
        if scene is not self._scene:
            self._log_static_scene(scene)
            self._scene = scene
        rec, plant, ctx = self.rec, scene.plant, env.plant_context
        rec.set_time("step", sequence=self._step)
        rec.set_time("sim_time", duration=env.context.get_time())
        self._step += 1
        for index in plant.GetBodyIndices(scene.hand_instance):
            body = plant.get_body(index)
            rec.log(f"world/hand/{body.name()}", _transform(plant.EvalBodyPoseInWorld(ctx, body)))
        rec.log("world/object", _transform(scene.object_pose(ctx)))
        tips = env.points_in_world(scene.hand.fingertips)
        rec.log("world/fingertips", rr.Points3D(tips, radii=0.004, colors=[[250, 80, 80]]))
        q = scene.hand_positions(ctx)
        for name, value, cmd in zip(scene.hand.policy_joints, q, env.q_command):
            rec.log(f"joints/q/{name}", rr.Scalars(value))
            rec.log(f"joints/cmd/{name}", rr.Scalars(cmd))
        if info is not None:
            terms = info["terms"]
            for key, value in (("r_d", terms.r_d), ("r_g", terms.r_g), ("r_t", terms.r_t), ("total", terms.total)):
                rec.log(f"reward/{key}", rr.Scalars(value))
            rec.log("task/lift", rr.Scalars(info["lift"]))
            rec.log("task/success", rr.Scalars(float(info["success"])))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()


def _shape_archetype(shape, X_FG: RigidTransform):
    """A rerun archetype drawing a SceneGraph shape posed at X_FG in its frame."""
    centre, quat = [X_FG.translation()], [rr.Quaternion(xyzw=_quat_xyzw(X_FG))]
    if isinstance(shape, Capsule):
        # rerun capsules run along their local +z from the origin.
        start = X_FG.multiply([0.0, 0.0, -shape.length() / 2])
        return rr.Capsules3D(lengths=[shape.length()], radii=[shape.radius()], translations=[start], quaternions=quat)
    if isinstance(shape, Box):
        return rr.Boxes3D(half_sizes=[[shape.width() / 2, shape.depth() / 2, shape.height() / 2]], centers=centre,
                          quaternions=quat)
    if isinstance(shape, Sphere):
        return rr.Ellipsoids3D(radii=[shape.radius()], centers=centre)
    if isinstance(shape, Cylinder):
        return rr.Ellipsoids3D(half_sizes=[[shape.radius(), shape.radius(), shape.length() / 2]], centers=centre,
                               quaternions=quat)
    if isinstance(shape, (Mesh, Convex)):
        mesh = trimesh.load(shape.filename(), force="mesh")
        vertices = X_FG.multiply(mesh.vertices.T * shape.scale()).T
        return rr.Mesh3D(vertex_positions=vertices, triangle_indices=mesh.faces)
    return None
