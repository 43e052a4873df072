"""Station tests: scenarios, identical ports across modes, HIL episodes and fault injection."""

import concurrent.futures as cf
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from rrd_content import blueprint_tree, logged_rows, matches

from dexdrake.systems.scenario import ScenarioError, load_scenario, parse_scenario

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def hil_scenario(camera: str = "sim"):
    s = load_scenario(CONFIGS / "hil.yaml")
    s.drivers.camera.kind = camera
    return s


def test_shipped_scenarios_load():
    modes = {name: load_scenario(CONFIGS / f"{name}.yaml").mode for name in ("sim", "hil", "real")}
    assert modes == {"sim": "sim", "hil": "hil", "real": "real"}
    real = load_scenario(CONFIGS / "real.yaml")
    assert real.drivers.hand.interface == "socketcan" and real.drivers.camera.kind == "k4a"


@pytest.mark.parametrize("text, message", [
    ("drivers: {hand: {kindd: sim}}", "unknown to the schema"),
    ("drivers: {hand: {kind: robot}, arm: {kind: robot}}", "not one of sim, emulated, emulated_process, emulated_world, hardware"),
    ("drivers: {hand: {kind: emulated}, arm: {kind: sim}}", "must match"),
    ("drivers: {hand: {kind: emulated}, arm: {kind: emulated}, camera: {kind: k4a}}",
     "not available in hil mode"),
    ("drivers: {hand: {kind: emulated, kp: [1, 2]}, arm: {kind: emulated}}", "kp: need 16 finite"),
    ("drivers: {hand: {kind: emulated, pwm_limit: [2000, 675, 450, 285, 375, 675, 450, 285, 375, 675, "
     "450, 285, 525, 405, 270, 270]}, arm: {kind: emulated}}",
     r"pwm_limit\[0\] = 2000 exceeds the vendor PWM limit 375"),
    ("drivers: {hand: {kind: emulated}, arm: {kind: emulated, max_velocity: 1.0e9}}",
     "max_velocity 1e\\+09 rad/s must be in"),
    ("drivers: {hand: {kind: emulated}, arm: {kind: emulated, kp: [20, 30, 300, 20, 15, 10]}}",
     r"kp\[2\] = 300 exceeds the LOWCMD gain 30 of joint3"),
    ("drivers: {hand: {kind: hardware}, arm: {kind: hardware, local_port: 0}, camera: {kind: k4a}}",
     "only allowed with an emulated arm"),
    ("drivers: {hand: {kind: emulated, port: 0}, arm: {kind: emulated}}", "drivers.hand.port 0 is not a UDP port"),
    ("drivers: {hand: {kind: emulated_world, interface: udp_multicast, channel: 239.74.163.3}, "
     "arm: {kind: emulated_world}, camera: {kind: recorded, recording: x.npz}}",
     r"drivers.camera.kind 'recorded' is not available in real mode \(use one of rendered\)"),
    ("drivers: {hand: {kind: emulated, process: true}, arm: {kind: emulated}}",
     "drivers.hand.process: the simulated-clock HIL"),
    ("drivers: {hand: {kind: hardware, process: false, realtime_priority: 50}, arm: {kind: hardware}, "
     "camera: {kind: k4a}}", "drivers.hand.realtime_priority 50: 1..99, for a driver in its own process"),
    ("drivers: {hand: {kind: hardware}, arm: {kind: hardware, realtime_priority: 100}, camera: {kind: k4a}}",
     "drivers.arm.realtime_priority 100"),
    ("drivers: {hand: {kind: hardware, heartbeat_timeout_s: 0.005}, arm: {kind: hardware}, camera: {kind: k4a}}",
     r"drivers.hand.heartbeat_timeout_s must be a finite time longer than the heartbeat's period \(0.01 s\), "
     "got 0.005"),
    ("drivers: {hand: {kind: hardware}, arm: {kind: hardware, process: false, heartbeat_timeout_s: 1.0}, "
     "camera: {kind: k4a}}", "drivers.arm.heartbeat_timeout_s: only a driver in its own process"),
    ("drivers: {hand: {kind: emulated}, arm: {kind: emulated}, camera: {kind: rendered, "
     "hold_pose_age_s: 3.0}}", r"need period_s \(0.5\) <= hold_pose_age_s \(3.0\) <= max_pose_age_s \(2.0\)"),
    ("drivers: {hand: {kind: emulated}, arm: {kind: emulated}, camera: {kind: rendered, "
     "hold_pose_age_s: 0.1}}", r"hold_pose_age_s \(0.1\)"),
    ("drivers: {hand: {kind: emulated, limit_margin_rad: 0.5}, arm: {kind: emulated}}",
     r"Allegro limit_margin_rad 0.5 must be >= 0 and leave every joint a range"),
    ("drivers: {hand: {kind: emulated}, arm: {kind: emulated, limit_margin_rad: -0.1}}",
     r"Z1 limit_margin_rad -0.1 must be >= 0"),
    ("object: no_such_object", "unknown object"),
    ("hand: adroit\ndrivers: {hand: {kind: emulated}, arm: {kind: emulated}}", "no Allegro-on-Z1"),
    ("control_period: 0.001", "must be >= time_step"),
    ("time_step: [1]", "time_step"),
    ("hil: {reply_timeout_s: 0}", "reply_timeout_s must be > 0"),
    ("policy: {checkpoint: p.pt, feature_path: exact}", "feature_path 'exact' is not one of fast, scenegraph"),
    ("drivers: {hand: {kind: emulated}, arm: {kind: emulated}}\npolicy: {checkpoint: p.pt, "
     "feature_path: scenegraph}", "'scenegraph' needs the simulated object's SceneGraph; in hil mode"),
])
def test_bad_scenarios_are_refused_with_a_clear_message(text, message):
    with pytest.raises(ScenarioError, match=message):
        parse_scenario(text, source="bad.yaml")


def test_joint_margins_come_from_the_scenario():
    """drivers.*.limit_margin_rad reaches the drivers: targets clamp that far inside the
    joint limits (default 0.02 rad), never onto them."""
    from dexdrake.hardware.allegro_can import check_allegro_config
    from dexdrake.hardware.z1_udp import check_z1_config
    from dexdrake.systems.scenario import driver_configs

    text = "drivers: {hand: {kind: emulated, limit_margin_rad: 0.05}, arm: {kind: emulated, limit_margin_rad: 0.1}}"
    hand, arm = driver_configs(parse_scenario(text))
    hs, zs = check_allegro_config(hand), check_z1_config(arm)
    np.testing.assert_allclose(hs.target_upper, hs.upper - 0.05)
    np.testing.assert_allclose(zs.target_lower, zs.lower + 0.1)
    hand, arm = driver_configs(parse_scenario("drivers: {hand: {kind: emulated}, arm: {kind: emulated}}"))
    assert hand.limit_margin_rad == arm.limit_margin_rad == 0.02


def test_missing_scenario_file():
    with pytest.raises(ScenarioError, match="does not exist"):
        load_scenario("no/such/scenario.yaml")


def _ports(diagram):
    return ([diagram.get_input_port(i).get_name() for i in range(diagram.num_input_ports())],
            [diagram.get_output_port(i).get_name() for i in range(diagram.num_output_ports())])


def _hold_then(offset: np.ndarray, after: float = 0.0, nan_after: float | None = None):
    """A controller commanding the first measured position plus `offset` (from `after` s),
    and NaN from `nan_after` s on."""
    start = {}

    def controller(t, hand_state, object_pose):
        n = len(offset)
        start.setdefault("q", hand_state[:n].copy())
        if nan_after is not None and t >= nan_after:
            return np.full(n, np.nan)
        return start["q"] + (offset if t >= after else 0.0)

    return controller


# one joint of every finger, both directions, thumb included (policy joint name -> offset, rad)
FINGER_OFFSETS = {"joint_0.0": 0.2, "joint_5.0": 0.5, "joint_10.0": 0.4, "joint_12.0": -0.4,
                  "joint_15.0": 0.3}


def _track_finger_offsets(station, steps: int = 40, world_minus_control: list | None = None):
    """Command FINGER_OFFSETS from the start pose; (start q, end q, offsets, result).
    `world_minus_control` collects world time - control time at every controller call."""
    from dexdrake.systems.diagram import run_station_episode

    hand = station.hand
    offset = np.zeros(hand.num_actuators)
    for joint, value in FINGER_OFFSETS.items():
        offset[hand.policy_joints.index(joint)] = value
    hold = _hold_then(offset)

    def controller(t, hand_state, object_pose):
        if world_minus_control is not None:
            world_minus_control.append(station.world.time - t)
        return hold(t, hand_state, object_pose)

    q0 = station.world.robot_positions()
    result = run_station_episode(station, controller, steps=steps)
    return q0, station.world.robot_positions(), offset, result


def _assert_tracks(q0, q1, offset, n_arm):
    """Commanded finger joints reach their targets, the others and the arm hold still."""
    moved = q1 - q0
    error = np.abs(moved - offset)
    assert np.max(error[n_arm:]) < 0.03, f"finger tracking errors {np.round(error[n_arm:], 3)}"
    assert np.max(np.abs(moved[:n_arm])) < 0.01, f"arm moved {np.round(moved[:n_arm], 4)}"


def test_sim_and_hil_expose_identical_ports_and_hil_joints_track_commands():
    from dexdrake.systems.station import make_station

    sim = make_station(load_scenario(CONFIGS / "sim.yaml"))
    with make_station(hil_scenario()) as station:
        assert _ports(station.diagram) == (["command"], ["hand_state", "object_pose"])
        # the sim station adds SceneGraph's QueryObject (DexRepSystem's SceneGraph path) only
        assert _ports(sim.diagram) == (["command"], ["hand_state", "object_pose", "query_object"])
        q0, q1, offset, result = _track_finger_offsets(station)
        world = station.world.stats()
    assert result.fault is None and result.steps == 40
    _assert_tracks(q0, q1, offset, len(station.hand.arm_joints))
    # every device runs on the world's clock: the CAN PD loop at 333 Hz of simulated time,
    # the control loop in lockstep at 50 Hz
    assert result.stats["can"]["rate_hz"] == pytest.approx(1000 / 3, rel=0.05)
    assert result.stats["policy"]["rate_hz"] == pytest.approx(50.0, rel=1e-6)
    assert result.stats["z1"]["packets_received"] > 50
    assert world["real_time_factor"] <= 1.05  # never faster than real time


def test_hil_outcome_does_not_depend_on_host_speed(monkeypatch):
    """A world that takes 3x real time per step (a loaded host) slows the episode down but
    tracks exactly as well: the drivers' PD, rate limits and watchdogs run on its clock."""
    import time

    from dexdrake.systems.hil_world import HilWorld
    from dexdrake.systems.station import make_station

    step = HilWorld.step

    def slow_step(self):
        time.sleep(2 * self.scenario.time_step)
        step(self)

    monkeypatch.setattr(HilWorld, "step", slow_step)
    offsets: list[float] = []
    with make_station(hil_scenario()) as station:
        q0, q1, offset, result = _track_finger_offsets(station, world_minus_control=offsets)
        world = station.world.stats()
    assert result.fault is None and result.steps == 40
    assert world["real_time_factor"] < 0.5
    _assert_tracks(q0, q1, offset, len(station.hand.arm_joints))
    # the control loop is in lockstep with the world: every policy step sees the world
    # exactly one fixed offset after its own time
    assert len(offsets) == 40 and np.ptp(offsets) < 1e-9


def _grasp_centre(hand, q: np.ndarray) -> np.ndarray:
    """The palm's grasp centre in the world at joint positions `q` (policy order)."""
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    plant = MultibodyPlant(0.0)
    (robot,) = Parser(plant).AddModels(str(hand.model_path))
    plant.Finalize()
    context = plant.CreateDefaultContext()
    for name, value in zip(hand.policy_joints, q):
        plant.GetJointByName(name, robot).set_angle(context, value)
    X = plant.EvalBodyPoseInWorld(context, plant.GetBodyByName(hand.palm.body, robot))
    return X @ np.array(hand.palm.centre)


def test_hil_episode_driven_by_the_shipped_policy():
    """`dexdrake hil`'s controller: the shipped Allegro-on-Z1 policy commands the emulated
    Allegro over CAN and the emulated Z1 over UDP (ground-truth pose here; the slow test
    and `dexdrake hil` use perception on rendered images). In 0.6 s it brings the grasp
    centre at least 5 cm nearer the object, wherever the object then is (a mirrored command
    moves it 0.6 m away)."""
    from dexdrake.systems.controllers import make_controller
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.station import make_station

    scenario = hil_scenario()
    controller, description = make_controller(scenario)
    assert controller.get_name() == "policy", description
    with make_station(scenario) as station:
        q0, p0 = station.world.robot_positions(), station.world.object_pose().translation()
        result = run_station_episode(station, controller, steps=30)
        q1, p1 = station.world.robot_positions(), station.world.object_pose().translation()
    assert result.fault is None and result.steps == 30
    assert result.stats["policy"]["rate_hz"] == pytest.approx(50.0, rel=1e-6)
    assert result.stats["z1"]["packets_received"] > 50 and result.stats["can"]["rate_hz"] > 300
    d0 = np.linalg.norm(_grasp_centre(station.hand, q0) - p0)
    d1 = np.linalg.norm(_grasp_centre(station.hand, q1) - p1)
    assert d1 < d0 - 0.05, (d0, d1)  # the arm moved toward the object


def test_controller_slot_holds_non_finite_and_clips_out_of_range_commands():
    """The station's controller slot applies the one bad-command rule (dexdrake/command_guard.py)."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import ConstantVectorSource

    from dexdrake.hands.description import load_hand
    from dexdrake.systems.station import ControllerSystem

    hand = load_hand("allegro_z1")
    n, (lo, hi) = hand.num_actuators, hand.joint_limits()
    q0 = (lo + hi) / 2

    def controller(t, hand_state, object_pose):
        if t > 0.045:
            return np.full(n, np.inf)
        q = q0.copy()
        q[0] = hi[0] + 1.0
        return q

    builder = DiagramBuilder()
    ctrl = builder.AddSystem(ControllerSystem(controller, hand, 0.01))
    state = builder.AddSystem(ConstantVectorSource(np.concatenate([q0, np.zeros(n)])))
    pose = builder.AddSystem(ConstantVectorSource(np.array([0, 0, 0, 1.0, 0, 0, 0])))
    builder.Connect(state.get_output_port(), ctrl.GetInputPort("hand_state"))
    builder.Connect(pose.get_output_port(), ctrl.GetInputPort("object_pose"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.AdvanceTo(0.085)
    command = ctrl.get_output_port().Eval(ctrl.GetMyContextFromRoot(simulator.get_context()))
    assert command[0] == hi[0] and np.array_equal(command[1:], q0[1:])
    assert ctrl.guard.counts == {"non_finite": 4, "clipped": 5}


def test_nan_command_holds_and_is_never_sent():
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.station import make_station

    with make_station(hil_scenario()) as station:
        n = station.hand.num_actuators
        q0 = station.world.robot_positions()
        result = run_station_episode(station, _hold_then(np.zeros(n), nan_after=0.1), steps=25)
        q1 = station.world.robot_positions()
        stats = station.stats()
    assert result.fault is None
    assert result.stats["policy"]["non_finite"] >= 15 and result.stats["policy"]["clipped"] == 0
    assert stats["can"]["rejected_commands"] == 0 and stats["z1"]["rejected_commands"] == 0
    n_arm = len(station.hand.arm_joints)
    assert np.max(np.abs(q1[:n_arm] - q0[:n_arm])) < 0.05


@pytest.mark.parametrize("device", ["allegro", "z1"])
def test_stalled_emulator_stream_ends_in_safe_state(device):
    from dexdrake.hardware.z1_udp import ArmFSMState
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.station import make_station

    with make_station(hil_scenario()) as station:
        emulator = station.devices[f"{device}_emulator"]
        hold, calls = _hold_then(np.zeros(station.hand.num_actuators)), []

        def controller(t, hand_state, object_pose):  # the stream stalls 5 steps into the episode
            calls.append(t)
            if len(calls) == 5:
                emulator.stall(2.0)
            return hold(t, hand_state, object_pose)

        result = run_station_episode(station, controller, steps=100)
        assert result.fault is not None and 5 <= result.steps < 100
        assert ("Allegro" if device == "allegro" else "Z1") in result.fault
    # after the station's exit every device is in its safe state
    hand_emu, arm_emu = station.devices["allegro_emulator"], station.devices["z1_emulator"]
    assert not hand_emu.servo_on and not np.any(hand_emu.pwm)
    assert arm_emu.fsm == ArmFSMState.PASSIVE
    assert not station.devices["allegro"].running and not station.devices["z1"].running


# ----------------------------------------------------------------------------- perception
class _Frame:
    def __init__(self):
        from dexdrake.hardware.kinect import CameraIntrinsics

        self.color = np.zeros((4, 4, 3), np.uint8)
        self.depth = np.zeros((4, 4), np.uint16)
        self.intrinsics = CameraIntrinsics(4, 4, 2.0, 2.0, 2.0, 2.0)
        self.X_WC = None


def _perception(outcomes, on_failure="hold", max_failures=2):
    """A PerceptionSystem whose estimates are `outcomes` (a pose 4x4 or None = failure)."""
    from dexdrake.systems.scenario import CameraDriver
    from dexdrake.systems.station import PerceptionSystem

    results = iter(outcomes)

    def estimate(color, depth, intrinsics, X_WC, prior=None, track=False):
        X = next(results)
        return {"success": X is not None, "reason": "segmentation found no object" if X is None else "",
                "X_WO": X, "fitness": 0.9 if X is not None else 0.0}

    camera = CameraDriver(kind="rendered", period_s=1e-6, first_pose_timeout_s=5.0,
                          max_consecutive_failures=max_failures, on_failure=on_failure)
    return PerceptionSystem(_Frame, cf.ThreadPoolExecutor(1), camera, estimate)


def test_perception_on_the_simulated_clock_uses_each_pose_one_period_after_its_frame():
    """hil: the latency is period_s of simulated time, however fast or slow the worker."""
    import threading

    from dexdrake.systems.scenario import CameraDriver
    from dexdrake.systems.station import PerceptionSystem

    frames, release = [], threading.Event()

    def estimate(color, depth, intrinsics, X_WC, prior=None, track=False):
        release.wait(5.0)  # the first estimate finishes only when the test says so
        X = np.eye(4)
        X[0, 3] = len(frames)
        return {"success": True, "reason": "", "X_WO": X, "fitness": 1.0}

    def read_frame():
        frames.append(1)
        return _Frame()

    camera = CameraDriver(kind="rendered", period_s=0.1)
    system = PerceptionSystem(read_frame, cf.ThreadPoolExecutor(1), camera, estimate,
                              simulated_clock=True)
    system.poll(0.0)  # frame 1 at t = 0
    release.set()
    cf.wait([system._future])
    system.poll(0.05)  # finished, but not due yet: not used
    assert not system.has_pose and len(frames) == 1
    release.clear()
    threading.Timer(0.2, release.set).start()
    system.poll(0.1)  # due: waits for the worker, uses it, takes frame 2
    assert system.has_pose and system.pose[0] == 1 and len(frames) == 2
    release.set()
    cf.wait([system._future])
    system.poll(0.15)
    assert system.pose[0] == 1
    system.poll(0.2)
    assert system.pose[0] == 2 and len(frames) == 3


def _drain(system, polls: int):
    for _ in range(polls):
        system.poll()
        if system._future is not None:
            cf.wait([system._future])


def test_perception_failure_holds_the_last_pose():
    X = np.eye(4)
    X[:3, 3] = [0.01, -0.02, 0.035]
    system = _perception([X, None, None, None, None])
    _drain(system, 10)
    assert system.has_pose and system.log.consecutive_failures >= 3
    np.testing.assert_allclose(system.pose, [0.01, -0.02, 0.035, 1, 0, 0, 0])


def test_perception_failure_stops_when_configured_or_when_no_pose_ever_came():
    from dexdrake.errors import StationFault

    X = np.eye(4)
    with pytest.raises(StationFault, match="perception failed 2 times"):
        _drain(_perception([X, None, None, None], on_failure="stop"), 6)
    with pytest.raises(StationFault, match="no object found|perception failed"):
        _drain(_perception([None, None, None], on_failure="hold"), 5)


def test_a_pose_older_than_its_limit_stops_the_station():
    """A worker that does not finish: the last pose keeps its frame's age, and past the
    camera's max_pose_age_s the station stops instead of feeding it on."""
    import threading

    from dexdrake.systems.scenario import CameraDriver
    from dexdrake.errors import StationFault
    from dexdrake.systems.station import PerceptionSystem

    hang = threading.Event()

    def estimate(color, depth, intrinsics, X_WC, prior=None, track=False):
        if track:  # every estimate after the first hangs
            hang.wait(5.0)
        return {"success": True, "reason": "", "X_WO": np.eye(4), "fitness": 1.0}

    camera = CameraDriver(kind="rendered", period_s=0.05, max_pose_age_s=0.3)
    system = PerceptionSystem(_Frame, cf.ThreadPoolExecutor(1), camera, estimate)
    try:
        system.poll()
        cf.wait([system._future])
        system.poll()
        assert system.has_pose
        t0 = time.monotonic()
        with pytest.raises(StationFault, match=r"object pose 0\.3\d s old \(limit 0\.3 s\)"):
            while time.monotonic() - t0 < 2.0:
                system.poll(time.monotonic() - t0)  # the running diagram's time (wall-paced)
                time.sleep(0.01)
    finally:
        hang.set()


def test_a_stale_pose_holds_the_devices_then_stops_the_station():
    """The worker stops answering after two poses (a track: the port's pose moves on at its
    velocity). Older than the camera's hold_pose_age_s, the devices get the joint positions
    measured when the hold began instead of the controller's command, and the "object_pose"
    port stops moving; older than max_pose_age_s, StationFault. On the wall clock, through
    the station's wiring (add_pose_age_hold) around a DriverSystem."""
    import threading
    from types import SimpleNamespace

    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder, EventStatus
    from pydrake.systems.primitives import ConstantVectorSource

    from dexdrake.systems.scenario import CameraDriver
    from dexdrake.errors import StationFault
    from dexdrake.systems.station import DriverSystem, PerceptionSystem, add_pose_age_hold

    class Joints:  # a driver whose joints move a tenth of the way to each target
        running = True

        def __init__(self):
            self.q, self.sent = np.zeros(3), []

        def state(self):
            return SimpleNamespace(q=self.q.copy(), dq=np.zeros(3), fault=None)

        def command_positions(self, q):
            self.sent.append(np.array(q))
            self.q = self.q + 0.1 * (np.asarray(q) - self.q)

    hang, calls = threading.Event(), []

    def estimate(color, depth, intrinsics, X_WC, prior=None, track=False):
        calls.append(track)
        if len(calls) > 2:  # the third estimate on hangs
            hang.wait(10.0)
        X = np.eye(4)
        X[0, 3] = 0.01 * len(calls)
        return {"success": True, "reason": "", "X_WO": X, "fitness": 1.0,
                "method": "track" if track else "global", "cpu_s": 0.0}

    period = 0.02
    camera = CameraDriver(kind="rendered", period_s=0.05, predict_s=0.5, hold_pose_age_s=0.3, max_pose_age_s=0.6)
    driver = Joints()
    builder = DiagramBuilder()
    perception = builder.AddSystem(PerceptionSystem(_Frame, cf.ThreadPoolExecutor(1), camera, estimate,
                                                    period=period))
    joints = builder.AddSystem(DriverSystem(driver, 3, period, "joints"))
    command = builder.AddSystem(ConstantVectorSource(np.ones(3)))
    to_devices = add_pose_age_hold(builder, joints.get_input_port(), joints.get_output_port(), perception, period)
    builder.Connect(command.get_output_port(), to_devices)
    diagram = builder.Build()
    seen = []  # (pose_stale, object_pose) at every step

    def monitor(root):
        ctx = perception.GetMyContextFromRoot(root)
        seen.append((perception.GetOutputPort("pose_stale").Eval(ctx)[0],
                     perception.GetOutputPort("object_pose").Eval(ctx).copy()))
        return EventStatus.Succeeded()

    try:
        perception.wait_for_first_pose()
        sim = Simulator(diagram)
        sim.set_target_realtime_rate(1.0)
        sim.set_monitor(monitor)
        with pytest.raises(StationFault, match=r"object pose 0\.6\d s old \(limit 0\.6 s\)"):
            sim.AdvanceTo(5.0)
    finally:
        hang.set()
    assert calls[:2] == [False, True] and any("holding" in e for e in perception.log.events)
    sent = np.array(driver.sent)
    commanded = np.all(sent == 1.0, axis=1)
    k = int(np.argmin(commanded))  # the first send of the hold
    assert k >= 5 and np.all(commanded[:k]), "the command was sent while the pose was fresh"
    held = sent[k]
    assert np.all(held < 1.0) and len(sent) - k >= 5 and np.all(sent[k:] == held)
    np.testing.assert_array_equal(driver.q, held)  # the joints stood still from then on
    fresh = [pose for stale, pose in seen if stale == 0.0]
    stale = [pose for stale, pose in seen if stale == 1.0]
    assert fresh[-1][0] > fresh[0][0] + 1e-3, "the tracked pose moves on while fresh"
    assert len(stale) >= 5 and all(np.array_equal(pose, stale[0]) for pose in stale)


def test_perception_moves_the_tracked_pose_on_to_the_present():
    """The pose the controller gets is the last estimate moved on at its track's velocity
    (between the last two frames) by the estimate's age, at most predict_s; the first pose
    of a track (a global registration) is used as it is."""
    from pydrake.math import RigidTransform, RollPitchYaw

    from dexdrake.systems.scenario import CameraDriver
    from dexdrake.systems.station import PerceptionSystem, pose_from_vector

    poses = iter([(RigidTransform([0.0, 0.0, 0.05]), "global"),
                  (RigidTransform(RollPitchYaw(0, 0, 0.02), [0.004, 0.0, 0.05]), "track"),
                  (RigidTransform(RollPitchYaw(0, 0, 0.04), [0.008, 0.0, 0.05]), "track")])
    priors = []

    def estimate(color, depth, intrinsics, X_WC, prior=None, track=False):
        priors.append(prior)
        X, method = next(poses)
        return {"success": True, "reason": "", "X_WO": X.GetAsMatrix4(), "fitness": 1.0,
                "method": method, "cpu_s": 0.0}

    camera = CameraDriver(kind="rendered", period_s=0.04, predict_s=0.05)
    system = PerceptionSystem(_Frame, cf.ThreadPoolExecutor(1), camera, estimate, simulated_clock=True)
    system.poll(0.0)
    system.poll(0.04)  # the first pose (frame at 0): held as it is
    np.testing.assert_allclose(system.predicted_pose()[:3], [0.0, 0.0, 0.05])
    system.poll(0.08)  # the second (frame at 0.04): moved on by 0.04 s at 0.1 m/s, 0.5 rad/s
    X = pose_from_vector(system.predicted_pose())
    np.testing.assert_allclose(X.translation(), [0.008, 0.0, 0.05], atol=1e-12)
    assert np.isclose(RollPitchYaw(X.rotation()).yaw_angle(), 0.04)
    system.poll(0.20)  # the third (frame at 0.08), 0.12 s old: moved on by predict_s only
    np.testing.assert_allclose(system.predicted_pose()[:3], [0.013, 0.0, 0.05], atol=1e-12)
    # the third frame (at 0.08) was tracked from the pose predicted for its time (checked once
    # its estimate has run: poll(0.08) only handed it to the worker thread)
    np.testing.assert_allclose(np.asarray(priors[2])[:3, 3], [0.008, 0.0, 0.05], atol=1e-12)


def test_a_camera_that_delivers_no_frame_is_a_perception_failure():
    """A camera read that raises (a malformed or timed-out capture) counts as a perception
    failure, held and then stopped by the camera's rules, not an exception out of the diagram."""
    from dexdrake.hardware.kinect import FrameError
    from dexdrake.systems.scenario import CameraDriver
    from dexdrake.errors import StationFault
    from dexdrake.systems.station import PerceptionSystem

    frames = iter([_Frame()])

    def read_frame():
        frame = next(frames, None)
        if frame is None:
            raise FrameError("capture lacks colour or transformed depth")
        return frame

    def estimate(color, depth, intrinsics, X_WC, prior=None, track=False):
        return {"success": True, "reason": "", "X_WO": np.eye(4), "fitness": 1.0}

    camera = CameraDriver(kind="k4a", period_s=1e-6, max_consecutive_failures=3, on_failure="stop")
    system = PerceptionSystem(read_frame, cf.ThreadPoolExecutor(1), camera, estimate)
    with pytest.raises(StationFault, match="perception failed 3 times.*camera read failed: FrameError"):
        _drain(system, 10)
    assert system.has_pose and system.log.failures == 3


@pytest.mark.slow
def test_full_hil_grasp_with_rendered_perception(tmp_path):
    """The whole `dexdrake hil` episode: perception on rendered images, the configured controller."""
    from dexdrake.systems.controllers import make_controller
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.rerun_logger import IMAGE_PERIOD_S, RerunLogger
    from dexdrake.systems.station import make_station

    scenario = hil_scenario("rendered")
    controller, _ = make_controller(scenario)
    rrd = tmp_path / "hil.rrd"
    logger = RerunLogger(rrd, "hil", scenario=scenario)
    with make_station(scenario) as station:
        logger.attach(station)
        p0 = station.world.object_pose().translation()
        estimates = []  # positions from every successful registration, in order
        log_to_rerun = station.perception.on_result

        def on_result(log):
            log_to_rerun(log)
            if log.result["success"]:
                estimates.append(np.asarray(log.result["X_WO"])[:3, 3].copy())

        station.perception.on_result = on_result
        result = run_station_episode(station, controller, steps=150, logger=logger)
        logger.close()
    assert result.fault is None
    assert estimates
    # the first frame is taken before the hand reaches the object; later ones see it move
    assert np.linalg.norm(estimates[0] - p0) < 0.03  # registration found the object
    # the recording's blueprint has the camera tab, and the camera images are in it
    rows, tree = logged_rows(rrd), blueprint_tree(rrd)
    assert all(any(matches(v, e) for e in rows) for v in tree.views())  # every view shows data
    (camera,) = [n for n in tree.walk() if n.name == "Camera"]
    for entity in ("/camera/image", "/camera/mask", "/camera/depth"):
        assert rows[entity] > 0 and any(matches(v, entity) for v in camera.views()), entity
    # images about every IMAGE_PERIOD_S (a recording of 25 Hz images grows ~10 MB/s); poses at every frame
    every = round(IMAGE_PERIOD_S / scenario.drivers.camera.period_s)
    assert every > 1 and rows["/camera/image"] == -(-rows["/perception/fitness"] // every)
    assert rows["/world/registered"] > 0 and rows["/world/object_true"] == rows["/perception/error_m"] == 150


def test_policy_checkpoint_paths_resolve_to_the_shipped_models(tmp_path, monkeypatch):
    from dexdrake.paths import resolve_model_path

    monkeypatch.chdir(tmp_path)  # a folder without models/: configs still name shipped weights
    assert resolve_model_path("models/weights/adroit_dexrep_policy.pt").is_file()
    assert resolve_model_path("runs/x.pt") == Path("runs/x.pt")
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "mine.pt").write_bytes(b"")
    assert resolve_model_path("models/mine.pt") == Path("models/mine.pt")  # an existing local file wins


# ----------------------------------------------------------------------------- policies
def _hil_config(tmp_path, policy: str | None, feature_set: str = "DexRep+Vel") -> str:
    text = (CONFIGS / "hil.yaml").read_text().split("\npolicy:")[0]
    if policy is not None:
        text += f"\npolicy:\n  checkpoint: {policy}\n  feature_set: {feature_set}\n"
    path = tmp_path / "hil.yaml"
    path.write_text(text)
    return str(path)


def _garbage(tmp_path) -> str:
    path = tmp_path / "garbage.pt"
    path.write_bytes(b"\x80\x04not a checkpoint")
    return str(path)


@pytest.mark.parametrize("policy, feature_set, reason", [
    ("no/such/policy.pt", "DexRep", "does not exist"),
    ("GARBAGE", "DexRep", "not a dexdrake policy file"),
    ("models/weights/adroit_dexrep_policy.pt", "DexRep", "trained for hand 'adroit'"),
    ("models/weights/allegro_z1_dexrep_policy.pt", "Hand2obj", "trained on feature set 'DexRep+Vel'"),
])
def test_hil_refuses_a_policy_it_cannot_run(tmp_path, capsys, policy, feature_set, reason):
    """Exit 2 and one line; never the scripted grasp in its place, never torch's advice to
    unpickle with weights_only=False."""
    from dexdrake.cli import main

    if policy == "GARBAGE":
        policy = _garbage(tmp_path)
    config = _hil_config(tmp_path, policy, feature_set)
    assert main(["hil", "--config", config, "--horizon", "1"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and err.startswith("dexdrake hil: error: policy refused")
    assert reason in err and "weights_only=False" not in err


def test_scripted_grasp_only_when_the_scenario_names_no_policy(tmp_path):
    from dexdrake.systems.controllers import OnMeasurements, make_controller

    controller, description = make_controller(load_scenario(_hil_config(tmp_path, None)))
    assert isinstance(controller.controller, OnMeasurements) and "no policy in the scenario" in description
    assert "lift 0.17 m" in description  # the hand's GraspScript, not a fixed plan text
    controller, description = make_controller(hil_scenario())
    assert controller.get_name() == "policy" and controller.HasSubsystemNamed("policy_system")
    assert "allegro_z1_dexrep_policy.pt" in description and "2473 observations -> 22 actions, arm by palm_step" in description
    with pytest.raises(ScenarioError, match="policy.checkpoint must name"):
        parse_scenario("policy: {checkpoint: ''}")


def _real_config(tmp_path, can_channel: str, arm_port: int, policy: str, local: int | None = None) -> str:
    """configs/real.yaml on a virtual CAN channel, a loopback Z1 port and a recorded frame."""
    import socket

    from dexdrake.hardware.kinect import CameraIntrinsics, RgbdFrame, save_frame

    frame = RgbdFrame(np.zeros((36, 64, 3), np.uint8), np.full((36, 64), 500, np.uint16),
                      CameraIntrinsics(64, 36, 50.0, 50.0, 31.5, 17.5), 0.0)
    save_frame(frame, tmp_path / "frame_000000.npz")
    if local is None:
        free = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        free.bind(("127.0.0.1", 0))
        local = free.getsockname()[1]
        free.close()
    text = (CONFIGS / "real.yaml").read_text()
    text = (text.replace("interface: socketcan", "interface: virtual")
            .replace("channel: can0", f"channel: {can_channel}")
            .replace("local_port: 8072", f"local_port: {local}")
            .replace("controller_port: 8071", f"controller_port: {arm_port}")
            .replace("kind: k4a", f"kind: recorded\n    recording: {tmp_path}")
            .replace("checkpoint: models/weights/allegro_z1_dexrep_policy.pt", f"checkpoint: {policy}"))
    path = tmp_path / "real.yaml"
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize("policy", ["models/weights/allegro_z1_dexrep_policy.pt", "GARBAGE"])
def test_real_dry_run_checks_every_device_and_the_policy(tmp_path, capsys, policy):
    """All devices answer (CAN emulator on a virtual bus, the Z1 emulator on loopback, a
    recorded frame): exit 0 and the policy's own description; a bad policy: exit 2."""
    import uuid

    import can

    from dexdrake.cli import main
    from dexdrake.hardware.allegro_emulator import AllegroEmulator
    from dexdrake.hardware.z1_emulator import Z1Emulator, Z1EmulatorConfig

    if policy == "GARBAGE":
        policy = _garbage(tmp_path)
    channel = f"dry-{uuid.uuid4().hex}"
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        with AllegroEmulator(bus) as hand, Z1Emulator(Z1EmulatorConfig(port=0)) as arm:
            code = main(["real", "--config", _real_config(tmp_path, channel, arm.port, policy), "--dry-run"])
            time.sleep(0.1)  # anything sent would have arrived
            arm_commands, arm_mode = arm.commands_received, arm.fsm
    finally:
        bus.shutdown()
    out, err = capsys.readouterr()
    if policy.endswith("garbage.pt"):
        assert code == 2 and "policy refused" in err and "all devices answered" not in out
        return
    assert code == 0, out + err
    for line in ("CAN virtual", "Z1 127.0.0.1", "controller port bound",
                 "nothing sent (the protocol has no pure query)", "camera recorded: OK",
                 "payload 0.955 kg", "controller: policy models/weights/allegro_z1_dexrep_policy.pt",
                 "diagram (built, not run): station (real: command_to_devices, workspace_guard, z1_driver, allegro_driver, "
                 "devices_to_hand_state, perception, pose_age_hold) -> dexrep (DexRep+Vel, fast path) -> controller (PolicySystem) -> command",
                 "all devices answered"):
        assert line in out, out
    assert "lift 0.17" not in out
    # the whole diagram was built around the drivers, yet nothing moved: the hand's servo never
    # came on and got no torque, the arm got nothing at all (not even a PASSIVE)
    assert not hand.servo_on and hand.answered_batches == 0
    assert arm_commands == 0 and arm_mode.name == "PASSIVE"


def test_a_station_built_without_starting_never_runs(tmp_path):
    """make_station(start=False) (the real dry run's diagram) is refused for hil; simulated
    anyway, its driver systems stop it before any command is stored; and the SceneGraph
    feature path is refused for it (no simulated object), with one line."""
    import uuid

    from pydrake.systems.analysis import Simulator

    from dexdrake.errors import DexdrakeError
    from dexdrake.systems.controllers import make_controller
    from dexdrake.systems.diagram import build_diagram, scenario_diagram
    from dexdrake.systems.station import make_station

    with pytest.raises(DexdrakeError, match="only a real station is built without starting"):
        make_station(hil_scenario(), start=False)
    scenario = load_scenario(_real_config(tmp_path, f"unstarted-{uuid.uuid4().hex}", 9, "x.pt"))
    scenario.policy = None
    controller, _ = make_controller(scenario)
    with make_station(scenario, start=False) as station:
        built = scenario_diagram(station, controller)
        with pytest.raises(DexdrakeError, match="^feature path 'scenegraph' needs the simulated object's "
                                                 "SceneGraph; a real station knows the object by its perceived pose"):
            build_diagram(station, None, "DexRep", "scenegraph")
        with pytest.raises(Exception, match="not running"):
            Simulator(built.diagram).AdvanceTo(0.1)
        assert not station.devices["allegro"]._has_command and not station.devices["z1"]._has_command


def test_hil_scripted_grasp_plans_on_the_perceived_pose_not_the_default_one(tmp_path):
    """The scripted fallback plans from the pose perception delivers: an object seen away
    from where its model was placed (and turned) is grasped where it was seen."""
    from pydrake.math import RigidTransform, RollPitchYaw

    from dexdrake.systems.controllers import make_controller
    from dexdrake.systems.scripted_grasp import plan_grasp
    from dexdrake.systems.station import pose_vector

    slot, _ = make_controller(load_scenario(_hil_config(tmp_path, None)))
    controller = slot.controller
    env = controller.env
    X_seen = RigidTransform(RollPitchYaw(0.0, 0.0, 0.7), [-0.04, 0.0, env.scene.object_info.rest_height])
    assert np.linalg.norm(env.object_position()[:2] - X_seen.translation()[:2]) > 0.05
    hand_state = np.concatenate([env.scene.hand.pregrasp_vector(), np.zeros(env.action_dim)])
    controller(0.0, hand_state, pose_vector(X_seen))
    script = controller._controller
    R_pregrasp = script.ik.palm_pose(script.q_open[: script.n_arm])[1]
    expected = plan_grasp(script.script, env.scene.object_info, X_seen, R_pregrasp)
    np.testing.assert_allclose(script.plan.grasp, expected.grasp, atol=1e-9)
    assert np.linalg.norm(script.plan.grasp[:2] - X_seen.translation()[:2]) <= abs(script.script.reach) + 1e-9
    centre = script.ik.palm_pose(script.q_grasp)[0]  # the arm's IK reaches the perceived grasp point
    assert np.linalg.norm(centre - script.plan.grasp) < 5e-3


def test_expert_in_the_controller_slot_reaches_for_the_object():
    """The expert (ReactiveGrasp) as a slot controller (measured state, object pose from the
    station) on the sim station: the grasp centre closes in on the object."""
    from dexdrake.systems.controllers import expert_controller
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.station import make_station

    scenario = load_scenario(CONFIGS / "sim.yaml")
    scenario.policy = None
    station = make_station(scenario)
    slot = expert_controller(scenario)
    result = run_station_episode(station, slot, steps=25)
    env = slot.controller.env  # the mirror: the last measured state
    p_object = env.object_position()
    d0 = np.linalg.norm(_grasp_centre(station.hand, station.hand.pregrasp_vector()) - p_object)
    d1 = np.linalg.norm(_grasp_centre(station.hand, env.hand_state()[: env.action_dim]) - p_object)
    assert result.fault is None and result.steps == 25 and result.stats["policy"]["non_finite"] == 0
    assert d1 < d0 - 0.03, (d0, d1)


def test_scenegraph_feature_path_reaches_dexrep_and_agrees_with_the_fast_path():
    """policy.feature_path of the scenario reaches the DexRepSystem (scenario_diagram). On the
    sim station's scene (box_cube held in the hand's occupancy grid) both paths query the
    same watertight mesh, so the features agree: the hand block exactly; occupancy up to
    marginal voxels (the fast path decides boundary voxels on the cached 2 mm SDF grid, the
    SceneGraph path on exact distances): at most max(2, 2 % of the occupied ones); surface
    distances to 1e-6 m (Open3D queries in float32); normals to a cosine of 0.99; local
    geometry the same nearest sample for at least 90 % of the points (near-ties)."""
    from pydrake.math import RigidTransform

    from dexdrake.systems.controllers import make_controller
    from dexdrake.systems.diagram import scenario_diagram
    from dexdrake.systems.scene import ObjectPlacement
    from dexdrake.systems.station import make_station

    features = {}
    for path in ("fast", "scenegraph"):
        scenario = load_scenario(CONFIGS / "sim.yaml")
        scenario.policy.feature_path = path
        station = make_station(scenario)
        built = scenario_diagram(station, make_controller(scenario)[0])
        assert built.dexrep.extractor.path == path
        context = built.diagram.CreateDefaultContext()
        scene = station.scene
        plant_context = scene.plant.GetMyMutableContextFromRoot(context)
        rng = np.random.default_rng(3)
        rows = []
        for _ in range(3):
            scene.set_initial_state(plant_context, ObjectPlacement(0.0, 0.0, 0.3), scene.hand.pregrasp_vector())
            X_WG = built.dexrep.extractor.grid_pose(plant_context)
            scene.plant.SetFreeBodyPose(plant_context, scene.object_body,
                                        RigidTransform(X_WG[:3, 3] + rng.uniform(-0.04, 0.04, 3)))
            rows.append(built.diagram.GetOutputPort("features").Eval(context).copy())
        features[path] = np.array(rows)
    hand = station.hand
    n, voxels = len(hand.dexrep_points), hand.occupancy.resolution ** 3
    blocks = built.dexrep.extractor.observation_blocks
    h = blocks["hand"]
    for a, b in zip(features["fast"], features["scenegraph"]):
        np.testing.assert_array_equal(a[:h], b[:h])
        occ_a, occ_b = a[h:h + voxels], b[h:h + voxels]
        assert occ_b.sum() > 10 and np.sum(occ_a != occ_b) <= max(2, 0.02 * occ_b.sum())
        surf_a, surf_b = (x[h + voxels:h + voxels + 4 * n].reshape(n, 4) for x in (a, b))
        np.testing.assert_allclose(surf_a[:, 0], surf_b[:, 0], atol=1e-6)
        assert np.all(np.einsum("ij,ij->i", surf_a[:, 1:], surf_b[:, 1:]) > 0.99)
        geo = slice(h + voxels + 4 * n, h + voxels + 4 * n + blocks["local_geo"])
        same = np.all(a[geo].reshape(n, -1) == b[geo].reshape(n, -1), axis=1)
        assert same.mean() >= 0.9


class _IdealJoints:
    """A stand-in for a HIL world and its joint driver at once: a robot that is exactly at
    the last commanded position one control period after the command (`advance_to`),
    measured as it is now (`state()`)."""

    running = True

    def __init__(self, q0: np.ndarray):
        from pydrake.math import RigidTransform

        self.q, self.target, self.time, self.pose = q0.copy(), q0.copy(), 0.0, RigidTransform()

    def state(self):
        from types import SimpleNamespace

        return SimpleNamespace(q=self.q.copy(), dq=np.zeros_like(self.q), fault=None)

    def command_positions(self, q) -> None:
        self.target = np.asarray(q, float).copy()

    def advance_to(self, t: float) -> None:
        self.q, self.time = self.target.copy(), t

    def begin(self, control_period: float) -> None:
        pass

    def release(self) -> None:
        pass

    def object_pose(self):
        return self.pose

    def stats(self) -> dict:
        return {}


def _stand_in_station(robot_type, make_pose=None):
    """A HIL station whose world and joint driver are one stand-in robot (`robot_type`, made at
    the pre-grasp pose), the object pose from `make_pose(period)` (default: WorldPoseSystem)."""
    from pydrake.systems.framework import DiagramBuilder

    from dexdrake.hands.description import load_hand
    from dexdrake.systems.station import DriverSystem, PerceptionSystem, Station, WorldPoseSystem

    scenario = hil_scenario()
    hand = load_hand(scenario.hand)
    robot = robot_type(hand.pregrasp_vector())
    builder = DiagramBuilder()
    period = scenario.control_period
    driver = builder.AddSystem(DriverSystem(robot, hand.num_actuators, period, "joints"))
    builder.ExportInput(driver.get_input_port(), "command")
    builder.ExportOutput(driver.get_output_port(), "hand_state")
    pose = builder.AddSystem(make_pose(period) if make_pose else WorldPoseSystem(robot, period))
    builder.ExportOutput(pose.GetOutputPort("object_pose"), "object_pose")
    perception = pose if isinstance(pose, PerceptionSystem) else None
    return Station(scenario, builder.Build(), hand, world=robot, devices={"allegro": robot},
                   perception=perception)


def test_device_station_adds_no_control_period_of_latency():
    """The station's driver systems sample the measurement before the controller runs and
    send its command before the world moves on, as in the simulated station: a controller
    stepping a joint by 0.01 rad from what it measures sees the robot reach each of its
    commands one control period later (before this, measurement and command each lagged
    one period: HIL responded 40 ms after simulation)."""
    from dexdrake.systems.diagram import run_station_episode

    station = _stand_in_station(_IdealJoints)
    n = station.hand.num_actuators
    seen = []

    def controller(t, hand_state, object_pose):
        seen.append(hand_state[0])
        q = hand_state[:n].copy()
        q[0] += 0.01
        return q

    result = run_station_episode(station, controller, 10)
    assert result.fault is None and len(seen) == 10
    np.testing.assert_allclose(np.diff(seen), 0.01, atol=1e-12)


class _FaultedJoints(_IdealJoints):
    """_IdealJoints whose driver has latched a fault (e.g. over-temperature) before the episode."""

    def state(self):
        st = super().state()
        st.fault = "over-temperature on joint 3"
        return st

    def command_positions(self, q) -> None:
        raise AssertionError("a command was sent to a faulted driver")


@pytest.mark.parametrize("with_perception", [False, True])
def test_driver_fault_during_the_held_start_ends_the_episode_as_a_fault(with_perception):
    """A driver that faults before the episode's first step (in the held start: while the
    station waits for the first object pose, or when the diagram initialises) ends the episode
    with the fault recorded and nothing sent, instead of raising out of the episode loop."""
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.scenario import CameraDriver
    from dexdrake.systems.station import PerceptionSystem

    def estimate(*args, **kwargs):  # the first pose never comes: the station waits, checking the drivers
        return {"success": False, "reason": "segmentation found no object", "X_WO": None, "fitness": 0.0}

    def perception(period):
        camera = CameraDriver(kind="rendered", period_s=0.01, first_pose_timeout_s=30.0,
                              max_consecutive_failures=10**6)
        return PerceptionSystem(_Frame, cf.ThreadPoolExecutor(1), camera, estimate, simulated_clock=True,
                                period=period)

    station = _stand_in_station(_FaultedJoints, perception if with_perception else None)
    n = station.hand.num_actuators
    result = run_station_episode(station, lambda t, hand_state, object_pose: hand_state[:n], 10)
    assert result.fault is not None and "over-temperature on joint 3" in result.fault
    assert result.steps == 0 and not result.success


def test_world_pauses_only_after_its_step_exchange_is_done(monkeypatch):
    """advance_to(t) returns once the step to t is complete, the drivers' replies included:
    the world's clock moves at a step's start (the devices run on it during the step), and a
    control loop woken by the clock alone would sample the drivers mid-exchange."""
    import time

    from dexdrake.systems.hil_world import HilWorld
    from dexdrake.systems.station import make_station

    publish, in_step = HilWorld._publish, threading.Event()

    def slow_publish(self):  # the clock has moved; the exchange of this step is still to come
        publish(self)
        if not self._held:  # (begun: longer than a waiter's poll of the clock, 50 ms)
            in_step.set()
            time.sleep(0.2)

    step = HilWorld.step

    def marked_step(self):
        step(self)
        in_step.clear()

    monkeypatch.setattr(HilWorld, "_publish", slow_publish)
    monkeypatch.setattr(HilWorld, "step", marked_step)
    with make_station(hil_scenario()) as station:
        world = station.world
        world.begin(station.scenario.control_period)
        for k in range(1, 6):
            world.advance_to(world.time + station.scenario.time_step)
            assert not in_step.is_set(), f"advance_to returned during step {k}"


def test_hil_episode_is_repeatable():
    """The same scenario and seed give the same HIL episode, bit for bit: the world begins at
    a fixed time from its initial state (held while the drivers start up) and every device
    exchange is in lockstep on its clock (systems/hil_world.py)."""
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.station import make_station

    def episode() -> np.ndarray:
        seen = []

        def controller(t, hand_state, object_pose):  # closed loop: small errors would grow
            seen.append(hand_state.copy())
            q = hand_state[: len(hand_state) // 2].copy()
            q[0] += 0.3 * np.sin(40 * q[0])
            q[8] += 0.2
            return q

        scenario = hil_scenario()
        assert scenario.drivers.arm.velocity_feedforward  # the Z1 client's ticks in phase with the world's
        with make_station(scenario) as station:
            result = run_station_episode(station, controller, 12)
        assert result.fault is None and result.stats["world"]["late_replies"] == 0
        return np.array(seen)

    first, second = episode(), episode()
    assert first.shape == second.shape and np.array_equal(first, second), \
        f"differ by up to {np.abs(first - second).max():.2e}"


def test_a_real_station_runs_its_drivers_in_their_own_processes(tmp_path):
    """configs/real.yaml's drivers (process by default) against emulators in this process (the
    hand on udp_multicast, the arm over UDP): the diagram reads their states through the
    proxies and holds the hand; leaving the station safe-stops both and ends their processes."""
    import socket

    from can.interfaces.udp_multicast import UdpMulticastBus
    from pydrake.systems.analysis import Simulator

    from dexdrake.hardware.allegro_emulator import AllegroEmulator
    from dexdrake.hardware.can_bus import open_can_bus
    from dexdrake.hardware.driver_process import DriverProcess
    from dexdrake.hardware.z1_emulator import Z1Emulator, Z1EmulatorConfig
    from dexdrake.hardware.z1_udp import free_udp_port
    from dexdrake.systems.station import make_station

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as free:
        free.bind(("", 0))
        port = free.getsockname()[1]
    group = UdpMulticastBus.DEFAULT_GROUP_IPv4
    bus = open_can_bus(dict(interface="udp_multicast", channel=group, port=port, receive_own_messages=False))
    try:
        client = free_udp_port()
        with AllegroEmulator(bus) as hand, Z1Emulator(Z1EmulatorConfig(port=0, client_port=client)) as arm:
            path = _real_config(tmp_path, group, arm.port, "x.pt", local=client)
            Path(path).write_text(Path(path).read_text().replace(  # normal scheduling: no privilege
                "interface: virtual", f"interface: udp_multicast\n    port: {port}").replace(
                "realtime_priority: 50", "realtime_priority: null").replace(  # a loaded host
                "watchdog_timeout_s: 0.05", "watchdog_timeout_s: 1.0").replace(  # the emulated arm rests
                "workspace_lower: [-0.45, -0.35, 0.0]", "workspace_lower: [-0.7, -0.35, -0.3]"))  # hand hanging
            scenario = load_scenario(path)
            with make_station(scenario) as station:
                drivers = [station.devices["allegro"], station.devices["z1"]]
                assert all(isinstance(d, DriverProcess) for d in drivers)
                pids = [d.pid for d in drivers]
                diagram = station.diagram
                sim = Simulator(diagram)
                ctx = sim.get_mutable_context()
                state = diagram.GetOutputPort("hand_state").Eval(diagram.CreateDefaultContext())
                diagram.GetInputPort("command").FixValue(ctx, state[: station.hand.num_actuators])
                sim.AdvanceTo(0.2)
                assert np.all(np.isfinite(diagram.GetOutputPort("hand_state").Eval(ctx)))
                assert hand.servo_on and arm.commands_received > 0
            assert not hand.servo_on and arm.fsm.name == "PASSIVE"
            assert not any(d.running for d in drivers)
            assert all(not Path(f"/proc/{pid}").exists()
                       or Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] == "Z"
                       for pid in pids)
    finally:
        bus.shutdown()
