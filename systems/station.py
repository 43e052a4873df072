"""The station: one diagram for sim, hardware-in-the-loop and real, built from a Scenario.

Every mode exposes the same ports (PORTS; policy joint order of the hand description):
  input  "command"      joint position set-points (n)
  output "hand_state"   measured [q; v] (2n)
  output "object_pose"  [x, y, z, qw, qx, qy, qz]
and the sim station also "query_object" (see sim below).
sim:  the Drake grasp scene (systems/scene.py); its set-points are clamped and
      rate-limited, and its joints' speeds checked, as the drivers would (an overspeed is
      a StationFault; systems/target_limits.py), and its "object_pose" is the pose the
      scenario's perception model delivers (noise, frames, latency: PerceivedPoseSystem),
      so that training, sim and hil agree. Also output "query_object" (SceneGraph's
      QueryObject, for DexRepSystem's SceneGraph feature path).
hil:  DriverSystem around the Allegro CAN driver (on a python-can `virtual` bus, talking to
      the firmware emulator) and around the Z1 UDP client (talking to the controller emulator
      on loopback, free ports), both emulators' joints driven by `HilWorld` (a Drake plant;
      every device and the control loop run on its simulated clock, in lockstep with the
      hand's PD loop and never faster than real time: see systems/hil_world.py); object
      pose from PerceptionSystem (rendered RGB-D of the world -> segmentation ->
      registration of the first pose, then tracking frame to frame, in a worker process;
      during the episode on the simulated clock, each pose used one camera period after
      its frame, moved on to the present at its track's velocity) or, with
      camera kind "sim", straight from the world.
real: the same driver systems on socketcan / the real z1_controller, each driver in its own
      process by default (`process` of a driver entry; hardware/driver_process.py), and a
      K4A camera (read in a thread that keeps the newest frame) with the same PerceptionSystem.
      With `emulated_world` drivers they serve a wall-clock HilWorld in a process of its own
      (systems/emulated_world.py) and the rendered camera draws its object where it is now.

Safety at the station level (the drivers keep their own limits, watchdogs and safe stop):
- `Station` is a context manager; leaving it (normally, by exception, Ctrl-C or SIGTERM)
  stops every driver (Allegro: zero torque, servo off; Z1: PASSIVE) and the emulators.
- A driver that latches a fault (e.g. a stalled stream) makes its system raise
  StationFault at its next update, which ends the episode and triggers the safe stop.
- A non-finite controller output is never sent: ControllerSystem holds the last command
  (dexdrake/command_guard.py, the rule of every mode).
- real: every command passes `workspace_guard` (systems/workspace.py) before the drivers: one
  whose palm centre or a fingertip leaves the scenario's workspace box raises StationFault;
  `Station.send`, the moves around a real episode (systems/real_episode.py), checks the same.
- Perception failures (a failed camera read, lost tracking that global registration cannot
  recover, a crashed worker) hold the last pose; after `max_consecutive_failures` failures in a
  row the camera's `on_failure` applies (hold: keep holding; stop: StationFault). No pose
  at most `max_pose_age_s` old within `first_pose_timeout_s` (the first, by global
  registration, may be older: the episode waits for the tracking after it) raises
  StationFault. Once one came, the age of the last pose's frame (failures, a registration
  or a worker that does not finish) is limited in two stages: older than the camera's
  `hold_pose_age_s`, the station holds (`PoseAgeHold`: the drivers get the joint positions
  measured when the hold began instead of the controller's command, and the "object_pose"
  port keeps its last value: the stale pose, moved on further, is not fed to the features)
  until a younger pose comes; older than `max_pose_age_s`, StationFault.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import multiprocessing
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np
from pydrake.common.eigen_geometry import AngleAxis, Quaternion
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import (
    Context,
    Diagram,
    DiagramBuilder,
    DiscreteValues,
    LeafSystem,
)
from pydrake.systems.primitives import Demultiplexer, MatrixGain, Multiplexer

from dexdrake.errors import DexdrakeError, StationFault
from dexdrake.hands.description import HandDescription, load_hand
from dexdrake.command_guard import CommandGuard
from dexdrake.perceived_pose import PerceivedPose, PerceptionModel
from dexdrake.systems.scenario import CameraDriver, Scenario, driver_configs, own_process, process_config

PORTS = {"inputs": ("command",), "outputs": ("hand_state", "object_pose")}


# ----------------------------------------------------------------------------- helpers
def pose_vector(X: RigidTransform) -> np.ndarray:
    """[x, y, z, qw, qx, qy, qz] of a pose."""
    q = X.rotation().ToQuaternion()
    return np.concatenate([X.translation(), [q.w(), q.x(), q.y(), q.z()]])


def pose_from_vector(x: np.ndarray) -> RigidTransform:
    """The pose of a [x, y, z, qw, qx, qy, qz] vector (quaternion normalised)."""
    q = np.asarray(x[3:7], float)
    q = q / np.linalg.norm(q)
    return RigidTransform(Quaternion(q), np.asarray(x[:3], float))


class LoopTimer:
    """Times of periodic calls on the diagram's clock (the simulated clock in hil) and on
    the wall clock, for loop rate and jitter statistics."""

    def __init__(self) -> None:
        self.times: list[float] = []
        self.wall_times: list[float] = []

    def tick(self, t: float) -> None:
        self.times.append(t)
        self.wall_times.append(time.monotonic())

    def stats(self) -> dict[str, float]:
        """period_stats on the diagram clock, plus the wall-clock rate and p99 period."""
        from dexdrake.hardware.safety import period_stats

        out = period_stats(self.times)
        wall = period_stats(self.wall_times)
        out.update(wall_rate_hz=wall["rate_hz"], wall_p99_ms=wall["p99_ms"])
        return out


# ----------------------------------------------------------------------------- drivers
class DriverSystem(LeafSystem):
    """Wraps a started joint driver (`AllegroHand`, bus order, or `Z1Arm`): input
    "q_command" (n), output "state" ([q; dq], 2n). Every `period` the state is sampled
    before the controller runs (an unrestricted update: Drake applies those before the
    same instant's discrete updates, so the controller reads this instant's measurement)
    and the command the controller computed from it is sent right after (a publish event,
    which sees the instant's updates): no control period of latency is added on either side,
    like the simulated station, whose controller reads the plant's state of the instant and
    whose set-points act from the next plant step. Raises StationFault when the driver has
    latched a fault (the driver is then in its safe stop) or is not running (never started:
    a station built for a dry run; or stopped), so that no command is ever stored for a
    driver that is not running."""

    def __init__(self, driver, num_joints: int, period: float, label: str):
        super().__init__()
        self.driver, self.label = driver, label
        self._cmd = self.DeclareVectorInputPort("q_command", num_joints)
        st = driver.state()  # the default state is the measured one, so initial commands hold
        state = self.DeclareDiscreteState(np.nan_to_num(np.concatenate([st.q, st.dq])))
        self.DeclareStateOutputPort("state", state)
        self.DeclareInitializationDiscreteUpdateEvent(self._read)
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, 0.0, self._sample)
        self.DeclarePeriodicPublishEvent(period, 0.0, self._send)

    def _read(self, context: Context, state: DiscreteValues) -> None:
        st = self.driver.state()
        if st.fault is not None:
            raise StationFault(f"{self.label} fault: {st.fault} (driver is in its safe stop)")
        if not self.driver.running:
            raise StationFault(f"{self.label}: the driver is not running (stopped, or never started)")
        state.set_value(0, np.concatenate([st.q, st.dq]))

    def _sample(self, context: Context, state) -> None:
        self._read(context, state.get_mutable_discrete_state())

    def _send(self, context: Context) -> None:
        if not self.driver.running:
            fault = self.driver.state().fault  # a driver process that stopped itself says why
            raise StationFault(f"{self.label}: the driver is not running "
                               + (f"({fault})" if fault else "(stopped, or never started)"))
        if self._cmd.HasValue(context):
            self.driver.command_positions(self._cmd.Eval(context))


# ----------------------------------------------------------------------------- perception
_WORKER: dict = {}


def _worker_init(mesh_path: str) -> None:
    """The perception worker: niced (+10) below the control loop and the driver processes,
    so that a global registration's seconds of CPU delay neither."""
    import os

    from dexdrake.hardware.perception import ObjectPoseEstimator

    os.nice(10)
    _WORKER["estimator"] = ObjectPoseEstimator(mesh_path)


def _worker_estimate(color: np.ndarray, depth: np.ndarray, intrinsics: tuple,
                     X_WC: np.ndarray | None, prior: np.ndarray | None = None,
                     track: bool = False) -> dict:
    """The object pose in one frame (in the perception worker process): with `track`,
    refined from `prior` (the last pose, 4x4; ObjectPoseEstimator.track), else, or when
    tracking is lost ("tracking_lost": why), by global registration (of a symmetric object's
    twins the one nearest `prior`). "method": which gave the pose; "cpu_s": this call's CPU."""
    from dexdrake.hardware.kinect import CameraIntrinsics, RgbdFrame
    from dexdrake.hardware.perception import transform_points

    cpu0 = time.process_time()
    est = _WORKER["estimator"]
    pose_C = None if X_WC is None else RigidTransform(X_WC)
    frame = RgbdFrame(color, depth, CameraIntrinsics(*intrinsics), 0.0, pose_C)
    prior_W = None if prior is None else RigidTransform(prior)
    mask, cloud = est.object_points(frame)
    result, method, lost = None, "track", ""
    if track and prior_W is not None:
        result = est.track(frame, prior_W, (mask, cloud))
        lost = result.reason
    if result is None or not result.success:
        result, method = est.estimate(frame, prior_W), "global"
    if pose_C is not None and len(cloud):
        cloud = transform_points(pose_C, cloud)
    return {"success": result.success and result.X_WO is not None,
            "reason": result.reason or ("no camera pose" if result.X_WO is None else ""),
            "X_WO": None if result.X_WO is None else result.X_WO.GetAsMatrix4(),
            "fitness": result.fitness, "mask": mask, "cloud": cloud[::4],
            "elapsed_s": result.elapsed_s, "method": method, "tracking_lost": lost,
            "cpu_s": time.process_time() - cpu0}


def perception_executor(mesh_path: str) -> cf.Executor:
    """A one-process pool that runs registration off the driver threads' interpreter."""
    return cf.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                  initializer=_worker_init, initargs=(str(mesh_path),))


@dataclass
class PerceptionLog:
    """What the perception system saw last (for logging)."""

    frame: object = None
    result: dict | None = None
    failures: int = 0
    consecutive_failures: int = 0
    successes: int = 0
    events: list[str] = field(default_factory=list)
    cpu_s: dict[str, list[float]] = field(default_factory=dict)  # per method ("track", "global"): CPU per frame
    tracking_losses: int = 0


class PerceptionSystem(LeafSystem):
    """Object pose from a camera: every `period_s` a frame is read (`read_frame()`) and
    handed to `executor` (`_worker_estimate`: with the camera's `tracking`, tracked from the
    pose predicted for the frame, else registered globally); results arrive asynchronously.
    Output "object_pose" (7), updated every `period` (default min(period_s, 0.05)): the last
    good pose moved on to the present (`predicted_pose`); see the module doc for the failure
    rules.

    With `simulated_clock` (hil) the episode's frames are paced on the diagram's simulated
    clock and each estimate is used exactly `period_s` of simulated time after its frame
    (an update that finds it unfinished waits: the world is paused at the control step), so
    the pose latency does not depend on the host's speed. Otherwise (real, and while
    waiting for the first pose) the wall clock paces it and estimates are used on arrival."""

    def __init__(self, read_frame: Callable[[], object], executor: cf.Executor,
                 camera: CameraDriver, estimate: Callable = _worker_estimate,
                 on_result: Callable[[PerceptionLog], None] | None = None,
                 simulated_clock: bool = False, period: float | None = None):
        super().__init__()
        self._read_frame, self._executor, self._estimate = read_frame, executor, estimate
        self.camera = camera
        self.simulated_clock = simulated_clock
        self._due = -np.inf  # simulated_clock: when the pending estimate is to be used
        self.on_result = on_result
        self.log = PerceptionLog()
        self._future: cf.Future | None = None
        self._pending_frame = None
        self._t0: float | None = None
        self.has_pose = False
        # a pose at most max_pose_age_s old has come: from then on an older one is a fault (the
        # first, by global registration, may take longer; the tracking after it catches up)
        self.fresh = False
        self.stale = False  # the last pose's frame is older than hold_pose_age_s: the station holds
        self.pose = np.array([0, 0, 0, 1.0, 0, 0, 0])  # the last estimate
        self._now = 0.0  # the clock's time at the last poll (simulated or wall)
        self._frame_time = 0.0  # the clock's time of the pending frame
        self._pose_time = 0.0  # the clock's time of the last pose's frame
        self._motion: list[tuple[float, RigidTransform]] = []  # the last 2 estimates of one track
        state = self.DeclareDiscreteState(self.pose)
        self.DeclareStateOutputPort("object_pose", state)
        self.DeclareStateOutputPort("pose_stale", self.DeclareDiscreteState(1))  # 1.0 while stale
        self.DeclareInitializationDiscreteUpdateEvent(self._init)
        # sampled before the controller runs (an unrestricted update), like DriverSystem's state
        self.DeclarePeriodicUnrestrictedUpdateEvent(period or min(camera.period_s, 0.05), 0.0, self._update)
        self._next_request = 0.0

    def _submit(self) -> None:
        frame = self._read_frame()
        self._pending_frame, self._frame_time = frame, self._now
        k = frame.intrinsics
        X_WC = None if frame.X_WC is None else frame.X_WC.GetAsMatrix4()
        # the prior: the pose predicted for this frame's time (tracking starts from it)
        prior = pose_from_vector(self.predicted_pose()).GetAsMatrix4() if self.has_pose else None
        self._future = self._executor.submit(self._estimate, frame.color, frame.depth,
                                             (k.width, k.height, k.fx, k.fy, k.cx, k.cy), X_WC, prior,
                                             track=self.camera.tracking and self.has_pose)

    def poll(self, sim_time: float | None = None) -> None:
        """Collect a finished estimate and start the next one when due (plain method);
        `sim_time` is the diagram's time (it paces the system with `simulated_clock`)."""
        wall = time.monotonic()
        if self._t0 is None:
            self._t0 = wall
        on_sim = self.simulated_clock and sim_time is not None
        now = self._now = sim_time if on_sim else wall
        cam = self.camera
        due = not on_sim or now >= self._due - 1e-9
        if on_sim and due and self._future is not None:
            cf.wait([self._future])
        if self._future is not None and self._future.done() and due:
            try:
                result = self._future.result()
            except Exception as err:  # a crashed worker is a perception failure
                result = {"success": False, "reason": f"perception worker failed: {err}"}
            self._future = None
            self._record(result, self._pending_frame, sim_time)
        age = now - self._pose_time
        self.fresh = self.fresh or (self.has_pose and age <= cam.max_pose_age_s)
        if not self.fresh and wall - self._t0 > cam.first_pose_timeout_s:
            raise StationFault(f"no object pose within {cam.first_pose_timeout_s} s" if not self.has_pose else
                               f"no object pose younger than {cam.max_pose_age_s} s within "
                               f"{cam.first_pose_timeout_s} s")
        if self.fresh and age > cam.max_pose_age_s:
            raise StationFault(f"object pose {age:.2f} s old (limit {cam.max_pose_age_s} s)")
        stale = self.fresh and age > cam.hold_pose_age_s
        if stale != self.stale:
            self.stale = stale
            self.log.events.append(f"t={sim_time or 0.0:.2f}s: " + (
                f"object pose {age:.2f} s old (hold limit {cam.hold_pose_age_s} s): holding" if stale
                else "object pose fresh again: the controller's commands resume"))
        if self._future is None and now >= self._next_request - 1e-9:
            self._next_request = self._due = now + cam.period_s
            try:
                self._submit()
            except StationFault:
                raise
            except Exception as err:  # a camera that delivers no frame is a perception failure
                self._record({"success": False, "reason": f"camera read failed: {type(err).__name__}: {err}"},
                             None, sim_time)

    def _record(self, result: dict, frame, sim_time: float | None) -> None:
        """Take one outcome: a pose, or a failure (counted; StationFault per the camera's rules)."""
        cam, log = self.camera, self.log
        log.frame, log.result = frame, result
        if "method" in result:
            log.cpu_s.setdefault(result["method"], []).append(result["cpu_s"])
        if result.get("tracking_lost"):
            log.tracking_losses += 1
            log.events.append(f"t={sim_time or 0.0:.2f}s: {result['tracking_lost']}")
        if result["success"]:
            log.successes += 1
            log.consecutive_failures = 0
            self.has_pose = True
            self._pose_time = self._frame_time
            X = RigidTransform(result["X_WO"])
            self.pose = pose_vector(X)
            tracked = result.get("method") == "track"  # a global registration starts a new track
            self._motion = [*self._motion[-1:], (self._frame_time, X)] if tracked else [(self._frame_time, X)]
        else:
            log.failures += 1
            log.consecutive_failures += 1
            log.events.append(f"t={sim_time or 0.0:.2f}s: {result['reason']}")
            if log.consecutive_failures >= cam.max_consecutive_failures and (
                    cam.on_failure == "stop" or not self.has_pose):
                raise StationFault(f"perception failed {log.consecutive_failures} times in a "
                                   f"row (last: {result['reason']})")
        if self.on_result is not None:
            self.on_result(log)

    def wait_for_first_pose(self, check: Callable[[], None] = lambda: None) -> None:
        """Block until a pose at most max_pose_age_s old arrives (StationFault after
        first_pose_timeout_s); `check()` runs between polls (e.g. to raise on a driver fault
        meanwhile)."""
        while not self.fresh:
            self.poll()
            check()
            time.sleep(0.02)

    def _init(self, context: Context, state: DiscreteValues) -> None:
        if self.simulated_clock:  # the episode starts: pace on the simulated clock from here
            self._next_request = self._due = self._now = context.get_time()
            # (the world has been paused at this time since the frames before it were taken)
            self._frame_time = self._pose_time = self._now
            self._motion = [(self._now, X) for _, X in self._motion[-1:]]
        state.set_value(0, self.pose)
        state.set_value(1, [0.0])

    def predicted_pose(self) -> np.ndarray:
        """The last estimate moved on at the velocity between the last two frames of its track
        (translation and rotation) from its frame's time to the last poll's, by at most the
        camera's `predict_s`: the pose now rather than when the frame was taken."""
        if len(self._motion) < 2 or self.camera.predict_s <= 0:
            return self.pose
        (t0, X0), (t1, X1) = self._motion
        if t1 <= t0:
            return self.pose
        h = min(self._now - t1, self.camera.predict_s) / (t1 - t0)
        turn = (X1.rotation() @ X0.rotation().inverse()).ToAngleAxis()
        R = RotationMatrix(AngleAxis(turn.angle() * h, turn.axis())) @ X1.rotation()
        p = X1.translation() + (X1.translation() - X0.translation()) * h
        return pose_vector(RigidTransform(R, p))

    def _update(self, context: Context, state) -> None:
        self.poll(context.get_time())
        discrete = state.get_mutable_discrete_state()
        if not self.stale:  # while stale the port keeps the last pose it had
            discrete.set_value(0, self.predicted_pose())
        discrete.set_value(1, [float(self.stale)])


class PoseAgeHold(LeafSystem):
    """Inputs "command" (n), "hand_state" (2n, measured) and "pose_stale" (1, from
    PerceptionSystem); output "command" (n): the input command while the object pose is
    fresh; while it is stale, the joint positions measured when it went stale, so that the
    hand and the arm hold still rather than follow a controller that sees an old pose. The
    latch ([holding, q]) is discrete state updated every `period`, after the drivers' and
    the perception's samples of the same instant (unrestricted updates come first)."""

    def __init__(self, num_joints: int, period: float):
        super().__init__()
        self.n = num_joints
        self._cmd = self.DeclareVectorInputPort("command", num_joints)
        self._hand = self.DeclareVectorInputPort("hand_state", 2 * num_joints)
        self._stale = self.DeclareVectorInputPort("pose_stale", 1)
        self.DeclareDiscreteState(num_joints + 1)
        self.DeclareVectorOutputPort("command", num_joints, self._calc)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)

    def _update(self, context: Context, state: DiscreteValues) -> None:
        latch = context.get_discrete_state_vector().get_value()
        if self._stale.Eval(context)[0] <= 0.5:
            state.set_value(np.zeros(self.n + 1))
        elif latch[0] <= 0.5:  # the hold begins: keep what is measured now
            state.set_value(np.r_[1.0, self._hand.Eval(context)[: self.n]])

    def _calc(self, context: Context, out) -> None:
        latch = context.get_discrete_state_vector().get_value()
        out.SetFromVector(latch[1:] if latch[0] > 0.5 else self._cmd.Eval(context))


def add_pose_age_hold(builder: DiagramBuilder, to_devices, hand_state, perception: PerceptionSystem,
                      period: float):
    """Put a PoseAgeHold in front of `to_devices` (the input port the devices' command
    enters), fed the measured `hand_state` (an output port, policy order) and `perception`'s
    "pose_stale"; returns the hold's "command" input, the command's new way in."""
    hold = builder.AddNamedSystem("pose_age_hold", PoseAgeHold(to_devices.size(), period))
    builder.Connect(hold.GetOutputPort("command"), to_devices)
    builder.Connect(hand_state, hold.GetInputPort("hand_state"))
    builder.Connect(perception.GetOutputPort("pose_stale"), hold.GetInputPort("pose_stale"))
    return hold.GetInputPort("command")


class WorldPoseSystem(LeafSystem):
    """Object pose read from the HIL world (camera kind "sim": no perception), sampled
    before the controller runs, like DriverSystem's state."""

    def __init__(self, world, period: float):
        super().__init__()
        self.world = world
        state = self.DeclareDiscreteState(pose_vector(world.object_pose()))
        self.DeclareStateOutputPort("object_pose", state)
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, 0.0, self._update)

    def _update(self, context: Context, state) -> None:
        state.get_mutable_discrete_state().set_value(0, pose_vector(self.world.object_pose()))


class PerceivedPoseSystem(LeafSystem):
    """The sim station's object pose as the scenario's perception model delivers it
    (dexdrake/perceived_pose.py: noise, frames, latency): input "true_pose", output
    "object_pose" (both [x, y, z, qw, qx, qy, qz]). `reset(seed)` starts an episode's draws;
    within an episode the output is evaluated at non-decreasing times, as the episode loops do."""

    def __init__(self, model: PerceptionModel, control_period: float):
        super().__init__()
        self.perceived = PerceivedPose(model, control_period)
        self._true = self.DeclareVectorInputPort("true_pose", 7)
        self.DeclareVectorOutputPort("object_pose", 7, self._calc)

    def reset(self, seed: int) -> None:
        self.perceived.reset(seed)

    def seen(self, t: float, X_WO: RigidTransform) -> RigidTransform:
        """The pose seen at time `t` (s) of the true pose `X_WO`."""
        p, R = self.perceived(t, X_WO.translation(), X_WO.rotation().matrix())
        return RigidTransform(RotationMatrix(R), p)

    def _calc(self, context: Context, out) -> None:
        out.SetFromVector(pose_vector(self.seen(context.get_time(), pose_from_vector(self._true.Eval(context)))))


# ----------------------------------------------------------------------------- controller
Controller = Callable[[float, np.ndarray, np.ndarray], np.ndarray]


class ControllerSystem(LeafSystem):
    """Runs `controller(t, hand_state, object_pose) -> q_command` every `period`.

    Inputs "hand_state", "object_pose"; output "command". The command starts at the
    measured position; controller outputs pass `guard` (dexdrake/command_guard.py: a
    non-finite one holds the last command, one beyond the hand's joint limits is clipped;
    `guard.counts`). The update times give the policy rate (`timer`)."""

    def __init__(self, controller: Controller, hand: HandDescription, period: float):
        super().__init__()
        self.controller = controller
        self.n = n = hand.num_actuators
        self.guard = CommandGuard(*hand.joint_limits())
        self.timer = LoopTimer()
        self._hand = self.DeclareVectorInputPort("hand_state", 2 * n)
        self._pose = self.DeclareVectorInputPort("object_pose", 7)
        state = self.DeclareDiscreteState(n)
        self.DeclareStateOutputPort("command", state)
        self.DeclareInitializationDiscreteUpdateEvent(self._init)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)

    def _init(self, context: Context, state: DiscreteValues) -> None:
        state.set_value(0, self._hand.Eval(context)[: self.n])

    def _update(self, context: Context, state: DiscreteValues) -> None:
        self.timer.tick(context.get_time())
        q = self.controller(context.get_time(), self._hand.Eval(context), self._pose.Eval(context))
        state.set_value(0, self.guard(q, context.get_discrete_state(0).get_value()))


# ----------------------------------------------------------------------------- station
@dataclass
class Station:
    """A built station: `diagram` (the common ports), and the devices behind it.

    Use as a context manager around the simulation: entering starts emulators, the HIL
    world and the drivers; leaving stops them all (safe stop), whatever happened."""

    scenario: Scenario
    diagram: Diagram
    hand: HandDescription
    scene: object = None  # sim: the GraspScene
    world: object = None  # hil: the HilWorld; real with emulated_world drivers: its WorldView
    devices: dict = field(default_factory=dict)
    perception: PerceptionSystem | None = None
    perceived: PerceivedPoseSystem | None = None  # sim: the scenario's perception model on "object_pose"
    workspace: object = None  # real: the WorkspaceBox every set-point is checked against
    _stop: contextlib.ExitStack | None = None

    @property
    def mode(self) -> str:
        return self.scenario.mode

    def stop(self) -> None:
        """Safe stop: drivers first (zero torque / PASSIVE), then emulators and the world.
        Idempotent; in the main thread SIGINT and SIGTERM are blocked while it runs (a signal
        that comes meanwhile is delivered after it), so no Ctrl-C cuts it short."""
        if self._stop is None:
            return
        stack, self._stop = self._stop, None
        main = threading.current_thread() is threading.main_thread()
        blocked = {signal.SIGINT, signal.SIGTERM}
        previous = signal.pthread_sigmask(signal.SIG_BLOCK, blocked) if main else None
        try:
            stack.close()
        finally:
            if previous is not None:
                signal.pthread_sigmask(signal.SIG_SETMASK, previous)

    def positions(self) -> np.ndarray:
        """The devices' measured joint positions, policy order (hil/real)."""
        n = self.hand.num_actuators
        arm, fingers = self.devices["z1"].state(), self.devices["allegro"].state()
        for name, st in (("Z1 arm", arm), ("Allegro hand", fingers)):
            if st.fault is not None:
                raise StationFault(f"{name} fault: {st.fault} (driver is in its safe stop)")
        measured = np.concatenate([arm.q, arm.dq, fingers.q, fingers.dq])
        return (_bus_maps(self.hand)[1] @ measured)[:n]

    def send(self, q: np.ndarray) -> None:
        """Joint set-points (policy order) straight to the drivers, past the workspace box
        (StationFault when they leave it): the moves around a real episode."""
        if self.workspace is not None:
            why = self.workspace.violation(q)
            if why is not None:
                raise StationFault(why)
        n_arm = len(self.hand.arm_joints)
        devices = _bus_maps(self.hand)[0] @ np.asarray(q, float)
        self.devices["z1"].command_positions(devices[:n_arm])
        self.devices["allegro"].command_positions(devices[n_arm:])

    def __enter__(self) -> Station:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stats(self) -> dict[str, dict]:
        """Loop statistics of the running devices (CAN, Z1, world)."""
        out = {}
        if "allegro" in self.devices:
            out["can"] = self.devices["allegro"].stats()
        if "z1" in self.devices:
            out["z1"] = self.devices["z1"].stats()
        if self.world is not None:
            out["world"] = self.world.stats()
        return out


def make_station(scenario: Scenario, start: bool = True, world=None) -> Station:
    """Build (and for hil/real, start the devices of) the station of `scenario`.

    For hil/real the devices run from here on: use the result as a context manager (or call
    `stop()`) so that they are stopped safely. `start=False` (real only: `dexdrake real
    --dry-run`) builds the same diagram around drivers that are made but never started:
    the CAN bus is opened, nothing is sent on it or to the Z1, the camera is not opened;
    such a station's DriverSystems raise StationFault if it is ever simulated. `world`: with
    `emulated_world` drivers, the running world's WorldView (systems/emulated_world.py), whose
    object the rendered camera draws and the episode scores."""
    if scenario.mode == "sim":
        return sim_station(scenario)
    if start and scenario.drivers.hand.kind == "emulated_world" and world is None:
        raise DexdrakeError("an emulated_world station needs its running world: start it with "
                            "systems/emulated_world.running_world and pass its WorldView")
    if not start and scenario.mode != "real":
        raise DexdrakeError(f"only a real station is built without starting (a {scenario.mode} "
                            "station's devices are its simulated world)")
    stack = contextlib.ExitStack()
    try:
        return _device_station(scenario, stack, start, world)
    except BaseException:
        stack.close()
        raise


def sim_station(scenario: Scenario) -> Station:
    """The sim station of `scenario` around its grasp scene: the set-points pass the
    drivers' joint limits and target rates, and their overspeed trip raises StationFault
    (systems/target_limits.py), as in hil and real; "object_pose" is the pose the scenario's
    perception model delivers (PerceivedPoseSystem; the true pose when it is exact)."""
    from dexdrake.systems.scene import build_grasp_scene
    from dexdrake.systems.target_limits import OverspeedMonitor, TargetLimiter, overspeed_limits, target_limits

    scene = build_grasp_scene(scenario, desired_state=True)
    builder = DiagramBuilder()
    sub = builder.AddNamedSystem("scene", scene.diagram)
    limiter = builder.AddNamedSystem("driver_target_limits", TargetLimiter(
        target_limits(scenario, scene.hand), scenario.time_step, scenario.control_period))
    builder.ExportInput(limiter.GetInputPort("command"), "command")
    builder.Connect(sub.GetOutputPort("hand_state"), limiter.GetInputPort("hand_state"))
    builder.Connect(limiter.GetOutputPort("desired_state"), sub.GetInputPort("desired_state"))
    overspeed = overspeed_limits(scenario, scene.hand)
    if overspeed is not None:
        monitor = builder.AddNamedSystem("driver_overspeed", OverspeedMonitor(
            *overspeed, scenario.time_step, list(scene.hand.policy_joints)))
        builder.Connect(sub.GetOutputPort("hand_state"), monitor.GetInputPort("hand_state"))
    perceived = None
    if not scenario.perception.is_exact:
        perceived = builder.AddNamedSystem("perceived_pose", PerceivedPoseSystem(
            scenario.perception, scenario.control_period))
        builder.Connect(sub.GetOutputPort("object_pose"), perceived.GetInputPort("true_pose"))
    builder.ExportOutput(sub.GetOutputPort("hand_state"), "hand_state")
    builder.ExportOutput((perceived or sub).GetOutputPort("object_pose"), "object_pose")
    builder.ExportOutput(sub.GetOutputPort("query_object"), "query_object")
    return Station(scenario, builder.Build(), scene.hand, scene=scene, perceived=perceived)


def _bus_maps(hand: HandDescription) -> tuple[np.ndarray, np.ndarray]:
    """(select, assemble): command (n) -> [arm (6); fingers (16, bus)] and
    [arm q; arm v; hand q; hand v] -> [q; v] in policy order."""
    n, n_arm = hand.num_actuators, len(hand.arm_joints)
    perm = hand.hardware_permutation()
    S = np.zeros((n, n))
    S[np.arange(n_arm), np.arange(n_arm)] = 1.0
    S[n_arm + np.arange(len(perm)), perm] = 1.0
    A = np.zeros((2 * n, 2 * n))
    nf = len(perm)
    for i in range(n_arm):
        A[i, i] = 1.0  # arm q
        A[n + i, n_arm + i] = 1.0  # arm v
    for k, p in enumerate(perm):
        A[p, 2 * n_arm + k] = 1.0  # hand q
        A[n + p, 2 * n_arm + nf + k] = 1.0  # hand v
    return S, A


def can_bus_args(scenario: Scenario) -> dict:
    """The can.Bus keyword arguments of the hand driver entry."""
    h = scenario.drivers.hand
    port = {} if h.port is None else {"port": h.port}
    return dict(interface=h.interface, channel=h.channel, bitrate=h.bitrate, receive_own_messages=False, **port)


def open_can_bus(scenario: Scenario):
    """The python-can bus of the hand driver entry (hardware/can_bus.open_can_bus);
    HardwareError when it cannot open."""
    from dexdrake.hardware import can_bus

    return can_bus.open_can_bus(can_bus_args(scenario))


def hil_drive(scenario: Scenario, hand: HandDescription):
    """The HIL world's joint drive (systems/scene.JointDrive): the arm's PD is the Z1
    controller's (the scenario's LOWCMD gains, else the model's, times the controller's gain
    scales); the fingers are torque-driven with the firmware emulator's PWM model
    (ddq = accel_per_pwm * pwm - damping * dq) at the scenario's torque per PWM count."""
    from dexdrake.hardware.allegro_emulator import EmulatorConfig
    from dexdrake.hardware.z1_model import KD_SCALE, KP_SCALE, z1_model
    from dexdrake.systems.scene import JointDrive

    arm, limits, emu = scenario.drivers.arm, z1_model().limits, EmulatorConfig()
    kp = limits.kp if arm.kp is None else np.asarray(arm.kp, float)
    kd = limits.kd if arm.kd is None else np.asarray(arm.kd, float)
    n_fingers = hand.num_actuators - len(hand.arm_joints)
    inertia = scenario.torque_per_pwm / emu.accel_per_pwm  # kg*m^2 reflected per finger joint
    return JointDrive(kp=np.r_[kp * KP_SCALE, np.zeros(n_fingers)], kd=np.r_[kd * KD_SCALE, np.zeros(n_fingers)],
                      rotor_inertia=np.r_[np.zeros(len(kp)), np.full(n_fingers, inertia)],
                      damping=np.r_[np.zeros(len(kp)), np.full(n_fingers, inertia * emu.damping)])


def start_world(scenario: Scenario, stack: contextlib.ExitStack, hand: HandDescription):
    """The scenario's grasp scene (with the HIL joint drive) as a started HilWorld, with the
    CAN firmware emulator on the hand entry's bus and the Z1 emulator on UDP: hil's world, and
    the wall-clock world's in its own process (systems/emulated_world.py)."""
    from dexdrake.systems.hil_world import HilWorld
    from dexdrake.systems.scene import ObjectPlacement, build_grasp_scene

    placement = ObjectPlacement.from_seed(scenario.seed)
    scene = build_grasp_scene(scenario, hil_drive(scenario, hand), sampled_outputs=True)
    emu_bus = open_can_bus(scenario)
    stack.callback(emu_bus.shutdown)
    world = HilWorld(scenario, scene, emu_bus, hand.pregrasp_vector(), placement)
    world.start()
    stack.callback(world.stop)
    return world


def _await_first_cycle(allegro, timeout: float = 1.0) -> None:
    from dexdrake.hardware.safety import HardwareError

    deadline = time.monotonic() + timeout
    while not np.isfinite(allegro.state().t):
        if time.monotonic() > deadline:
            raise HardwareError(f"Allegro: no complete position cycle within {timeout} s of start")
        time.sleep(0.005)


def _device_station(scenario: Scenario, stack: contextlib.ExitStack, start: bool, world=None) -> Station:
    """hil/real: drivers of the scenario (a started real station runs each driver entry
    with `process` in its own process, hardware/driver_process.py; a dry run's drivers are
    never started and stay in-process), the diagram around them, perception."""
    from dexdrake.hardware.allegro_can import AllegroHand
    from dexdrake.hardware.driver_process import DriverProcess, allegro_on_bus, z1_client
    from dexdrake.hardware.z1_udp import Z1Arm

    hand = load_hand(scenario.hand)
    devices: dict = {}
    arm_port = arm_local_port = None
    clock = time.monotonic
    if scenario.mode == "hil":  # every device runs on the world's simulated clock
        world = start_world(scenario, stack, hand)
        devices["allegro_emulator"], devices["z1_emulator"] = world.hand_emulator, world.arm_emulator
        arm_port, arm_local_port, clock = world.arm_emulator.port, world.arm_client_port, world.clock
    hand_cfg, arm_cfg = driver_configs(scenario, arm_port, arm_local_port)
    if scenario.mode == "hil":  # a sample of the arm's state sees the world's reply of its last step;
        arm_cfg = replace(arm_cfg, reply_wait_s=scenario.hil.reply_timeout_s)  # the hand's speed is
        hand_cfg = replace(hand_cfg, receive_timestamps=False)  # timed on the simulated clock
    executor = None
    cam = scenario.drivers.camera
    if cam.kind != "sim":
        from dexdrake.objects.library import get_object

        executor = perception_executor(str(get_object(scenario.object).mesh_path))
        stack.callback(executor.shutdown, wait=False, cancel_futures=True)
        if start:  # its process's spawn, imports and model set-up, before any driver loop runs
            executor.submit(time.monotonic).result()
    # opened (a rendered camera's first frame sets its renderer up) before any driver loop runs
    read_frame = camera_reader(scenario, world, stack) if start and executor is not None else _unopened_camera
    hand_entry, arm_entry = scenario.drivers.hand, scenario.drivers.arm
    if start and own_process(hand_entry):
        allegro = DriverProcess(partial(allegro_on_bus, can_bus_args(scenario), hand_entry.device_id,
                                        hand_cfg), process_config(hand_entry), "Allegro hand")
    else:
        bus = open_can_bus(scenario)
        stack.callback(bus.shutdown)
        allegro = AllegroHand(bus, hand_entry.device_id, hand_cfg, clock=clock)
    if start and own_process(arm_entry):
        z1 = DriverProcess(partial(z1_client, arm_cfg), process_config(arm_entry), "Z1 arm")
    else:
        z1 = Z1Arm(arm_cfg, clock=clock)
    devices["allegro"], devices["z1"] = allegro, z1
    if scenario.mode == "hil":  # the world steps in lockstep with the Z1 client's ticks once it runs
        world.attach_arm_client(z1)
    if start:
        stack.enter_context(allegro)  # starts; its exit is the hand's safe stop
        _await_first_cycle(allegro)
        stack.enter_context(z1)

    period = scenario.control_period
    n, n_arm = hand.num_actuators, len(hand.arm_joints)
    S, A = _bus_maps(hand)
    builder = DiagramBuilder()
    select = builder.AddNamedSystem("command_to_devices", MatrixGain(S))
    to_devices = select.get_input_port()  # the command's way in, built backwards
    workspace = None
    if scenario.mode == "real":  # every set-point the controller sends keeps the hand in the box
        from dexdrake.systems.workspace import WorkspaceBox, WorkspaceGuard

        workspace = WorkspaceBox(hand, scenario.real.workspace_lower, scenario.real.workspace_upper)
        guard = builder.AddNamedSystem("workspace_guard", WorkspaceGuard(workspace, n, StationFault))
        builder.Connect(guard.get_output_port(), to_devices)
        to_devices = guard.get_input_port()
    arm_sys = builder.AddNamedSystem("z1_driver", DriverSystem(z1, n_arm, period, "Z1 arm"))
    hand_sys = builder.AddNamedSystem("allegro_driver",
                                      DriverSystem(allegro, len(hand.hardware_joints), period, "Allegro hand"))
    split = builder.AddSystem(Demultiplexer([n_arm, n - n_arm]))
    builder.Connect(select.get_output_port(), split.get_input_port())
    builder.Connect(split.get_output_port(0), arm_sys.get_input_port())
    builder.Connect(split.get_output_port(1), hand_sys.get_input_port())
    mux = builder.AddSystem(Multiplexer([2 * n_arm, 2 * (n - n_arm)]))
    builder.Connect(arm_sys.get_output_port(), mux.get_input_port(0))
    builder.Connect(hand_sys.get_output_port(), mux.get_input_port(1))
    assemble = builder.AddNamedSystem("devices_to_hand_state", MatrixGain(A))
    builder.Connect(mux.get_output_port(), assemble.get_input_port())
    builder.ExportOutput(assemble.get_output_port(), "hand_state")

    perception = None
    if executor is None:
        pose_sys = builder.AddNamedSystem("world_pose", WorldPoseSystem(world, period))
    else:
        perception = pose_sys = builder.AddNamedSystem("perception", PerceptionSystem(
            read_frame, executor, cam, simulated_clock=scenario.mode == "hil", period=period))
        to_devices = add_pose_age_hold(builder, to_devices, assemble.get_output_port(), perception, period)
    builder.ExportInput(to_devices, "command")
    builder.ExportOutput(pose_sys.GetOutputPort("object_pose"), "object_pose")
    station = Station(scenario, builder.Build(), hand, world=world, devices=devices, perception=perception,
                      workspace=workspace)
    station._stop = stack.pop_all()
    return station


def _unopened_camera():
    raise StationFault("the camera of a station built without starting is never read")


def _camera_pose(cam: CameraDriver) -> RigidTransform:
    from dexdrake.hardware.kinect import look_at

    return look_at(cam.eye, cam.target)


def camera_reader(scenario: Scenario, world, stack: contextlib.ExitStack) -> Callable[[], object]:
    """A function returning the next RgbdFrame of the configured camera."""
    from dexdrake.hardware.kinect import (
        DepthNoiseModel, DrakeRenderedCamera, K4ADevice, LatestFrame, RecordedSequence,
    )
    from dexdrake.objects.library import get_object

    cam = scenario.drivers.camera
    X_WC = _camera_pose(cam)
    if cam.kind == "rendered":  # hil, emulated_world: the world's object; emulated_process: a static scene
        from dexdrake.systems.scene import ObjectPlacement

        info = get_object(scenario.object)
        source = DrakeRenderedCamera(X_WC, {info.name: info.mesh_path}, cam.width, cam.height,
                                     DepthNoiseModel() if cam.depth_noise else None, scenario.seed)
        static = ObjectPlacement.from_seed(scenario.seed).pose(info)

        def place() -> None:
            source.set_object_pose(info.name, static if world is None else world.object_pose())

        def read():
            place()
            return source.read()

        place()
        source.warm_up()  # not in the control loop: the first render holds the interpreter for up to 1 s
        return read
    if cam.kind == "recorded":
        source = RecordedSequence(cam.recording, loop=True)
    else:
        source = LatestFrame(K4ADevice(cam.device_id, X_WC=X_WC))  # reads never block the loop
    stack.callback(source.close)

    def read_posed():
        frame = source.read()
        if frame.X_WC is None:
            from dexdrake.hardware.kinect import RgbdFrame

            frame = RgbdFrame(frame.color, frame.depth, frame.intrinsics, frame.timestamp, X_WC)
        return frame

    return read_posed
