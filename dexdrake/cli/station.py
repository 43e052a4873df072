"""Sub-commands `hil` (a full grasp episode against the emulated devices) and `real`
(`--dry-run`: connectivity checks and the plan; moves nothing)."""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np

from dexdrake import argtypes
from dexdrake.errors import DexdrakeError


def add_parser(subparsers) -> None:
    hil = subparsers.add_parser("hil", help="run one grasp episode hardware-in-the-loop")
    hil.add_argument("--config", default="configs/hil.yaml", help="scenario YAML (mode hil)")
    hil.add_argument("--steps", type=argtypes.count, default=150, help="control steps")
    hil.add_argument("--rrd", type=argtypes.output_file(".rrd"), help="write a rerun recording of the loop to this .rrd file")
    hil.set_defaults(func=run_hil)

    real = subparsers.add_parser("real", help="the real Allegro + Z1 + Kinect station")
    real.add_argument("--config", required=True, help="scenario YAML (mode real)")
    real.add_argument("--dry-run", action="store_true",
                      help="check connectivity, print limits and the plan, move nothing")
    real.set_defaults(func=run_real)


# ----------------------------------------------------------------------------- controllers
class ScriptedGraspController:
    """The scripted grasp (systems/scripted_grasp.py) driven by measured state and the
    perceived object pose: planned once, from the first pose, with the hand's own IK."""

    def __init__(self, scenario):
        from dexdrake.systems.scene import SceneConfig, build_grasp_scene

        self.scene = build_grasp_scene(SceneConfig(hand=scenario.hand, object=scenario.object))
        self.context = self.scene.diagram.CreateDefaultContext()
        self.plant_context = self.scene.plant.GetMyMutableContextFromRoot(self.context)
        self._X_obj = None
        self._script = None
        self._t0 = 0.0

    def object_pose(self):
        """The perceived object pose the grasp is planned on (the first one seen)."""
        return self._X_obj

    def object_position(self) -> np.ndarray:
        return self._X_obj.translation().copy()

    def __call__(self, t: float, hand_state: np.ndarray, object_pose: np.ndarray) -> np.ndarray:
        from dexdrake.systems.scripted_grasp import ScriptedGrasp
        from dexdrake.systems.station import pose_from_vector

        n = self.scene.hand.num_actuators
        if self._script is None:
            q = self.scene.plant.GetPositions(self.plant_context).copy()
            q[self.scene.q_index] = hand_state[:n]
            self.scene.plant.SetPositions(self.plant_context, q)
            self._X_obj = pose_from_vector(object_pose)
            self._t0 = t
            self._script = ScriptedGrasp(self)
        self.context.SetTime(t - self._t0)
        return self._script(self)


class PolicyController:
    """A trained DexRepNet policy: DexRep features of (measured hand, perceived object).

    Refused (a DexdrakeError naming the checkpoint and the reason) when the checkpoint is
    missing or unreadable, or was trained for another hand, feature set or action size."""

    def __init__(self, scenario):
        from dexdrake.dexrep.feature_sets import FeatureExtractor
        from dexdrake.dexrep.geometry import load_object_geometry
        from dexdrake.learn.policy import load_policy
        from dexdrake.paths import resolve_model_path
        from dexdrake.systems.scene import SceneConfig, build_grasp_scene

        entry = scenario.policy
        self.path = resolve_model_path(entry.checkpoint)
        try:
            self.policy, self.metadata = load_policy(self.path)
        except DexdrakeError as err:
            raise DexdrakeError(f"policy refused: {err}") from None
        cfg = self.policy.config
        if cfg.hand != scenario.hand:
            raise DexdrakeError(f"policy refused: {entry.checkpoint} was trained for hand {cfg.hand!r}, "
                                f"the scenario runs {scenario.hand!r}")
        if cfg.feature_set != entry.feature_set:
            raise DexdrakeError(f"policy refused: {entry.checkpoint} was trained on feature set "
                                f"{cfg.feature_set!r}, the scenario gives it {entry.feature_set!r}")
        self.scene = build_grasp_scene(SceneConfig(hand=scenario.hand, object=scenario.object))
        if cfg.action_dim != self.scene.hand.num_actuators:
            raise DexdrakeError(f"policy refused: {entry.checkpoint} has {cfg.action_dim} actions, hand "
                                f"{scenario.hand!r} has {self.scene.hand.num_actuators} joints")
        self.plant_context = self.scene.plant.CreateDefaultContext()
        geometry = load_object_geometry(self.scene.object_info.mesh_path)
        self.features = FeatureExtractor(self.scene.hand, self.scene.plant, self.scene.hand_instance,
                                         geometry, entry.feature_set)
        if self.features.size != cfg.obs_dim:
            raise DexdrakeError(f"policy refused: {entry.checkpoint} expects {cfg.obs_dim} observations, "
                                f"feature set {entry.feature_set!r} gives {self.features.size}")
        lo, hi = self.scene.hand.joint_limits()
        self.mid, self.half = (hi + lo) / 2, (hi - lo) / 2
        self.description = (f"policy {entry.checkpoint} (hand {cfg.hand}, feature set {cfg.feature_set}, "
                            f"{cfg.obs_dim} observations -> {cfg.action_dim} joint targets, "
                            f"stage {self.metadata.get('stage', 'unknown')})")

    def __call__(self, t: float, hand_state: np.ndarray, object_pose: np.ndarray) -> np.ndarray:
        import torch

        from dexdrake.systems.station import pose_from_vector

        n = self.scene.hand.num_actuators
        plant = self.scene.plant
        q = plant.GetPositions(self.plant_context).copy()
        q[self.scene.q_index] = hand_state[:n]
        plant.SetPositions(self.plant_context, q)
        obs = self.features(self.plant_context, pose_from_vector(object_pose))
        with torch.inference_mode():
            action, _ = self.policy.act(obs, None)
        return self.mid + np.asarray(action, float) * self.half


def make_controller(scenario):
    """(controller, description) of what the scenario asks for: its policy (a policy that
    cannot be run is refused with a DexdrakeError, never replaced), or the scripted grasp
    when the scenario names no policy."""
    if scenario.policy is not None:
        controller = PolicyController(scenario)
        return controller, controller.description
    return ScriptedGraspController(scenario), describe_script(scenario.hand)


def describe_script(hand_name: str) -> str:
    """The scripted grasp's plan, from the GraspScript the hand description configures."""
    from dexdrake.hands.description import load_hand
    from dexdrake.systems.scripted_grasp import GraspScript, with_overrides

    hand = load_hand(hand_name)
    g = with_overrides(GraspScript, hand.grasp_script, hand, "grasp_script")
    return (f"scripted grasp (no policy in the scenario): from the first perceived pose, approach "
            f"{g.hover:.2f} m above the object by {g.approach_end:.1f} s, descend by {g.descend_end:.1f} s, "
            f"close by {g.close_end:.1f} s, lift {g.lift:.2f} m by {g.lift_end:.1f} s")


# ----------------------------------------------------------------------------- episode
@dataclass
class EpisodeResult:
    success: bool
    max_lift: float
    steps: int
    wall_s: float
    stats: dict
    fault: str | None


def run_episode(station, controller, steps: int, logger=None) -> EpisodeResult:
    """Run `steps` control periods of `controller` on a built station, scoring the lift with
    dexdrake.task: sim as fast as it goes, hil on the world's simulated clock (the world
    pauses at each control step until the controller has run), real in wall-clock real
    time. A StationFault
    ends the episode early (the station is stopped by the caller's context manager)."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder

    from dexdrake.hardware.safety import HardwareError
    from dexdrake.systems.station import ControllerSystem, StationFault
    from dexdrake.task import SuccessTracker

    sc = station.scenario
    builder = DiagramBuilder()
    st = builder.AddNamedSystem("station", station.diagram)
    ctrl = builder.AddNamedSystem("controller", ControllerSystem(controller, station.hand, sc.control_period))
    builder.Connect(ctrl.get_output_port(), st.GetInputPort("command"))
    builder.Connect(st.GetOutputPort("hand_state"), ctrl.GetInputPort("hand_state"))
    builder.Connect(st.GetOutputPort("object_pose"), ctrl.GetInputPort("object_pose"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    if station.mode == "sim":
        from dexdrake.systems.scene import ObjectPlacement

        scene = station.scene
        plant_context = scene.plant.GetMyMutableContextFromRoot(context)
        placement = ObjectPlacement.sample(np.random.default_rng(sc.seed))
        scene.set_initial_state(plant_context, placement, scene.hand.pregrasp_vector())
        object_pose = lambda: scene.object_pose(plant_context).translation()  # noqa: E731
    elif station.world is None:  # real: the devices run on the wall clock
        simulator.set_target_realtime_rate(1.0)
        object_pose = lambda: None  # noqa: E731
    else:  # hil: the control loop follows the world's simulated clock (systems/hil_world.py)
        object_pose = lambda: station.world.object_pose().translation()  # noqa: E731
    if station.perception is not None:
        _await_first_pose(station)
    t_world = 0.0
    if station.world is not None:  # pause the world where the episode starts
        station.world.advance_to(station.world.time)
        t_world = station.world.time
    simulator.Initialize()
    t_start = context.get_time()
    p_start = object_pose()
    tracker = SuccessTracker(p_start) if p_start is not None else None
    fault = None
    wall0 = time.perf_counter()
    done = 0
    try:
        for k in range(1, steps + 1):
            if station.world is not None:  # lockstep: the world pauses at each control step
                station.world.advance_to(t_world + k * sc.control_period)
            simulator.AdvanceTo(t_start + k * sc.control_period)
            done = k
            p = object_pose()
            if tracker is not None:
                tracker.update(p)
            if logger is not None:
                logger.log_step(k, diagram, context, ctrl, station)
    except (StationFault, HardwareError) as err:
        fault = str(err)
    except RuntimeError as err:  # a Python exception raised inside a Drake event
        if "StationFault" not in repr(err) and "fault" not in str(err).lower():
            raise
        fault = str(err)
    finally:
        if station.world is not None:
            station.world.release()
    wall = time.perf_counter() - wall0
    stats = station.stats()
    stats["policy"] = ctrl.timer.stats()
    stats["policy"].update(ctrl.guard.counts)
    return EpisodeResult(tracker.success if tracker else False, tracker.max_lift if tracker else float("nan"),
                         done, wall, stats, fault)


def _await_first_pose(station) -> None:
    """Hold (the drivers keep the measured position) until perception delivers a pose."""
    from dexdrake.systems.station import StationFault

    def check() -> None:
        for name in ("allegro", "z1"):
            dev = station.devices.get(name)
            if dev is not None and dev.state().fault is not None:
                raise StationFault(f"{name} fault while waiting for the first pose: {dev.state().fault}")

    station.perception.wait_for_first_pose(check)


# ----------------------------------------------------------------------------- commands
def _fmt_rate(name: str, s: dict) -> str:
    return (f"{name}: {s.get('rate_hz', 0):.0f} Hz, period p50 {s.get('p50_ms', float('nan')):.2f} ms, "
            f"p99 {s.get('p99_ms', float('nan')):.2f} ms, max {s.get('max_ms', float('nan')):.2f} ms")


def run_hil(args: argparse.Namespace) -> int:
    from dexdrake.systems.scenario import ScenarioError, load_scenario
    from dexdrake.systems.station import make_station

    scenario = load_scenario(args.config)
    if scenario.mode != "hil":
        raise ScenarioError(f"{args.config} is a {scenario.mode} scenario; `hil` needs emulated drivers")
    if args.steps <= 0:
        raise DexdrakeError(f"--steps must be > 0, got {args.steps}")
    rrd = args.rrd or scenario.rrd
    controller, description = make_controller(scenario)  # refused before any device starts
    logger = None
    with make_station(scenario) as station:
        if rrd:
            from dexdrake.systems.station import StationRerunLogger

            logger = StationRerunLogger(rrd, station)
        result = run_episode(station, controller, args.steps, logger)
    if logger is not None:
        logger.close()
    print(f"hil: {scenario.object} seed={scenario.seed} controller={description}")
    print(f"success={result.success} max_lift={result.max_lift:.3f} m steps={result.steps} "
          f"wall={result.wall_s:.1f} s" + (f" rrd={rrd}" if rrd else ""))
    clock = "simulated clock" if scenario.mode == "hil" else "wall clock"
    print(f"  loop rates on the devices' {clock}:")
    for key, name in (("can", "CAN (Allegro PD loop)"), ("z1", "Z1 UDP loop"), ("policy", "policy/control")):
        if key in result.stats:
            print("    " + _fmt_rate(name, result.stats[key]))
    world = result.stats.get("world")
    if world:
        print(f"  world: {world['sim_time_s']:.2f} s simulated in {world['wall_s']:.2f} s wall "
              f"(real-time factor {world['real_time_factor']:.2f}), step p50 {world['step_p50_ms']:.2f} ms "
              f"p99 {world['step_p99_ms']:.2f} ms wall, late hand replies {world['late_replies']:.0f}")
    print(f"  policy on the wall clock: {result.stats['policy']['wall_rate_hz']:.1f} Hz, "
          f"non-finite commands held {result.stats['policy']['non_finite']}, "
          f"clipped {result.stats['policy']['clipped']}")
    if result.fault:
        print(f"  stopped safely: {result.fault}")
        return 1
    return 0


def run_real(args: argparse.Namespace) -> int:
    from dexdrake.systems.scenario import ScenarioError, load_scenario

    scenario = load_scenario(args.config)
    if scenario.mode != "real":
        raise ScenarioError(f"{args.config} is a {scenario.mode} scenario; `real` needs hardware drivers")
    if not args.dry_run:
        raise DexdrakeError("running the real station moves the robot; check it first with --dry-run "
                            "(a supervised real episode is not enabled in this version)")
    return dry_run(scenario)


def dry_run(scenario) -> int:
    """Connectivity checks; prints limits and the plan; commands nothing."""
    from dexdrake.hands.description import load_hand
    from dexdrake.hardware.allegro_can import Info, Msg, Request, Serial, check_allegro_config, decode, encode
    from dexdrake.hardware.safety import HardwareError
    from dexdrake.hardware.z1_model import NUM_ARM_JOINTS, z1_model
    from dexdrake.hardware.z1_udp import ArmFSMState, RecvState, SendCmd, check_z1_config
    from dexdrake.systems.scenario import driver_configs
    from dexdrake.systems.station import open_can_bus

    hand = load_hand(scenario.hand)
    h, c = scenario.drivers.hand, scenario.drivers.camera
    hand_cfg, arm_cfg = driver_configs(scenario)
    hs, zs = check_allegro_config(hand_cfg), check_z1_config(arm_cfg)
    print(f"real dry run: {scenario.name} hand={scenario.hand} object={scenario.object}")
    lower = np.concatenate([zs.lower, hs.lower])
    upper = np.concatenate([zs.upper, hs.upper])
    joints = list(hand.arm_joints) + list(hand.hardware_joints)
    for j, l, u in zip(joints, lower, upper):
        print(f"  limit {j:<11} [{l:+.3f}, {u:+.3f}] rad")
    print(f"  hand: max target rate {hand_cfg.max_target_rate} rad/s, watchdog "
          f"{hand_cfg.watchdog_timeout_s * 1e3:.0f} ms, PWM limits {hs.pwm_limit.astype(int).tolist()}")
    print(f"  arm: {arm_cfg.mode.name}, max velocity {zs.max_velocity:.3f} rad/s, watchdog "
          f"{arm_cfg.watchdog_timeout_s * 1e3:.0f} ms, effort {zs.effort.tolist()} N*m, gravity "
          f"feed-forward {'on' if arm_cfg.gravity_feedforward else 'off'}; payload "
          f"{z1_model().payload_kg:.3f} kg (the hand, from the model): set it as `load` in "
          "z1_controller/config/config.xml")
    _, description = make_controller(scenario)  # a policy that cannot run is refused here
    print(f"  controller: {description}; control period {scenario.control_period * 1e3:.0f} ms")
    ok = True
    # CAN: open the bus and ask for info + serial (RTR requests only: nothing moves)
    try:
        bus = open_can_bus(scenario)
        try:
            replies = {}
            for msg_id, kind in ((Msg.INFO, Info), (Msg.SERIAL, Serial)):
                bus.send(encode(Request(msg_id), h.device_id))
                deadline = time.monotonic() + 0.3
                while time.monotonic() < deadline and kind not in replies:
                    m = bus.recv(0.05)
                    if m is not None:
                        try:
                            f = decode(m, h.device_id)
                        except HardwareError:
                            continue
                        if isinstance(f, kind):
                            replies[kind] = f
            if Info in replies and Serial in replies:
                print(f"  CAN {h.interface}:{h.channel}: OK, {replies[Info]} serial {replies[Serial].text!r}")
            else:
                ok = False
                print(f"  CAN {h.interface}:{h.channel}: bus opens but the hand does not answer info/serial "
                      "(powered? device id? bitrate 1 Mbit/s?)")
        finally:
            bus.shutdown()
    except HardwareError as err:
        ok = False
        print(f"  CAN: FAILED: {err}")
    # Z1: listen for controller state on the SDK port, sending PASSIVE only (no motion)
    import socket

    a = arm_cfg
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind((a.host, a.local_port))
        sock.settimeout(0.3)
        sock.sendto(SendCmd(ArmFSMState.PASSIVE).pack(), (a.host, a.controller_port))
        data = sock.recv(4096)
        st = RecvState.unpack(data)
        print(f"  Z1 {a.host}:{a.local_port} -> {a.controller_port}: OK, state {st.state.name}, q = "
              f"{np.round([j.Pos for j in st.joints[:NUM_ARM_JOINTS]], 3).tolist()}")
    except (OSError, HardwareError) as err:
        ok = False
        print(f"  Z1 {a.host}:{a.local_port} -> {a.controller_port}: FAILED: {err} "
              "(is z1_controller running?)")
    finally:
        sock.close()
    # camera: one frame
    try:
        from dexdrake.hardware.kinect import K4ADevice, RecordedSequence

        source = RecordedSequence(c.recording) if c.kind == "recorded" else K4ADevice(c.device_id, warmup_frames=1)
        try:
            frame = source.read()
            print(f"  camera {c.kind}: OK, frame {frame.color.shape[1]}x{frame.color.shape[0]}")
        finally:
            source.close()
    except DexdrakeError as err:
        ok = False
        print(f"  camera {c.kind}: FAILED: {err}")
    if not ok:
        print("dry run: hardware not ready (nothing was moved)")
        return 1
    print("dry run: all devices answered (nothing was moved)")
    return 0
