"""The one diagram of every mode, built from a Scenario (systems/scenario.py):

    station (systems/station.py)                       controller slot
      sim:  grasp scene (plant + SceneGraph, PD)       policy:   PolicySystem -> set-points
      hil:  drivers, emulators, HIL world, perception  scripted: ControllerSystem(scripted grasp)
      real: drivers, devices, perception               external: the diagram's "command" input
        |  hand_state, object_pose                        ^  |
        +-------> DexRepSystem --- features --------------+  |
        +---------------------------------------------------+  |  (hand_state, object_pose)
        <------------------------- command ----------------------+

Every controller slot has the output "command" (joint set-points, policy order) and the
inputs "features", "hand_state" and "object_pose" that it reads (connected by name). With
no controller (training rollouts: systems/grasp_env.py) the diagram exports "command" as an
input and "features" as an output. The built diagram's outputs: "hand_state",
"object_pose", "features", and "command" when a controller is in the slot.

`run_station_episode` builds it around a station and runs it through the one episode loop
(dexdrake/episode.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Context, Diagram, DiagramBuilder, System
from pydrake.systems.primitives import AffineSystem, PassThrough

from dexdrake.episode import EpisodeResult, run_episode
from dexdrake.errors import DexdrakeError
from dexdrake.hands.description import HandDescription
from dexdrake.systems.dexrep_system import DexRepSystem
from dexdrake.systems.scenario import Scenario
from dexdrake.systems.station import ControllerSystem, LoopTimer, Station, StationFault, pose_from_vector

SLOT_INPUTS = ("features", "hand_state", "object_pose")


# ----------------------------------------------------------------------------- controllers
def joint_map(hand: HandDescription) -> tuple[np.ndarray, np.ndarray]:
    """(mid, half) of each joint's range: set-point = mid + action * half (policy order)."""
    lo, hi = hand.joint_limits()
    return (hi + lo) / 2, (hi - lo) / 2


def policy_controller(scenario: Scenario, hand: HandDescription) -> tuple[Diagram, str]:
    """The scenario's policy in the slot: PolicySystem (features -> normalised action) and
    the map to joint set-points; refused (a DexdrakeError naming the checkpoint and the
    reason) when the checkpoint is missing or unreadable, or was trained for another hand,
    feature set or action size."""
    from dexdrake.dexrep.feature_sets import observation_blocks
    from dexdrake.learn.policy import load_policy
    from dexdrake.paths import resolve_model_path
    from dexdrake.systems.policy_system import PolicySystem

    entry = scenario.policy
    try:
        policy, metadata = load_policy(resolve_model_path(entry.checkpoint))
    except DexdrakeError as err:
        raise DexdrakeError(f"policy refused: {err}") from None
    cfg = policy.config
    if cfg.hand != scenario.hand:
        raise DexdrakeError(f"policy refused: {entry.checkpoint} was trained for hand {cfg.hand!r}, "
                            f"the scenario runs {scenario.hand!r}")
    if cfg.feature_set != entry.feature_set:
        raise DexdrakeError(f"policy refused: {entry.checkpoint} was trained on feature set "
                            f"{cfg.feature_set!r}, the scenario gives it {entry.feature_set!r}")
    if cfg.action_dim != hand.num_actuators:
        raise DexdrakeError(f"policy refused: {entry.checkpoint} has {cfg.action_dim} actions, hand "
                            f"{scenario.hand!r} has {hand.num_actuators} joints")
    size = sum(observation_blocks(hand, entry.feature_set).values())
    if size != cfg.obs_dim:
        raise DexdrakeError(f"policy refused: {entry.checkpoint} expects {cfg.obs_dim} observations, "
                            f"feature set {entry.feature_set!r} gives {size}")
    n = hand.num_actuators
    mid, half = joint_map(hand)
    builder = DiagramBuilder()
    system = builder.AddNamedSystem("policy_system", PolicySystem(policy, scenario.control_period))
    to_command = builder.AddNamedSystem("action_to_command", AffineSystem(
        np.zeros((0, 0)), np.zeros((0, n)), np.zeros(0), np.zeros((n, 0)), np.diag(half), mid))
    builder.Connect(system.GetOutputPort("action"), to_command.get_input_port())
    builder.ExportInput(system.GetInputPort("observation"), "features")
    for name, size in (("hand_state", 2 * n), ("object_pose", 7)):  # read by loggers only
        builder.ExportInput(builder.AddNamedSystem(name, PassThrough(size)).get_input_port(), name)
    builder.ExportOutput(to_command.get_output_port(), "command")
    description = (f"policy {entry.checkpoint} (hand {cfg.hand}, feature set {cfg.feature_set}, "
                   f"{cfg.obs_dim} observations -> {cfg.action_dim} joint targets, "
                   f"stage {metadata.get('stage', 'unknown')})")
    slot = builder.Build()
    slot.set_name("policy")
    return slot, description


class ScriptedGraspOnMeasurements:
    """The scripted grasp (systems/scripted_grasp.py) driven by the measured hand state and
    the perceived object pose, as a ControllerSystem callback: planned once, from the first
    pose, with the hand's own IK on a private scene."""

    def __init__(self, scenario: Scenario):
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


def describe_script(hand: HandDescription) -> str:
    """The scripted grasp's plan, from the GraspScript the hand description configures."""
    from dexdrake.systems.scripted_grasp import script_for

    g = script_for(hand)
    return (f"scripted grasp (no policy in the scenario): from the first perceived pose, approach "
            f"{g.hover:.2f} m above the object by {g.approach_end:.1f} s, descend by {g.descend_end:.1f} s, "
            f"close by {g.close_end:.1f} s, lift {g.lift:.2f} m by {g.lift_end:.1f} s")


def make_controller(scenario: Scenario):
    """(controller slot system, description) of what the scenario asks for: its policy (a
    policy that cannot be run is refused with a DexdrakeError, never replaced), or the
    scripted grasp when the scenario names no policy."""
    from dexdrake.hands.description import load_hand

    hand = load_hand(scenario.hand)
    if scenario.policy is not None:
        return policy_controller(scenario, hand)
    system = ControllerSystem(ScriptedGraspOnMeasurements(scenario), hand, scenario.control_period)
    return system, describe_script(hand)


# ----------------------------------------------------------------------------- builder
@dataclass
class BuiltDiagram:
    """The diagram of one mode and its parts (`controller` None: the "command" input is free)."""

    station: Station
    diagram: Diagram
    dexrep: DexRepSystem | None
    controller: object = None

    @property
    def policy_system(self):
        """The slot's PolicySystem, if a policy is in the slot."""
        c = self.controller
        return c.GetSubsystemByName("policy_system") if isinstance(c, Diagram) and c.HasSubsystemNamed(
            "policy_system") else None

    def hold_measured(self, context: Context) -> None:
        """Make the slot's first command the measured position (a policy's held action
        otherwise starts at zero, the middle of every joint's range)."""
        policy = self.policy_system
        if policy is not None:
            q = self.diagram.GetOutputPort("hand_state").Eval(context)[: self.station.hand.num_actuators]
            mid, half = joint_map(self.station.hand)
            policy.GetMyMutableContextFromRoot(context).get_mutable_discrete_state(0).SetFromVector(
                np.clip((q - mid) / half, -1.0, 1.0))

    @property
    def timer(self) -> LoopTimer:
        return self.policy_system.timer if self.policy_system is not None else self.controller.timer

    @property
    def command_counts(self) -> dict[str, int]:
        """Bad commands the slot held or clipped (systems/command_guard.py)."""
        return (self.policy_system or self.controller).guard.counts


def build_diagram(station: Station, controller=None, feature_set: str | None = "DexRep") -> BuiltDiagram:
    """The station of a scenario with DexRepSystem computing `feature_set` (None: no
    DexRepSystem, for controllers that read no features) and `controller` in the slot (see
    the module doc; None leaves the slot's "command" as the diagram's input)."""
    builder = DiagramBuilder()
    st = builder.AddNamedSystem("station", station.diagram)
    dexrep = None
    if feature_set is not None:
        from dexdrake.dexrep.geometry import object_geometry
        from dexdrake.systems.scene import build_grasp_scene
        from dexdrake.systems.station import scene_config

        scene = station.scene or build_grasp_scene(scene_config(station.scenario))  # hil/real: kinematics only
        dexrep = builder.AddNamedSystem("dexrep", DexRepSystem(scene.hand, scene.plant, scene.hand_instance,
                                                               object_geometry(station.scenario.object), feature_set))
        for name in ("hand_state", "object_pose"):
            builder.Connect(st.GetOutputPort(name), dexrep.GetInputPort(name))
        builder.ExportOutput(dexrep.GetOutputPort("features"), "features")
    for name in ("hand_state", "object_pose"):
        builder.ExportOutput(st.GetOutputPort(name), name)
    if controller is None:
        builder.ExportInput(st.GetInputPort("command"), "command")
    else:
        slot = builder.AddNamedSystem("controller", controller)
        for name in SLOT_INPUTS:
            if slot.HasInputPort(name):
                source = dexrep.GetOutputPort(name) if name == "features" else st.GetOutputPort(name)
                builder.Connect(source, slot.GetInputPort(name))
        builder.Connect(slot.GetOutputPort("command"), st.GetInputPort("command"))
        builder.ExportOutput(slot.GetOutputPort("command"), "command")
    return BuiltDiagram(station, builder.Build(), dexrep, controller)


# ----------------------------------------------------------------------------- episodes
class StationEpisode:
    """A built diagram with a controller in its slot as an env of the one episode loop: each
    `step` advances one control period (the slot acts; the loop's action is unused). Scored
    with dexdrake.task on the object's true pose (sim: the plant, hil: the world; real: not
    known, lift NaN). A StationFault or HardwareError ends the episode (info["fault"]); the
    station is stopped by its owner's context manager."""

    def __init__(self, built: BuiltDiagram, steps: int, logger=None):
        self.built, self.horizon, self.logger = built, steps, logger
        self.object_name = built.station.scenario.object
        self.simulator = Simulator(built.diagram)
        self.context = self.simulator.get_mutable_context()
        self._world_paused = False

    def _object_position(self) -> np.ndarray | None:
        station = self.built.station
        if station.scene is not None:
            return station.scene.object_pose(station.scene.plant.GetMyContextFromRoot(self.context)).translation()
        if station.world is not None:
            return station.world.object_pose().translation()
        return None

    def reset(self, seed: int) -> None:
        from dexdrake.systems.scene import ObjectPlacement
        from dexdrake.task import SuccessTracker

        station, period = self.built.station, self.built.station.scenario.control_period
        if station.scene is not None:
            scene = station.scene
            placement = ObjectPlacement.sample(np.random.default_rng(seed))
            scene.set_initial_state(scene.plant.GetMyMutableContextFromRoot(self.context), placement,
                                    scene.hand.pregrasp_vector())
        elif station.world is None:  # real: the devices run on the wall clock
            self.simulator.set_target_realtime_rate(1.0)
        if station.perception is not None:
            _await_first_pose(station)
        if station.world is not None:  # pause the world where the episode starts (lockstep)
            station.world.advance_to(station.world.time)
            self._world_paused = True
        self.built.hold_measured(self.context)
        self.simulator.Initialize()
        self.t_start, self.k, self.period = self.context.get_time(), 0, period
        self.t_world = station.world.time if station.world is not None else 0.0
        p = self._object_position()
        self.tracker = None if p is None else SuccessTracker(p)

    def step(self, action=None) -> tuple[None, float, bool, dict]:
        from dexdrake.hardware.safety import HardwareError

        station = self.built.station
        k = self.k + 1
        fault = None
        try:
            if station.world is not None:  # lockstep: the world pauses at each control step
                station.world.advance_to(self.t_world + k * self.period)
            self.simulator.AdvanceTo(self.t_start + k * self.period)
        except (StationFault, HardwareError) as err:
            fault = str(err)
        except RuntimeError as err:  # a Python exception raised inside a Drake event
            if "StationFault" not in repr(err) and "fault" not in str(err).lower():
                raise
            fault = str(err)
        if fault is None:
            self.k = k
            if self.tracker is not None:
                self.tracker.update(self._object_position())
            if self.logger is not None:
                self.logger.log_step(k, self.built.diagram, self.context, self.built.controller, station)
        info = {"success": self.tracker.success if self.tracker else False,
                "lift": self.tracker.max_lift if self.tracker else float("nan"), "fault": fault}
        return None, 0.0, k >= self.horizon, info

    def close(self) -> None:
        if self._world_paused:
            self.built.station.world.release()
            self._world_paused = False


def _await_first_pose(station: Station) -> None:
    """Hold (the drivers keep the measured position) until perception delivers a pose."""

    def check() -> None:
        for name in ("allegro", "z1"):
            dev = station.devices.get(name)
            if dev is not None and dev.state().fault is not None:
                raise StationFault(f"{name} fault while waiting for the first pose: {dev.state().fault}")

    station.perception.wait_for_first_pose(check)


def run_station_episode(station: Station, controller, steps: int, logger=None) -> EpisodeResult:
    """`steps` control periods of `controller` (a slot system, or a callback
    `controller(t, hand_state, object_pose) -> q_command` run in ControllerSystem) in the
    station's diagram (`build_diagram`), through the one episode loop: sim as fast as it
    goes, hil on the world's simulated clock (the world pauses at each control step until
    the controller has run), real in wall-clock real time. `stats`: the devices' loop
    statistics and the controller's ("policy": rate, bad commands held or clipped)."""
    if steps < 1:
        raise DexdrakeError(f"steps must be >= 1, got {steps}")
    if not isinstance(controller, System):
        controller = ControllerSystem(controller, station.hand, station.scenario.control_period)
    policy = station.scenario.policy
    feature_set = (policy.feature_set if policy is not None else "DexRep") if controller.HasInputPort("features") else None
    built = build_diagram(station, controller, feature_set)
    env = StationEpisode(built, steps, logger)
    try:
        result = run_episode(env, lambda observation: None, station.scenario.seed)
    finally:
        env.close()
    result.steps = env.k  # control periods completed (a fault ends the episode inside one)
    result.stats = station.stats()
    result.stats["policy"] = {**built.timer.stats(), **built.command_counts}
    return result
