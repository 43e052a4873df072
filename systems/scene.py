"""The simulated grasp scene: a hand, a table and one object in a Drake diagram.

Built from a Scenario (systems/scenario.py: hand, object, plant step): the plant steps at
the scenario's `time_step` with the SAP solver and point contact; commands are PD
set-points held between control steps. SAP treats the joint PD controllers implicitly, so
the stiff gains of the model files are stable at any step. Plant output ports are computed
on demand unless `sampled_outputs` (a reader of the net actuation after every step, the
HIL world, wants them sampled: on demand, each read repeats the step's solve). The robot is
gravity compensated (the virtual arm of the paper's model is a free-floating base held by
servos).

An episode starts from `GraspScene.reset(context, seed)`: the object placed by the seed's
randomisation (`ObjectPlacement.from_seed`), the hand at rest at its pre-grasp pose. A
simulation that diverges (a non-finite state, or the plant's step fails from its state)
raises `SimulationDiverged` from `GraspScene.advance`.

The HIL world (systems/hil_world.py) steps the same scene built with a `JointDrive`: the
arm's PD gains those of the Z1 controller, the fingers torque-driven (the Allegro firmware
emulator's PWM), with the emulator's reflected inertia and damping.

Ports of the diagram (policy joint order, see the hand description):
  input  "command"     joint position set-points (n)       (no JointDrive, no desired_state)
  input  "desired_state" [q_d; v_d] of the plant's PD (2n)   (with a JointDrive or desired_state)
  input  "actuation"   feed-forward joint torques (n)                      (with a JointDrive)
  input  "generalized_force" applied generalized forces (plant velocities) (with a JointDrive)
  output "hand_state"  [q; v] (2n)
  output "object_pose" [x, y, z, qw, qx, qy, qz]
  output "net_actuation" joint torques the actuators apply, PD included (n)
  output "query_object" SceneGraph's QueryObject (for signed-distance queries)
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import ClassVar

import numpy as np
from pydrake.geometry import Box, GeometryId, ProximityProperties, Role, SceneGraph
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.plant import (
    AddMultibodyPlant,
    CoulombFriction,
    MultibodyPlant,
    MultibodyPlantConfig,
)
from pydrake.multibody.parsing import Parser
from pydrake.multibody.tree import JointActuatorIndex, ModelInstanceIndex, PdControllerGains
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Context, Diagram, DiagramBuilder
from pydrake.systems.primitives import MatrixGain

from dexdrake.errors import DexdrakeError
from dexdrake.hands.description import HandDescription, load_hand
from dexdrake.objects.library import (
    DISTANCE_GEOMETRY_NAME,
    ObjectInfo,
    add_object,
    exclude_distance_geometry_from_contact,
    get_object,
)
from dexdrake.systems.scenario import Scenario

TABLE_SIZE = (1.0, 1.0, 0.04)  # a thin box with its top face at z = 0 (not a half-space)


TABLE_FRICTION = 1.0  # Coulomb friction of the table (the objects' is the library's)


class SimulationDiverged(DexdrakeError):
    """The simulated plant cannot continue: a non-finite state, or its step fails from it."""


@dataclass(frozen=True)
class JointDrive:
    """The hand's actuators where they are not the model file's PD (policy order): PD gains
    kp, kd (both 0: torque-driven) and, for torque-driven joints, the reflected rotor
    inertia (kg*m^2) and viscous damping (N*m*s/rad)."""

    kp: np.ndarray
    kd: np.ndarray
    rotor_inertia: np.ndarray
    damping: np.ndarray


@dataclass(frozen=True)
class ObjectPlacement:
    """The paper's randomisation: x in [-0.05, 0.05], y in [-0.05, 0], yaw in [-pi, pi]."""

    X_RANGE: ClassVar[tuple[float, float]] = (-0.05, 0.05)
    Y_RANGE: ClassVar[tuple[float, float]] = (-0.05, 0.0)

    x: float
    y: float
    yaw: float

    @classmethod
    def sample(cls, rng: np.random.Generator) -> "ObjectPlacement":
        return cls(rng.uniform(*cls.X_RANGE), rng.uniform(*cls.Y_RANGE), rng.uniform(-np.pi, np.pi))

    @classmethod
    def from_seed(cls, seed: int) -> "ObjectPlacement":
        """The placement of episode `seed`: the first draws of default_rng(seed)."""
        return cls.sample(np.random.default_rng(seed))

    @classmethod
    def nearest_start(cls, xy: np.ndarray) -> np.ndarray:
        """The start position (x, y) nearest `xy`: no farther from the true start than `xy` is."""
        (x_lo, x_hi), (y_lo, y_hi) = cls.X_RANGE, cls.Y_RANGE
        return np.array([min(max(xy[0], x_lo), x_hi), min(max(xy[1], y_lo), y_hi)])

    def pose(self, info: ObjectInfo) -> RigidTransform:
        return RigidTransform(RollPitchYaw(0.0, 0.0, self.yaw), [self.x, self.y, info.rest_height])


@dataclass
class GraspScene:
    scenario: Scenario
    diagram: Diagram
    plant: MultibodyPlant
    scene_graph: SceneGraph
    hand: HandDescription
    hand_instance: ModelInstanceIndex
    object_instance: ModelInstanceIndex
    object_info: ObjectInfo
    distance_geometry_id: GeometryId
    # policy order <-> plant position/velocity indices of the hand's joints
    q_index: np.ndarray
    v_index: np.ndarray

    def hand_positions(self, plant_context: Context) -> np.ndarray:
        return self.plant.GetPositions(plant_context)[self.q_index]

    def object_pose(self, plant_context: Context) -> RigidTransform:
        return self.plant.EvalBodyPoseInWorld(plant_context, self.object_body)

    @cached_property
    def object_body(self):
        return self.plant.GetBodyByName(self.object_info.name, self.object_instance)

    def set_initial_state(self, plant_context: Context, placement: ObjectPlacement, q_hand: np.ndarray) -> None:
        """Hand at rest at `q_hand` (policy order), object at `placement`, all at rest (from the
        plant's default state, not the context's: that may hold a diverged simulation's NaNs)."""
        q = self.plant.GetDefaultPositions()
        q[self.q_index] = q_hand
        self.plant.SetPositions(plant_context, q)
        self.plant.SetVelocities(plant_context, np.zeros(self.plant.num_velocities()))
        self.plant.SetFreeBodyPose(plant_context, self.object_body, placement.pose(self.object_info))

    def reset(self, plant_context: Context, seed: int, q_hand: np.ndarray | None = None) -> ObjectPlacement:
        """The start of episode `seed`: the object at `ObjectPlacement.from_seed(seed)`, the
        hand at rest at `q_hand` (default: the pre-grasp pose); returns the placement."""
        placement = ObjectPlacement.from_seed(seed)
        q0 = self.hand.pregrasp_vector() if q_hand is None else np.asarray(q_hand, float)
        self.set_initial_state(plant_context, placement, q0)
        return placement

    def advance(self, simulator: Simulator, t: float) -> None:
        """`simulator.AdvanceTo(t)`; raises SimulationDiverged when the plant's state becomes
        non-finite, or when Drake fails (a C++ RuntimeError) and the plant's own step fails
        from the state it stopped at (the contact solver or SceneGraph refusing it); any
        other error propagates."""
        context = self.plant.GetMyContextFromRoot(simulator.get_context())
        try:
            simulator.AdvanceTo(t)
        except RuntimeError as err:
            if type(err) is not RuntimeError or not self._step_fails(context):
                raise
            raise SimulationDiverged(str(err).splitlines()[0]) from err
        if not np.isfinite(self.plant.GetPositions(context)).all():
            raise SimulationDiverged("non-finite plant positions")

    def _step_fails(self, plant_context: Context) -> bool:
        if not np.all(np.isfinite(self.plant.GetPositionsAndVelocities(plant_context))):
            return True
        try:
            self.plant.EvalUniquePeriodicDiscreteUpdate(plant_context)
        except RuntimeError:
            return True
        return False


def _joint_indices(plant: MultibodyPlant, instance: ModelInstanceIndex, names) -> tuple[np.ndarray, np.ndarray]:
    joints = [plant.GetJointByName(n, instance) for n in names]
    return np.array([j.position_start() for j in joints]), np.array([j.velocity_start() for j in joints])


def _add_table(plant: MultibodyPlant, friction: float) -> None:
    X = RigidTransform([0.0, 0.0, -TABLE_SIZE[2] / 2])
    props = ProximityProperties()
    props.AddProperty("material", "coulomb_friction", CoulombFriction(friction, friction))
    world = plant.world_body()
    plant.RegisterCollisionGeometry(world, X, Box(*TABLE_SIZE), "table", props)
    plant.RegisterVisualGeometry(world, X, Box(*TABLE_SIZE), "table", np.array([0.45, 0.35, 0.25, 1.0]))


def _actuator_order(plant: MultibodyPlant, instance: ModelInstanceIndex, hand: HandDescription) -> np.ndarray:
    """P with P[a, i] = 1 when actuator a drives policy joint i (actuator = P @ policy order)."""
    actuators = [plant.get_joint_actuator(i) for i in plant.GetJointActuatorIndices(instance)]
    order = [a.joint().name() for a in actuators]
    if sorted(order) != sorted(hand.policy_joints):
        raise ValueError(f"hand {hand.name!r}: actuated joints {order} differ from policy_joints")
    P = np.zeros((len(order), len(order)))
    for row, joint in enumerate(order):
        P[row, hand.policy_joints.index(joint)] = 1.0
    return P


def _set_drive(plant: MultibodyPlant, instance: ModelInstanceIndex, hand: HandDescription, drive: JointDrive) -> None:
    """Applies `drive` to the hand's actuators (before the plant is finalised)."""
    actuators = [plant.get_joint_actuator(JointActuatorIndex(i)) for i in range(plant.num_actuators())]
    actuators = {a.joint().name(): a for a in actuators if a.model_instance() == instance}
    for i, name in enumerate(hand.policy_joints):
        joint, actuator = plant.GetJointByName(name, instance), actuators[name]
        actuator.set_controller_gains(PdControllerGains(p=drive.kp[i], d=drive.kd[i]))
        if drive.kp[i] == 0.0 and drive.kd[i] == 0.0:
            actuator.set_default_rotor_inertia(drive.rotor_inertia[i])
            actuator.set_default_gear_ratio(1.0)
            joint.set_default_damping(drive.damping[i])


def build_grasp_scene(scenario: Scenario, drive: JointDrive | None = None, desired_state: bool = False,
                      sampled_outputs: bool = False) -> GraspScene:
    """Builds the diagram of `scenario`'s hand and object at its plant step (the hand's
    actuators as `drive` says, if given; the PD's desired velocities as an input with
    `desired_state`, else zero; output ports sampled every step with `sampled_outputs`; see
    the module doc for the ports); the episode's start is applied by `reset`."""
    hand = load_hand(scenario.hand)
    info = get_object(scenario.object)
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(
        MultibodyPlantConfig(
            time_step=scenario.time_step,
            discrete_contact_approximation=scenario.contact_approximation,
            contact_model="point",
            use_sampled_output_ports=sampled_outputs,
        ),
        builder,
    )
    (hand_instance,) = Parser(plant).AddModels(hand.model_path)
    plant.set_gravity_enabled(hand_instance, False)
    if drive is not None:
        _set_drive(plant, hand_instance, hand, drive)
    _add_table(plant, TABLE_FRICTION)
    object_instance = add_object(plant, info, masses=hand.object_mass)
    plant.Finalize()

    # The object's watertight mesh serves distance queries only: keep it out of contact.
    exclude_distance_geometry_from_contact(scene_graph)
    inspector = scene_graph.model_inspector()
    object_frame = plant.GetBodyFrameIdOrThrow(plant.GetBodyByName(info.name, object_instance).index())
    (distance_id,) = [
        g
        for g in inspector.GetGeometries(object_frame, Role.kProximity)
        if inspector.GetName(g).endswith(DISTANCE_GEOMETRY_NAME)
    ]

    P = _actuator_order(plant, hand_instance, hand)
    n = len(P)
    if drive is None and not desired_state:  # set-points q_d -> desired state [q_d; 0] in actuator order
        gains = builder.AddSystem(MatrixGain(np.vstack([P, np.zeros_like(P)])))
        builder.ExportInput(gains.get_input_port(), "command")
    else:
        gains = builder.AddSystem(MatrixGain(np.kron(np.eye(2), P)))
        builder.ExportInput(gains.get_input_port(), "desired_state")
    if drive is not None:
        torques = builder.AddSystem(MatrixGain(P))
        builder.Connect(torques.get_output_port(), plant.get_actuation_input_port(hand_instance))
        builder.ExportInput(torques.get_input_port(), "actuation")
        builder.ExportInput(plant.get_applied_generalized_force_input_port(), "generalized_force")
    builder.Connect(gains.get_output_port(), plant.get_desired_state_input_port(hand_instance))
    net = builder.AddSystem(MatrixGain(P.T))
    builder.Connect(plant.get_net_actuation_output_port(hand_instance), net.get_input_port())
    builder.ExportOutput(net.get_output_port(), "net_actuation")

    q_index, v_index = _joint_indices(plant, hand_instance, hand.policy_joints)
    nq = plant.num_positions()
    S = np.zeros((2 * n, nq + plant.num_velocities()))
    S[np.arange(n), q_index] = 1.0
    S[n + np.arange(n), nq + v_index] = 1.0
    select = builder.AddSystem(MatrixGain(S))
    builder.Connect(plant.get_state_output_port(), select.get_input_port())
    builder.ExportOutput(select.get_output_port(), "hand_state")

    # Free body state is [qw qx qy qz x y z; w; v]: reorder to [x y z qw qx qy qz].
    P = np.zeros((7, 13))
    for row, col in enumerate([4, 5, 6, 0, 1, 2, 3]):
        P[row, col] = 1.0
    pose = builder.AddSystem(MatrixGain(P))
    builder.Connect(plant.get_state_output_port(object_instance), pose.get_input_port())
    builder.ExportOutput(pose.get_output_port(), "object_pose")
    builder.ExportOutput(scene_graph.get_query_output_port(), "query_object")

    diagram = builder.Build()
    return GraspScene(
        scenario, diagram, plant, scene_graph, hand, hand_instance, object_instance, info, distance_id, q_index, v_index
    )
