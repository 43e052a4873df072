"""A step-by-step grasp environment over the Drake scene (the learning `Env` protocol).

Built from a sim Scenario (systems/scenario.py): the sim station of every mode, its plant
step, control period and the drivers' target limits. Actions are normalised set-points in
[-1, 1] (policy order) of the joints or, with `arm_action` "palm_pose" or "palm_step", of the
palm's pose or its step and of the fingers (dexdrake/hands/action_map.py). Each `step` holds the
set-point for one control period of the plant and scores the step with `dexdrake.task`.
Observations are the selected DexRep feature set (hand state always included), computed at
the object pose the scenario's perception model delivers (dexdrake/perceived_pose.py: pose
noise, frame period and latency, drawn from the episode seed); the reward and success use
the true pose. With `feature_set=None` the observation is the hand state [q; v] alone.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator

from dexdrake.dexrep.geometry import ObjectGeometry, object_geometry
from dexdrake.episode import EpisodeResult, run_episode
from dexdrake.errors import DexdrakeError, StationFault
from dexdrake.hands.action_map import ActionMap
from dexdrake.task import SuccessTracker, TaskSpec, reward_terms
from dexdrake.command_guard import CommandGuard
from dexdrake.systems.diagram import BuiltDiagram, build_diagram
from dexdrake.systems.scenario import Scenario, ScenarioError, validate_scenario
from dexdrake.systems.scene import ObjectPlacement, SimulationDiverged
from dexdrake.systems.station import sim_station


class GraspEnv:
    """One hand, one object at a time, on the diagram of every mode (systems/diagram.py) with
    the sim station of `scenario` (its object: the first of `objects`, default the
    scenario's) and an empty controller slot: each step feeds its "command" input and
    observes what its DexRepSystem computes. The diagram is built once per object."""

    def __init__(
        self,
        scenario: Scenario,
        feature_set: str | None = None,
        horizon: int = 200,
        task: TaskSpec = TaskSpec(),
        objects: list[str] | None = None,
        arm_action: str = "joints",
    ):
        validate_scenario(scenario, f"scenario {scenario.name!r}")
        if scenario.mode != "sim":
            raise ScenarioError(f"scenario {scenario.name!r}: GraspEnv runs the sim station, not {scenario.mode}")
        self.scenario, self.feature_set, self.horizon, self.task = scenario, feature_set, horizon, task
        self.objects = objects or [scenario.object]
        self._scenes: dict[str, tuple[BuiltDiagram, Simulator, ObjectGeometry]] = {}
        self._use(self.objects[0])
        self.actions = ActionMap(self.scene.hand, arm_action)
        self.command_guard = CommandGuard(*self.scene.hand.joint_limits())  # counts bad commands of the current episode
        self.action_dim = self.scene.hand.num_actuators
        self.observation_blocks = self._features.observation_blocks if self._features else {"hand": 2 * self.action_dim}

    # -- scene management -------------------------------------------------------------
    def _use(self, name: str) -> None:
        if name not in self._scenes:
            built = build_diagram(sim_station(replace(self.scenario, object=name)), None, self.feature_set)
            self._scenes[name] = (built, Simulator(built.diagram), object_geometry(name))
        self.built, self.simulator, self.geometry = self._scenes[name]
        self.diagram, self.scene = self.built.diagram, self.built.station.scene
        self._perceived = self.built.station.perceived  # None: the features see the true pose
        self._features = None if self.built.dexrep is None else self.built.dexrep.extractor
        self.context = self.simulator.get_mutable_context()
        self.plant_context = self.scene.plant.GetMyMutableContextFromRoot(self.context)
        self._command_port = self.diagram.GetInputPort("command")
        self._tip_bodies = [self.scene.plant.GetBodyByName(p.body, self.scene.hand_instance)
                            for p in self.scene.hand.fingertips]
        self._tip_offsets = np.array([[*p.offset, 1.0] for p in self.scene.hand.fingertips])
        self._tip_rows = _rows_of(self.scene.hand.fingertips, self.scene.hand.dexrep_points)
        self._tips_at: np.ndarray | None = None  # the plant positions _tips belongs to

    # -- protocol -----------------------------------------------------------------------
    def reset(self, seed: int, q_hand: np.ndarray | None = None, object_name: str | None = None) -> np.ndarray:
        """Start an episode: object `object_name` (default: drawn from `seed` among the env's
        objects) placed with the seed's randomisation, the hand at `q_hand` (default pre-grasp)."""
        rng = np.random.default_rng(seed)
        ObjectPlacement.sample(rng)  # the placement's draws come first (GraspScene.reset)
        drawn = self.objects[rng.integers(len(self.objects))]
        if object_name is not None and object_name not in self.objects:
            raise DexdrakeError(f"object {object_name!r} is not one of this env's objects {self.objects}")
        self._use(object_name or drawn)
        self.seed = seed
        self.context.SetTime(0.0)
        self.scene.reset(self.plant_context, seed, q_hand)
        self.simulator.Initialize()
        self.p_start = self.object_position()
        self.tracker = SuccessTracker(self.p_start, self.task)
        self.steps = 0
        self.q_command = self.scene.hand_positions(self.plant_context)
        self.command_guard.reset_counts()
        if self._perceived is not None:
            self._perceived.reset(seed)
        self._observation = self.observation()
        return self._observation

    def mirror(self, hand_state: np.ndarray, X_WO: RigidTransform) -> None:
        """Put the plant in a measured state, for controllers driven by measurements: the
        hand at [q; v] (policy order), the object at rest at X_WO."""
        plant, ctx, n = self.scene.plant, self.plant_context, self.action_dim
        q = plant.GetPositions(ctx)
        q[self.scene.q_index] = hand_state[:n]
        plant.SetPositions(ctx, q)
        v = np.zeros(plant.num_velocities())
        v[self.scene.v_index] = hand_state[n:]
        plant.SetVelocities(ctx, v)
        plant.SetFreeBodyPose(ctx, self.scene.object_body, X_WO)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, dict]:
        """One control period at normalised set-points `action` (the bad-command rule of
        `command_guard` applies: non-finite -> the last command held, out of [-1, 1] -> clipped)."""
        a = np.asarray(action, dtype=float)
        if a.shape == (self.action_dim,):
            a = self.actions.command(a, self.scene.hand_positions(self.plant_context))
        return self.step_positions(a)

    def normalise(self, q_command: np.ndarray) -> np.ndarray:
        """The normalised action that `step` maps to set-points `q_command` (from the arm's
        present position)."""
        return self.actions.normalise(q_command, self.scene.hand_positions(self.plant_context))

    def step_positions(self, q_command: np.ndarray) -> tuple[np.ndarray, float, bool, dict]:
        """Like `step` with joint set-points in physical units (rad, m); `command_guard`
        holds non-finite commands and clips to the joint limits, counting both."""
        self.q_command = self.command_guard(q_command, self.q_command)
        self._command_port.FixValue(self.context, self.q_command)
        self.steps += 1
        try:
            self.scene.advance(self.simulator, self.context.get_time() + self.scenario.control_period)
        except SimulationDiverged as err:  # the state is unusable until the next reset: no lift
            return self._end(f"simulation diverged at step {self.steps} (seed {self.seed}): {err}", float("nan"))
        except StationFault as err:  # the drivers' overspeed trip, modelled (systems/target_limits.py)
            lift = float(self.object_position()[2] - self.p_start[2])
            return self._end(f"driver fault at step {self.steps} (seed {self.seed}): {err}", lift)
        self._observation = self.observation()
        p_obj = self.object_position()
        terms = reward_terms(self.fingertip_distances(), p_obj, self.p_start, self.task)
        success = self.tracker.update(p_obj)
        done = self.steps >= self.horizon
        info = {"success": success, "lift": float(p_obj[2] - self.p_start[2]), "terms": terms}
        return self._observation, terms.total, done, info

    def _end(self, fault: str, lift: float) -> tuple[np.ndarray, float, bool, dict]:
        """The step a fault ended the episode: failed, with `fault` and `lift` in its info (the
        last good observation is returned)."""
        return self._observation, 0.0, True, {"success": False, "lift": lift, "fault": fault}

    # -- state access -------------------------------------------------------------------
    def observation(self) -> np.ndarray:
        """The features of the diagram's DexRepSystem (its "features" output), or the hand
        state without a feature set. Its extractor runs on the plant's own context, whose
        kinematics the reward then reuses: reading the port would evaluate them again on the
        system's private context (scripts/bench_features_port.py measures both).
        On the fast path at the true pose its closest-point query also gives the fingertip
        distances (the fingertips are DexRep points), so the reward makes no query of its own.
        Called once per control step (the perception model takes its frames here)."""
        if self._features is None:
            return self.hand_state()
        features, closest = self._features.with_closest(self.plant_context, self.seen_object_pose())
        if (closest is not None and self._tip_rows is not None and self._features.path == "fast"
                and self._perceived is None):
            self._tips = np.maximum(closest.distance[self._tip_rows], 0.0)
            self._tips_at = self.scene.plant.GetPositions(self.plant_context)
        return features

    @property
    def object_name(self) -> str:
        return self.scene.object_info.name

    def hand_state(self) -> np.ndarray:
        plant, ctx = self.scene.plant, self.plant_context
        return np.concatenate([plant.GetPositions(ctx)[self.scene.q_index], plant.GetVelocities(ctx)[self.scene.v_index]])

    def object_pose(self) -> RigidTransform:
        return self.scene.object_pose(self.plant_context)

    def seen_object_pose(self) -> RigidTransform:
        """The object pose the features see now: the true one, or the perception model's."""
        X_WO = self.object_pose()
        if self._perceived is None:
            return X_WO
        return self._perceived.seen(self.context.get_time(), X_WO)

    def object_position(self) -> np.ndarray:
        return self.object_pose().translation().copy()

    def points_in_world(self, points) -> np.ndarray:
        """World positions (k x 3) of hand-description BodyPoints."""
        plant, ctx, inst = self.scene.plant, self.plant_context, self.scene.hand_instance
        return np.array(
            [
                plant.CalcPointsPositions(ctx, plant.GetFrameByName(p.body, inst), np.array(p.offset), plant.world_frame())[:, 0]
                for p in points
            ]
        )

    def fingertip_distances(self) -> np.ndarray:
        """Distance (>= 0) of each fingertip to the object's surface: one exact closest-point
        query on the object's watertight mesh (the same mesh SceneGraph holds for distance
        queries), computed once per configuration and shared by the reward and the expert."""
        plant, ctx = self.scene.plant, self.plant_context
        q = plant.GetPositions(ctx)
        if self._tips_at is None or not np.array_equal(self._tips_at, q):
            tips = np.array([plant.EvalBodyPoseInWorld(ctx, b).GetAsMatrix34() @ o
                             for b, o in zip(self._tip_bodies, self._tip_offsets)])
            X_WO = self.scene.object_pose(ctx)
            p_O = (tips - X_WO.translation()) @ X_WO.rotation().matrix()
            self._tips = np.maximum(self.geometry.closest_points(p_O).distance, 0.0)
            self._tips_at = q
        return self._tips.copy()

    def rollout(self, make_controller, seed: int, logger=None, object_name: str | None = None) -> EpisodeResult:
        """Runs one episode from `reset(seed)` (on `object_name` when given; the one episode
        loop, dexdrake/episode.py).
        `make_controller(env)` is called once after the reset and returns
        `controller(env) -> q_command` (set-points), called every control step; `logger` (a
        RerunLogger) records the episode."""
        controller = None

        def act(observation: np.ndarray) -> np.ndarray:
            nonlocal controller
            controller = controller or make_controller(self)
            return self.normalise(controller(self))

        return run_episode(self, act, seed, object_name=object_name, **({} if logger is None else logger.hooks(self)))


def _rows_of(points, among) -> np.ndarray | None:
    """Indices in `among` of each of `points` (same body and offset), or None if one is missing."""
    keys = [(p.body, tuple(p.offset)) for p in among]
    try:
        return np.array([keys.index((p.body, tuple(p.offset))) for p in points])
    except ValueError:
        return None
