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

DexRepSystem's distance queries take the "fast" path (the object's cached geometry at the
"object_pose" pose, every mode) or the "scenegraph" path (the sim station's "query_object").
The slot's controllers are made in systems/controllers.py; `scenario_diagram` builds the
diagram with a scenario's options and `run_station_episode` runs it around a station
through the one episode loop (dexdrake/episode.py).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Context, Diagram, DiagramBuilder, System

from dexdrake.dexrep.feature_sets import FeaturePath
from dexdrake.episode import EpisodeResult, run_episode
from dexdrake.errors import DexdrakeError, StationFault
from dexdrake.hardware.safety import HardwareError
from dexdrake.systems.dexrep_system import DexRepSystem
from dexdrake.systems.scene import SimulationDiverged
from dexdrake.systems.station import ControllerSystem, LoopTimer, Station

SLOT_INPUTS = ("features", "hand_state", "object_pose")


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
            policy.hold(policy.GetMyMutableContextFromRoot(context), q)

    @property
    def timer(self) -> LoopTimer:
        return self.policy_system.timer if self.policy_system is not None else self.controller.timer

    def describe(self) -> str:
        """One line: the station's named systems, the DexRepSystem's feature set and path, the slot."""
        parts = [s.get_name() for s in self.station.diagram.GetSystems() if not s.get_name().startswith("drake/")]
        text = f"station ({self.station.mode}: {', '.join(parts)})"
        if self.dexrep is not None:
            text += f" -> dexrep ({self.dexrep.extractor.feature_set}, {self.dexrep.extractor.path} path)"
        kind = "PolicySystem" if self.policy_system is not None else type(self.controller).__name__
        slot = "command input" if self.controller is None else f"controller ({kind})"
        return f"{text} -> {slot} -> command"

    @property
    def command_counts(self) -> dict[str, int]:
        """Bad commands the slot held or clipped (dexdrake/command_guard.py)."""
        return (self.policy_system or self.controller).guard.counts


def build_diagram(station: Station, controller=None, feature_set: str | None = "DexRep",
                  feature_path: FeaturePath = "fast") -> BuiltDiagram:
    """The station of a scenario with DexRepSystem computing `feature_set` (None: no
    DexRepSystem, for controllers that read no features) along `feature_path` ("fast": the
    object's cached geometry at the "object_pose" port's pose; "scenegraph": the sim
    station's "query_object", refused for hil/real, whose object is known only by its
    perceived pose), and `controller` in the slot (see the module doc; None leaves the
    slot's "command" as the diagram's input)."""
    builder = DiagramBuilder()
    st = builder.AddNamedSystem("station", station.diagram)
    dexrep = None
    if feature_set is not None:
        from dexdrake.dexrep.geometry import object_geometry
        from dexdrake.systems.scenario import simulated
        from dexdrake.systems.scene import build_grasp_scene

        scenegraph = feature_path == "scenegraph"
        if scenegraph and station.scene is None:
            raise DexdrakeError(f"feature path 'scenegraph' needs the simulated object's SceneGraph; a "
                                f"{station.mode} station knows the object by its perceived pose: use 'fast'")
        if scenegraph and station.perceived is not None:
            raise DexdrakeError("feature path 'scenegraph' sees the true object; the scenario's perception "
                                "model (noise, frames, latency) needs 'fast'")
        scene = station.scene or build_grasp_scene(simulated(station.scenario))  # hil/real: kinematics only
        dexrep = builder.AddNamedSystem("dexrep", DexRepSystem(
            scene.hand, scene.plant, scene.hand_instance, object_geometry(station.scenario.object), feature_set,
            feature_path, scene.distance_geometry_id if scenegraph else None))
        for name in ("hand_state", "object_pose", "query_object")[: 3 if scenegraph else 2]:
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


def scenario_diagram(station: Station, controller: System) -> BuiltDiagram:
    """`build_diagram` with the options of the station's scenario: its policy's feature set
    and path (DexRep on the fast path without a policy entry), and no DexRepSystem when the
    slot reads no "features"."""
    policy = station.scenario.policy
    if not controller.HasInputPort("features"):
        return build_diagram(station, controller, None)
    if policy is None:
        return build_diagram(station, controller)
    return build_diagram(station, controller, policy.feature_set, policy.feature_path)


# ----------------------------------------------------------------------------- episodes
class StationEpisode:
    """A built diagram with a controller in its slot as an env of the one episode loop: each
    `step` advances one control period (the slot acts; the loop's action is unused). Scored
    with dexdrake.task on the object's true pose (sim: the plant, hil: the world, real with
    emulated_world drivers: the world process's; else not known, lift NaN). A StationFault or
    HardwareError, in a step or in the held start before the first one (`reset`: the
    world's begin, the wait for the first pose, the diagram's initialization), ends the
    episode (info["fault"]; a fault in the held start at the first step, which then sends
    nothing); the station is stopped by its owner's context manager.
    A `logger` (a RerunLogger attached to the station) records every control step and the
    fault that ended the episode."""

    def __init__(self, built: BuiltDiagram, steps: int, logger=None):
        self.built, self.horizon, self.logger = built, steps, logger
        self.object_name = built.station.scenario.object
        self.simulator = Simulator(built.diagram)
        self.context = self.simulator.get_mutable_context()
        self._world_paused = False

    def _true_pose(self) -> RigidTransform | None:
        """The object's true pose: the sim plant's or the world's (hil, an emulated real world);
        None on a real robot."""
        station = self.built.station
        if station.scene is not None:
            return station.scene.object_pose(station.scene.plant.GetMyContextFromRoot(self.context))
        if station.world is not None:
            return station.world.object_pose()
        return None

    def _object_position(self) -> np.ndarray | None:
        X_WO = self._true_pose()
        return None if X_WO is None else X_WO.translation()

    def reset(self, seed: int) -> None:
        from dexdrake.task import SuccessTracker

        station, period = self.built.station, self.built.station.scenario.control_period
        if station.scene is not None:
            station.scene.reset(station.scene.plant.GetMyMutableContextFromRoot(self.context), seed)
        elif station.mode == "real":  # the devices (and an emulated world) run on the wall clock
            self.simulator.set_target_realtime_rate(1.0)
        if station.perceived is not None:
            station.perceived.reset(seed)
        def held_start() -> None:  # a fault here ends the episode as a fault, before its first step
            if station.mode == "hil":  # the world starts the episode paused, from its initial
                station.world.begin(period)  # state (lockstep; the drivers run on its clock)
                self._world_paused = True
            if station.perception is not None:
                _await_first_pose(station)
            self.built.hold_measured(self.context)
            self.simulator.Initialize()

        self.start_fault = self._fault_of(held_start)
        self.t_start, self.k, self.period = self.context.get_time(), 0, period
        self.t_world = station.world.time if station.mode == "hil" else 0.0
        p = self._object_position()
        self.tracker = None if p is None else SuccessTracker(p)

    def step(self, action=None) -> tuple[None, float, bool, dict]:
        station = self.built.station
        k = self.k + 1

        def advance() -> None:  # the controller acts on this instant's measurements (DriverSystem),
            if station.scene is not None:
                station.scene.advance(self.simulator, self.t_start + k * self.period)
                return
            self.simulator.AdvanceTo(self.t_start + k * self.period)
            if station.mode == "hil":  # then the world runs one control period and pauses
                station.world.advance_to(self.t_world + k * self.period)

        fault = self.start_fault or self._fault_of(advance)
        if fault is None:
            self.k = k
            if self.tracker is not None:
                self.tracker.update(self._object_position())
            if self.logger is not None:
                self._log(station)
        info = {"success": self.tracker.success if self.tracker else False,
                "lift": self.tracker.max_lift if self.tracker else float("nan"), "fault": fault}
        return None, 0.0, k >= self.horizon, info

    def _log(self, station: Station) -> None:
        """This control step to the logger (systems/rerun_logger.RerunLogger.log_station_step)."""
        built, port = self.built, self.built.diagram.GetOutputPort
        self.logger.log_station_step(
            self.context.get_time(), port("hand_state").Eval(self.context), port("command").Eval(self.context),
            port("object_pose").Eval(self.context), {**built.timer.stats(), **built.command_counts},
            self._true_pose())

    def close(self) -> None:
        if self._world_paused:
            self.built.station.world.release()
            self._world_paused = False

    def _fault_of(self, run: Callable[[], None]) -> str | None:
        """Run `run`; a station's fault it raises (StationFault, HardwareError, or the sim
        station's SimulationDiverged; pydrake re-raises an event's exception as its own type)
        is logged and returned (the episode ends with it); any other exception (a bug)
        propagates."""
        try:
            run()
        except (StationFault, HardwareError, SimulationDiverged) as err:
            fault = str(err) if not isinstance(err, SimulationDiverged) else f"simulation diverged: {err}"
            if self.logger is not None:
                self.logger.log_fault(fault)
            return fault
        return None


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
    station's diagram (`scenario_diagram`), through the one episode loop: sim as fast as it
    goes, hil on the world's simulated clock (the world pauses at each control step until
    the controller has run), real in wall-clock real time. `stats`: the devices' loop
    statistics and the controller's ("policy": rate, bad commands held or clipped). `logger`:
    a RerunLogger (systems/rerun_logger.py) attached to the station, or None."""
    if steps < 1:
        raise DexdrakeError(f"steps must be >= 1, got {steps}")
    if not isinstance(controller, System):
        controller = ControllerSystem(controller, station.hand, station.scenario.control_period)
    built = scenario_diagram(station, controller)
    env = StationEpisode(built, steps, logger)
    try:
        result = run_episode(env, lambda observation: None, station.scenario.seed)
    finally:
        env.close()
    result.steps = env.k  # control periods completed (a fault ends the episode inside one)
    result.stats = station.stats()
    result.stats["policy"] = {**built.timer.stats(), **built.command_counts}
    return result
