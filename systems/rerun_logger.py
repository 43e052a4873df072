"""The one rerun logger: every mode (sim, eval, demo, hil, real) records its episodes with
the same entities and sends the same blueprint (viewer layout), adding only what it has.

Entities (time lines `step`, control steps over the whole recording, `sim_time`, seconds,
and `episode`):
  world/table, world/hand/<body>/geom<k>        static geometry
  world/object/mesh                             the object's mesh (again when it changes)
  world/hand/<body>, world/object               Transform3D per step
  world/fingertips                              Points3D per step
  world/dexrep/{grid, grid/voxels, hand_points, closest_points, links, normals}
  dexrep/distance/<point>
  joints/<group>/<joint>/{q, cmd}               measured and commanded, per finger (`arm`,
                                                `wrist` and one group per fingertip)
  task/lift, task/band/{low, high}, task/success, reward/{r_d, r_g, r_t, total}
  episodes                                      TextLog: object and seed of each episode
hil and real add (from the station):
  world/object_true (hil: the emulated world's object)
  camera/{image, depth, mask}, world/cloud, world/registered, perception/{fitness, error_m}
  loop/<can|z1|policy|world>/..., latency/..., faults/<counter>, faults/log
The blueprint: the 3D scene large (left), its eye framing hand and object, with the DexRep
view and (with a camera) the camera images one tab away; on the right the task panel (lift
against the success band, reward terms, success), the joints grouped per finger (command
and measured in one plot), and for hil/real the loop rates, latencies and faults.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import trimesh
from pydrake.geometry import Box, Capsule, Convex, Cylinder, Mesh, Role, Sphere
from pydrake.math import RigidTransform

from dexdrake.dexrep.feature_sets import FeatureExtractor
from dexdrake.dexrep.features import SURFACE_CLIP
from dexdrake.dexrep.occupancy import occupied_voxels
from dexdrake.errors import DexdrakeError
from dexdrake.task import SuccessTracker, TaskSpec, reward_terms
from dexdrake.systems.grasp_env import GraspEnv
from dexdrake.systems.scenario import simulated
from dexdrake.systems.scene import TABLE_SIZE, GraspScene
from dexdrake.systems.station import pose_from_vector

MODES = ("sim", "eval", "demo", "hil", "real")
STATION_MODES = ("hil", "real")  # modes whose episodes run on the station (drivers, perception)
NORMAL_LENGTH = 0.02  # m, drawn length of the DexRep normal arrows
SERIES_BATCH = 50  # control steps of scalars sent at once
_PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
            (227, 119, 194), (127, 127, 127)]


def _quat_xyzw(X: RigidTransform) -> list[float]:
    q = X.rotation().ToQuaternion()
    return [q.x(), q.y(), q.z(), q.w()]


def _transform(X: RigidTransform) -> rr.Transform3D:
    return rr.Transform3D(translation=X.translation(), quaternion=rr.Quaternion(xyzw=_quat_xyzw(X)))


def joint_groups(scene: GraspScene) -> dict[str, list[str]]:
    """Policy joints grouped for plotting: `arm`, then one group per fingertip (the joints
    that move only that tip, named after it: fftip -> ff, index_tip -> index), then `wrist`
    (joints moving several tips). Read from the model's kinematic tree."""
    plant, hand, inst = scene.plant, scene.hand, scene.hand_instance
    tips = {p.name.removesuffix("tip").rstrip("_"): plant.GetBodyByName(p.body, inst).index()
            for p in hand.fingertips}
    groups: dict[str, list[str]] = {"arm": list(hand.arm_joints), **{f: [] for f in tips}, "wrist": []}
    for name in hand.policy_joints[len(hand.arm_joints):]:
        moved = set(plant.GetBodiesKinematicallyAffectedBy([plant.GetJointByName(name, inst).index()]))
        fingers = [f for f, body in tips.items() if body in moved]
        groups[fingers[0] if len(fingers) == 1 else "wrist"].append(name)
    return {g: joints for g, joints in groups.items() if joints}


def eye_framing(scene: GraspScene, plant_context, task: TaskSpec = TaskSpec()) -> tuple[np.ndarray, np.ndarray]:
    """(eye position, look target) of a 3D view framing the hand (palm and fingertips), the
    object and its lift target: seen from the side of the fingers' direction, from above."""
    plant, hand, inst = scene.plant, scene.hand, scene.hand_instance
    X_WP = plant.EvalBodyPoseInWorld(plant_context, plant.GetBodyByName(hand.palm.body, inst))
    palm = X_WP.multiply(np.array(hand.palm.centre))
    tips = [plant.EvalBodyPoseInWorld(plant_context, plant.GetBodyByName(p.body, inst)).multiply(np.array(p.offset))
            for p in hand.fingertips]
    p_obj = scene.object_pose(plant_context).translation()
    points = np.array([palm, *tips, p_obj, p_obj + [0, 0, task.target_height]])
    target = (points.min(axis=0) + points.max(axis=0)) / 2
    radius = max(float(np.linalg.norm(points - target, axis=1).max()), 0.1)
    fingers = np.mean(tips, axis=0) - palm
    fingers[2] = 0.0
    fingers = fingers / np.linalg.norm(fingers) if np.linalg.norm(fingers) > 1e-3 else np.array([0.0, 1.0, 0.0])
    side = np.array([fingers[1], -fingers[0], 0.0])
    direction = side + 0.4 * fingers + np.array([0.0, 0.0, 0.6])
    return target + 2.5 * radius * direction / np.linalg.norm(direction), target


def blueprint(mode: str, groups: dict[str, list[str]], eye: np.ndarray, target: np.ndarray,
              camera: bool = False) -> rrb.Blueprint:
    """The viewer layout of a recording (see the module doc); `camera`: the recording has
    camera images (hil/real with perception)."""
    eye_controls = rrb.EyeControls3D(position=eye, look_target=target, eye_up=[0.0, 0.0, 1.0])
    scene = rrb.Spatial3DView(name="Scene", origin="world", contents=["+ /world/**", "- /world/dexrep/**"],
                              eye_controls=eye_controls)
    dexrep = rrb.Horizontal(
        rrb.Spatial3DView(name="DexRep: voxels, hand points, closest points", origin="world",
                          contents=["+ /world/dexrep/**", "+ /world/object/**", "+ /world/hand/**"],
                          eye_controls=eye_controls),
        rrb.TimeSeriesView(name="DexRep distances (m)", origin="dexrep/distance"),
        column_shares=[3, 1], name="DexRep")
    left = [scene, dexrep]
    if camera:
        left.append(rrb.Vertical(
            rrb.Horizontal(rrb.Spatial2DView(name="Camera image and mask", origin="camera",
                                             contents=["+ /camera/image", "+ /camera/mask"]),
                           rrb.Spatial2DView(name="Depth", origin="camera/depth")),
            rrb.TimeSeriesView(name="Perception: fitness, error against the truth (m)", origin="perception"),
            row_shares=[2, 1], name="Camera"))
    task = [rrb.TimeSeriesView(name="Lift (m) and the success band", contents=["+ /task/lift", "+ /task/band/**"]),
            rrb.TimeSeriesView(name="Reward terms and success", contents=["+ /reward/**", "+ /task/success"])]
    if mode == "eval":  # many episodes: which object and seed each is
        task.append(rrb.TextLogView(name="Episodes", origin="episodes"))
    task = rrb.Vertical(*task, name="Task")
    joints = rrb.Grid(*[rrb.TimeSeriesView(name=f"{group} joints: measured (thick), command (thin)",
                                           origin=f"joints/{group}") for group in groups], name="Joints")
    right = [task, joints]
    if mode in STATION_MODES:
        right.append(rrb.Horizontal(
            rrb.TimeSeriesView(name="Loop rates (Hz)", origin="loop"),
            rrb.TimeSeriesView(name="Latencies (ms)", origin="latency"),
            rrb.Vertical(rrb.TimeSeriesView(name="Fault counters", contents=["+ /faults/**", "- /faults/log"]),
                         rrb.TextLogView(name="Faults and events", contents=["+ /faults/log"])),
            name="Station"))
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Tabs(*left, name="3D"), rrb.Vertical(*right, row_shares=[2, 3, 2][:len(right)]),
                       column_shares=[3, 2]),
        rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="expanded", timeline="step"))


IMAGE_PERIOD_S = 0.5  # camera images (colour, depth, mask) are recorded about this often; poses at every frame


class RerunLogger:
    """Records episodes to an .rrd file (or a live viewer with spawn=True) in one of MODES.

    sim, eval, demo: `log_step(env, info)` after each `GraspEnv.reset` (info None) and step,
    hooked into the one episode loop by `hooks(env)`. hil, real and a sim station (`dexdrake
    sim --config`): `RerunLogger(..., scenario=scenario)`, `attach(station)`, and `systems/diagram.run_station_episode` calls
    `log_station_step` every control step and `log_fault` on the fault that ends the episode;
    perception results are logged as they arrive. The blueprint is sent with the first
    episode (its eye frames that episode's hand and object)."""

    def __init__(self, path: str | Path | None, mode: str, spawn: bool = False, scenario=None):
        if mode not in MODES:
            raise DexdrakeError(f"unknown recording mode {mode!r}; one of {', '.join(MODES)}")
        if mode in STATION_MODES and scenario is None:
            raise DexdrakeError(f"a {mode} recording needs a scenario")
        if scenario is not None and mode not in (*STATION_MODES, "sim"):  # sim: `dexdrake sim --config`
            raise DexdrakeError(f"a {mode} recording takes no scenario")
        self.mode, self.station = mode, None
        self.rec = rr.RecordingStream(f"dexdrake_{mode}")
        if path is not None:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(str(path))
        elif spawn:
            self.rec.spawn()
        self._step, self._episode = -1, -1
        self._groups: dict[str, list[str]] | None = None  # set with the blueprint
        self._scene: GraspScene | None = None
        self._extractors: dict[int, FeatureExtractor] = {}
        self._mirror = None  # station modes: a GraspEnv holding the measured state
        self._tracker: SuccessTracker | None = None
        self._faults: dict[str, str] = {}
        self._perception_results = 0
        self._image_every = 1  # log the camera's images with every k-th perception result
        self._series: dict[str, list[tuple[int, float, int, float]]] = {}  # scalars not yet sent
        self._time = (0, 0.0, 0)  # (step, sim_time, episode) of the current step
        if scenario is not None:  # built before the station starts its devices
            self._mirror = GraspEnv(simulated(scenario), horizon=1)
            self._image_every = max(1, round(IMAGE_PERIOD_S / scenario.drivers.camera.period_s))

    def attach(self, station) -> None:
        """Records `station`'s loop (hil, real): its devices' statistics and perception results."""
        self.station = station
        if station.perception is not None:
            station.perception.on_result = self.log_perception

    # ------------------------------------------------------------------ sim, eval, demo
    def log_step(self, env, info: dict | None) -> None:
        """Logs `env`'s current state; `info` is the step's info dict (None at a reset,
        which starts a new episode; a step whose info has a fault ends the episode with it,
        its state not logged, e.g. a diverged simulation's)."""
        self._set_time(env.context.get_time(), new_episode=info is None)
        if info is not None and info.get("fault"):
            self.log_fault(info["fault"])
            return
        if info is None:
            self._start_episode(env.scene, env.plant_context, env.seed)
        self._log_state(env)
        if info is not None:
            self._log_task(info)

    def hooks(self, env) -> dict:
        """`on_reset` and `on_step` for the one episode loop (dexdrake/episode.run_episode)
        that log every reset and step of `env` here."""
        return {"on_reset": lambda: self.log_step(env, None), "on_step": lambda reward, info: self.log_step(env, info)}

    # ------------------------------------------------------------------ hil, real
    def log_station_step(self, t: float, hand_state: np.ndarray, command: np.ndarray, object_pose: np.ndarray,
                         policy_stats: dict, true_pose: RigidTransform | None = None) -> None:
        """One control step of the station at time `t`: measured `hand_state` [q; v], the
        `command`, the perceived `object_pose` [x, y, z, qw, qx, qy, qz], the controller's
        `policy_stats` (rates, bad commands held or clipped) and, in sim and hil, the
        `true_pose` of the object.
        The task is scored on the true pose when there is one, else on the perceived one;
        the scene and DexRep show what the controller sees."""
        env = self._mirror
        scene, ctx = env.scene, env.plant_context
        q = scene.plant.GetPositions(ctx).copy()
        q[scene.q_index] = hand_state[: scene.hand.num_actuators]
        scene.plant.SetPositions(ctx, q)
        X_WO = pose_from_vector(object_pose)
        scored = true_pose if true_pose is not None else X_WO
        scene.plant.SetFreeBodyPose(ctx, scene.object_body, scored)
        p = scored.translation()
        first = self._tracker is None
        if first:
            env.p_start = p.copy()
            self._tracker = SuccessTracker(env.p_start, env.task)
        info = {"terms": reward_terms(env.fingertip_distances(), p, env.p_start, env.task),
                "lift": float(p[2] - env.p_start[2]), "success": self._tracker.update(p)}
        scene.plant.SetFreeBodyPose(ctx, scene.object_body, X_WO)
        self._set_time(t, new_episode=first)
        if first:
            sc = self.station.scenario
            self._start_episode(scene, ctx, sc.seed)
            self.rec.log("faults/log", rr.TextLog(f"{sc.mode} episode started: {sc.hand}, {sc.object}, camera "
                                                  f"{sc.drivers.camera.kind}", level=rr.TextLogLevel.INFO))
        env.q_command = np.asarray(command, float)
        self._log_state(env)
        self._log_task(info)
        if true_pose is not None:
            self.rec.log("world/object_true", _transform(true_pose))
            if self.station.perception is not None:
                self._scalar("perception/error_m", float(np.linalg.norm(p - X_WO.translation())))
        self._log_station_stats({**self.station.stats(), "policy": policy_stats})

    def log_fault(self, text: str) -> None:
        """The fault that stopped the episode (at the last logged step)."""
        self.rec.log("faults/log", rr.TextLog(text, level=rr.TextLogLevel.CRITICAL))

    def log_perception(self, log) -> None:
        """One perception result (a `PerceptionLog`), on the `perception` time line."""
        rec = self.rec
        self._perception_results += 1
        rec.set_time("perception", sequence=self._perception_results)
        frame, result = log.frame, log.result or {}
        if (self._perception_results - 1) % self._image_every == 0:
            if frame is not None:
                rec.log("camera/image", rr.Image(frame.color))
                rec.log("camera/depth", rr.DepthImage(frame.depth, meter=1000.0))
            if result.get("mask") is not None:
                rec.log("camera/mask", rr.SegmentationImage(result["mask"].astype(np.uint8)))
        if result.get("cloud") is not None and len(result["cloud"]):
            rec.log("world/cloud", rr.Points3D(result["cloud"], radii=0.002, colors=[[200, 200, 60]]))
        if result.get("success"):
            X = np.asarray(result["X_WO"])
            rec.log("world/registered", rr.Transform3D(mat3x3=X[:3, :3], translation=X[:3, 3]))
        elif result:
            rec.log("faults/log", rr.TextLog(f"perception: {result.get('reason') or 'failed'}",
                                             level=rr.TextLogLevel.WARN))
        rec.log("perception/fitness", rr.Scalars(float(result.get("fitness", 0.0))))
        if "elapsed_s" in result:
            rec.log("latency/perception_ms", rr.Scalars(1e3 * float(result["elapsed_s"])))
        rec.log("faults/perception/failures", rr.Scalars(float(log.failures)))

    def close(self) -> None:
        self._send_series()
        self.rec.flush()
        self.rec.disconnect()

    # ------------------------------------------------------------------ common
    def _set_time(self, t: float, new_episode: bool) -> None:
        self._step += 1
        self._episode += int(new_episode)
        self.rec.set_time("step", sequence=self._step)
        self.rec.set_time("sim_time", duration=t)
        self.rec.set_time("episode", sequence=self._episode)
        self._time = (self._step, t, self._episode)
        if self._step % SERIES_BATCH == 0:
            self._send_series()

    def _scalar(self, path: str, value: float) -> None:
        """A scalar of the current step (sent in columns: one rr.log per scalar costs ~0.2 ms)."""
        self._series.setdefault(path, []).append((*self._time, value))

    def _send_series(self) -> None:
        for path, rows in self._series.items():
            step, t, episode, value = zip(*rows)
            self.rec.send_columns(path, indexes=[rr.TimeColumn("step", sequence=step),
                                                 rr.TimeColumn("sim_time", duration=t),
                                                 rr.TimeColumn("episode", sequence=episode)],
                                  columns=rr.Scalars.columns(scalars=value))
        self._series.clear()

    def _start_episode(self, scene: GraspScene, plant_context, seed) -> None:
        if self._groups is None:
            self._groups = joint_groups(scene)
            eye, target = eye_framing(scene, plant_context)
            camera = self.station is not None and self.station.perception is not None
            self.rec.send_blueprint(blueprint(self.mode, self._groups, eye, target, camera))
            self._log_static(scene)
        if scene is not self._scene:
            self._scene = scene
            mesh = trimesh.load(scene.object_info.mesh_path, force="mesh")
            shown = [("world/object/mesh", [60, 140, 220, 255])]
            if self.station is not None and self.station.world is not None:
                shown.append(("world/object_true/mesh", [60, 220, 120, 90]))
            for path, color in shown:
                self.rec.log(path, rr.Mesh3D(vertex_positions=mesh.vertices, triangle_indices=mesh.faces,
                                             vertex_normals=mesh.vertex_normals, albedo_factor=color))
        self.rec.log("episodes", rr.TextLog(f"episode {self._episode}: {scene.object_info.name} seed {seed}"))

    def _log_static(self, scene: GraspScene) -> None:
        rec, plant, inspector = self.rec, scene.plant, scene.scene_graph.model_inspector()
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        half = np.array(TABLE_SIZE) / 2
        rec.log("world/table", rr.Boxes3D(half_sizes=[half], centers=[[0, 0, -half[2]]], colors=[[115, 90, 64]]),
                static=True)
        for index in plant.GetBodyIndices(scene.hand_instance):
            frame_id = plant.GetBodyFrameIdIfExists(index)
            if frame_id is None:
                continue
            for k, g in enumerate(inspector.GetGeometries(frame_id, Role.kProximity)):
                archetype = _shape_archetype(inspector.GetShape(g), inspector.GetPoseInFrame(g))
                if archetype is not None:
                    rec.log(f"world/hand/{plant.get_body(index).name()}/geom{k}", archetype, static=True)
        task = TaskSpec()
        styles = {"task/lift": ((31, 119, 180), 3.0, "lift"),
                  "task/band/low": ((150, 150, 150), 1.0, "success band low"),
                  "task/band/high": ((150, 150, 150), 1.0, "success band high"),
                  "task/success": ((44, 160, 44), 3.0, "success"),
                  "reward/total": ((0, 0, 0), 2.5, "total"), "reward/r_d": ((255, 127, 14), 1.5, "r_d (distance)"),
                  "reward/r_g": ((148, 103, 189), 1.5, f"r_g (lifted > {task.lift_threshold} m)"),
                  "reward/r_t": ((214, 39, 40), 1.5, "r_t (near target)")}
        for path, (color, width, name) in styles.items():
            rec.log(path, rr.SeriesLines(colors=[color], widths=[width], names=[name]), static=True)
        for group, joints in self._groups.items():
            for k, joint in enumerate(joints):
                color = _PALETTE[k % len(_PALETTE)]
                rec.log(f"joints/{group}/{joint}/q", rr.SeriesLines(colors=[color], widths=[2.5], names=[joint]),
                        static=True)
                rec.log(f"joints/{group}/{joint}/cmd",
                        rr.SeriesLines(colors=[color], widths=[1.0], names=[f"{joint} cmd"]), static=True)

    def _log_state(self, env: GraspEnv) -> None:
        """The hand, the object, the fingertips, the joints (measured, commanded) and DexRep."""
        rec, scene, plant_context = self.rec, env.scene, env.plant_context
        plant = scene.plant
        for index in plant.GetBodyIndices(scene.hand_instance):
            body = plant.get_body(index)
            rec.log(f"world/hand/{body.name()}", _transform(plant.EvalBodyPoseInWorld(plant_context, body)))
        X_WO = scene.object_pose(plant_context)
        rec.log("world/object", _transform(X_WO))
        rec.log("world/fingertips", rr.Points3D(env.points_in_world(scene.hand.fingertips), radii=0.004,
                                                colors=[[250, 80, 80]]))
        q = dict(zip(scene.hand.policy_joints, scene.hand_positions(plant_context)))
        cmd = dict(zip(scene.hand.policy_joints, env.q_command))
        for group, joints in self._groups.items():
            for joint in joints:
                self._scalar(f"joints/{group}/{joint}/q", float(q[joint]))
                self._scalar(f"joints/{group}/{joint}/cmd", float(cmd[joint]))
        self._log_dexrep(scene, plant_context, X_WO)

    def _log_dexrep(self, scene: GraspScene, plant_context, X_WO: RigidTransform) -> None:
        key = id(scene)
        if key not in self._extractors:
            from dexdrake.dexrep.geometry import load_object_geometry

            self._extractors[key] = FeatureExtractor(scene.hand, scene.plant, scene.hand_instance,
                                                     load_object_geometry(scene.object_info.mesh_path), "Occ+Surf")
        hand, rec = scene.hand, self.rec
        snap = self._extractors[key].snapshot(plant_context, X_WO)
        X = snap.X_WG
        rec.log("world/dexrep/grid", rr.Transform3D(translation=X[:3, 3], mat3x3=X[:3, :3]))
        centres, half = occupied_voxels(snap.occupancy, hand.occupancy.size, hand.occupancy.resolution)
        rec.log("world/dexrep/grid/voxels", rr.Boxes3D(centers=centres, half_sizes=np.full_like(centres, half),
                                                        colors=[[240, 170, 40, 120]]))
        p, c = snap.hand_points, snap.closest.points
        rec.log("world/dexrep/hand_points", rr.Points3D(p, radii=0.003, colors=[[40, 200, 90]],
                                                        labels=[pt.name for pt in hand.dexrep_points]))
        rec.log("world/dexrep/closest_points", rr.Points3D(c, radii=0.002, colors=[[230, 60, 200]]))
        rec.log("world/dexrep/links", rr.LineStrips3D(np.stack([p, c], axis=1), radii=0.0006, colors=[[150, 150, 150]]))
        rec.log("world/dexrep/normals", rr.Arrows3D(origins=c, vectors=snap.closest.normals * NORMAL_LENGTH,
                                                    colors=[[60, 120, 250]]))
        for pt, value in zip(hand.dexrep_points, np.clip(snap.closest.distance, 0.0, SURFACE_CLIP)):
            self._scalar(f"dexrep/distance/{pt.name}", float(value))

    def _log_task(self, info: dict) -> None:
        task, terms = TaskSpec(), info["terms"]
        for key, value in (("r_d", terms.r_d), ("r_g", terms.r_g), ("r_t", terms.r_t), ("total", terms.total)):
            self._scalar(f"reward/{key}", float(value))
        self._scalar("task/lift", float(info["lift"]))
        self._scalar("task/band/low", task.target_height - task.success_radius)
        self._scalar("task/band/high", task.target_height + task.success_radius)
        self._scalar("task/success", float(info["success"]))

    def _log_station_stats(self, stats: dict) -> None:
        rec = self.rec
        for device, s in stats.items():
            if "rate_hz" in s:
                self._scalar(f"loop/{device}/rate_hz", float(s["rate_hz"]))
            if "wall_rate_hz" in s:
                self._scalar(f"loop/{device}/wall_rate_hz", float(s["wall_rate_hz"]))
            for key in ("p99_ms", "max_ms", "step_p99_ms", "wall_p99_ms"):
                if np.isfinite(s.get(key, np.nan)):
                    self._scalar(f"latency/{device}/{key}", float(s[key]))
            if "lag_s" in s:
                self._scalar(f"latency/{device}/lag_ms", 1e3 * float(s["lag_s"]))
            for key in ("rejected_commands", "clamped_commands", "torque_clamped", "duplicates", "late_replies",
                        "non_finite", "clipped"):
                if key in s:
                    self._scalar(f"faults/{device}/{key}", float(s[key]))
            for key in ("frame_errors", "packet_errors"):
                if key in s:
                    self._scalar(f"faults/{device}/{key}", float(sum(s[key].values())))
            fault = s.get("fault")
            if fault and self._faults.get(device) != fault:
                self._faults[device] = fault
                rec.log("faults/log", rr.TextLog(f"{device}: {fault}", level=rr.TextLogLevel.ERROR))


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
