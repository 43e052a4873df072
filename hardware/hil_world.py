"""The hardware-in-the-loop world: a Drake plant co-simulated in real time with the
Allegro firmware emulator and the Z1 controller emulator.

The emulators keep their bus/UDP behaviour (framing, periods, servo and FSM logic, fault
injection) but hand their joint dynamics to the plant:
  Allegro: torque frames (PWM) -> plant actuation tau = pwm * torque_per_pwm on the finger
           joints (zero when the servo is off or torque frames stop, as the firmware does);
  Z1:      the controller's joint PD (LOWCMD/JOINTCTRL set-points, gains kp*25.6 and
           kd*0.0128, feed-forward torque) -> the plant's implicit PD actuators;
           PASSIVE -> hold with damping only;
  plant joint positions/velocities -> the emulators' streamed positions and states.
The emulators have no pluggable dynamics hook, so `CoSimAllegroEmulator` and
`CoSimZ1Emulator` subclass them and replace their private `_integrate` step.
The robot is gravity compensated (as in the simulated scene); the object is not.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
from pydrake.geometry import SceneGraph
from pydrake.math import RigidTransform
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlant, MultibodyPlantConfig
from pydrake.multibody.tree import JointActuatorIndex, PdControllerGains
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder

from dexdrake.hands.description import HandDescription, load_hand
from dexdrake.hardware.allegro_emulator import AllegroEmulator
from dexdrake.hardware.safety import HardwareError
from dexdrake.hardware.z1_emulator import Z1Emulator
from dexdrake.hardware.z1_udp import KD_SCALE, KP_SCALE, ArmFSMState
from dexdrake.objects.library import add_object, exclude_distance_geometry_from_contact, get_object
from dexdrake.systems.scenario import Scenario
from dexdrake.systems.scene import ObjectPlacement, _add_table


class CoSimAllegroEmulator(AllegroEmulator):
    """The Allegro firmware emulator with its joint state supplied by the HIL world."""

    def _integrate(self, dt: float, now: float) -> None:
        active = self.servo_on and now - self._last_torque <= self.config.torque_timeout_s
        if not active:
            with self._lock:
                self._pwm[:] = 0.0

    def set_joint_state(self, q: np.ndarray, dq: np.ndarray) -> None:
        """Joint positions/velocities (bus order) measured in the world."""
        with self._lock:
            self._q = np.clip(q, self.lower, self.upper)
            self._dq = np.asarray(dq, float).copy()


class CoSimZ1Emulator(Z1Emulator):
    """The Z1 controller emulator with its joint state supplied by the HIL world."""

    def _integrate(self, dt: float, now: float) -> None:
        with self._lock:
            if self.fsm != ArmFSMState.PASSIVE and now - self._last_cmd > self.config.command_timeout_s:
                self.fsm = ArmFSMState.PASSIVE

    def joint_command(self) -> tuple[ArmFSMState, np.ndarray, np.ndarray, np.ndarray]:
        """(state, q_d, dq_d, tau_ff) the controller is tracking now."""
        with self._lock:
            return self.fsm, self._q_d.copy(), self._dq_d.copy(), self._tau_ff.copy()

    def set_joint_state(self, q: np.ndarray, dq: np.ndarray, tau: np.ndarray) -> None:
        with self._lock:
            self._q = np.clip(q, self.lower, self.upper)
            self._dq = np.asarray(dq, float).copy()
            self._tau = np.asarray(tau, float).copy()


@dataclass
class WorldPlant:
    """The world's diagram and the index maps between device orders and the plant."""

    diagram: Diagram
    plant: MultibodyPlant
    scene_graph: SceneGraph
    hand: HandDescription
    robot: object  # ModelInstanceIndex
    object_body: object
    q_index: np.ndarray  # policy order -> plant positions
    v_index: np.ndarray  # policy order -> plant velocities
    act_index: np.ndarray  # policy order -> actuator (actuation / desired-state) order


def build_world_plant(scenario: Scenario) -> WorldPlant:
    """Robot (arm PD in the plant, fingers torque-driven), table and object; see module doc."""
    hand = load_hand(scenario.hand)
    info = get_object(scenario.object)
    arm_cfg, w = scenario.drivers.arm, scenario.hil
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(
        MultibodyPlantConfig(time_step=scenario.time_step, discrete_contact_approximation="sap",
                             contact_model="point"), builder)
    (robot,) = Parser(plant).AddModels(str(hand.model_path))
    plant.set_gravity_enabled(robot, False)
    n_arm = len(hand.arm_joints)
    for i, name in enumerate(hand.policy_joints):
        joint = plant.GetJointByName(name, robot)
        actuator = _actuator_of(plant, robot, name)
        if i < n_arm:
            actuator.set_controller_gains(PdControllerGains(p=arm_cfg.kp[i] * KP_SCALE,
                                                            d=arm_cfg.kd[i] * KD_SCALE))
        else:
            actuator.set_controller_gains(PdControllerGains(p=0.0, d=0.0))  # torque-driven
            actuator.set_default_rotor_inertia(w.finger_reflected_inertia)
            actuator.set_default_gear_ratio(1.0)
            joint.set_default_damping(w.finger_damping)
    _add_table(plant, 1.0)
    object_instance = add_object(plant, info)
    plant.Finalize()
    exclude_distance_geometry_from_contact(scene_graph)
    builder.ExportInput(plant.get_desired_state_input_port(robot), "desired_state")
    builder.ExportInput(plant.get_actuation_input_port(), "actuation")
    diagram = builder.Build()
    actuators = [plant.get_joint_actuator(i) for i in plant.GetJointActuatorIndices(robot)]
    order = [a.joint().name() for a in actuators]
    q_index = np.array([plant.GetJointByName(j, robot).position_start() for j in hand.policy_joints])
    v_index = np.array([plant.GetJointByName(j, robot).velocity_start() for j in hand.policy_joints])
    act_index = np.array([order.index(j) for j in hand.policy_joints])
    body = plant.GetBodyByName(info.name, object_instance)
    return WorldPlant(diagram, plant, scene_graph, hand, robot, body, q_index, v_index, act_index)


def _actuator_of(plant: MultibodyPlant, robot, joint_name: str):
    for i in range(plant.num_actuators()):
        actuator = plant.get_joint_actuator(JointActuatorIndex(i))
        if actuator.model_instance() == robot and actuator.joint().name() == joint_name:
            return actuator
    raise HardwareError(f"joint {joint_name!r} has no actuator in the robot model")


class HilWorld:
    """Steps the world plant in real time in a thread, exchanging state with the emulators.

    `start()` / `stop()` or a context manager. The plant time follows the wall clock; when
    the host is too slow the plant falls behind by at most `max_lag_s` per step (counted in
    `stats()["lag_s"]`) instead of taking huge steps.
    """

    def __init__(self, scenario: Scenario, hand_emulator: CoSimAllegroEmulator,
                 arm_emulator: CoSimZ1Emulator, q0: np.ndarray, placement: ObjectPlacement):
        self.scenario = scenario
        self.world = build_world_plant(scenario)
        self.hand_emulator, self.arm_emulator = hand_emulator, arm_emulator
        w = self.world
        self.n_arm = len(w.hand.arm_joints)
        self.bus_perm = w.hand.hardware_permutation()  # q_bus = q_policy[perm]
        self._simulator = Simulator(w.diagram)
        self._context = self._simulator.get_mutable_context()
        self._plant_context = w.plant.GetMyMutableContextFromRoot(self._context)
        q = w.plant.GetPositions(self._plant_context).copy()
        q[w.q_index] = q0
        w.plant.SetPositions(self._plant_context, q)
        info = get_object(scenario.object)
        w.plant.SetFreeBodyPose(self._plant_context, w.object_body, placement.pose(info))
        self.placement = placement
        n = w.hand.num_actuators
        self._desired = np.zeros(2 * n)
        self._actuation = np.zeros(w.plant.num_actuators())
        self._lock = threading.Lock()
        self._object_pose = w.plant.EvalBodyPoseInWorld(self._plant_context, w.object_body)
        self._q = q0.copy()
        self._running = threading.Event()
        self._thread: threading.Thread | None = None
        self.steps = 0
        self.max_lag_s = 0.0
        self._push_inputs()
        self._simulator.Initialize()
        self._publish()

    # -------------------------------------------------------------- state access
    def object_pose(self) -> RigidTransform:
        """The object's pose in the world now (a copy)."""
        with self._lock:
            return RigidTransform(self._object_pose)

    def robot_positions(self) -> np.ndarray:
        """The robot's joint positions in policy order now."""
        with self._lock:
            return self._q.copy()

    @property
    def time(self) -> float:
        return self._context.get_time()

    def stats(self) -> dict[str, float]:
        return {"steps": float(self.steps), "sim_time_s": self.time, "lag_s": self.max_lag_s}

    # -------------------------------------------------------------- exchange
    def _push_inputs(self) -> None:
        w, n_arm = self.world, self.n_arm
        n = w.hand.num_actuators
        q_now = w.plant.GetPositions(self._plant_context)[w.q_index]
        fsm, q_d, dq_d, tau_ff = self.arm_emulator.joint_command()
        arm = w.act_index[:n_arm]
        if fsm == ArmFSMState.PASSIVE:  # damping only: hold wherever the arm is
            q_d, dq_d, tau_ff = q_now[:n_arm], np.zeros(n_arm), np.zeros(n_arm)
        self._desired[:] = 0.0
        self._desired[arm] = q_d
        self._desired[n + arm] = dq_d
        self._actuation[:] = 0.0
        self._actuation[arm] = tau_ff
        pwm_bus = self.hand_emulator.pwm
        fingers = w.act_index[n_arm:]
        tau_fingers = np.zeros(n - n_arm)
        tau_fingers[self.bus_perm - n_arm] = pwm_bus * self.scenario.hil.torque_per_pwm
        self._actuation[fingers] = tau_fingers
        w.diagram.get_input_port(0).FixValue(self._context, self._desired)
        w.diagram.get_input_port(1).FixValue(self._context, self._actuation)

    def _publish(self) -> None:
        w, n_arm = self.world, self.n_arm
        q = w.plant.GetPositions(self._plant_context)[w.q_index]
        v = w.plant.GetVelocities(self._plant_context)[w.v_index]
        tau = w.plant.get_net_actuation_output_port().Eval(self._plant_context)[w.act_index]
        self.arm_emulator.set_joint_state(q[:n_arm], v[:n_arm], tau[:n_arm])
        self.hand_emulator.set_joint_state(q[self.bus_perm], v[self.bus_perm])
        with self._lock:
            self._q = q
            self._object_pose = w.plant.EvalBodyPoseInWorld(self._plant_context, w.object_body)

    # -------------------------------------------------------------- thread
    def start(self) -> None:
        if self._thread is not None:
            raise HardwareError("HIL world: already started")
        self._running.set()
        self._thread = threading.Thread(target=self._run, name="hil-world", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._running.clear()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def __enter__(self) -> HilWorld:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        h = self.scenario.time_step
        max_lag = self.scenario.hil.max_lag_s
        wall0 = time.monotonic() - self.time
        while self._running.is_set():
            wall = time.monotonic() - wall0
            t = self.time
            if wall - t >= h:
                target = min(wall, t + max_lag)
                self._push_inputs()
                self._simulator.AdvanceTo(target)
                self._publish()
                self.steps += 1
                self.max_lag_s = max(self.max_lag_s, wall - self.time)
            time.sleep(max(h - (time.monotonic() - wall0 - self.time), 0.0005))

