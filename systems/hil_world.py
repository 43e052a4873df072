"""The hardware-in-the-loop world: a Drake plant co-simulated with the Allegro firmware
emulator and the Z1 controller emulator, on one simulated clock. The plant is the
scenario's grasp scene (systems/scene.py), which the station builds with the HIL joint
drive (`station.hil_drive`) and hands in: the world builds no plant of its own.

The emulators keep their bus/UDP behaviour (framing, periods, servo and FSM logic, fault
injection) and get their joints from the plant through their public dynamics hooks:
  Allegro (`JointDynamics`): effective PWM -> plant actuation tau = pwm * scenario.torque_per_pwm
           (allegro_units.NM_PER_PWM, the one PWM -> N*m assumption, times hil.pwm_torque_scale) on the
           finger joints (zero when the servo is off; the last PWM stays applied while the
           servo is on, whether or not torque frames keep coming, as specs/allegro_v4.md says);
  Z1 (`ArmDynamics`): the controller's LOWCMD/JOINTCTRL set-points -> the plant's implicit PD
           actuators (gains kp*25.6 and kd*0.0128, feed-forward torque); PASSIVE -> hold
           with damping only. The arm carries its weight and the hand's: the gravity load
           of the Z1 model (hardware/z1_model.py) acts on the arm joints, so the client's
           gravity feed-forward is what holds it up;
  plant joint positions/velocities (and arm torques) -> what the emulators stream and reply.

Timing design (correctness must not depend on how the host schedules threads):
- One clock. `HilWorld.clock()` is the plant's time. The emulators, both drivers (their PD
  dt, rate limits and watchdogs) and the station's control loop all run on it, so every
  device period, timeout and derivative is measured in simulated seconds.
- Lockstep with the hand's PD loop. The world thread advances in ticks of DEVICE_TICK_S
  (the plant updates at its own step, a whole number of ticks, and holds its state between),
  services both emulators (they stream the frames that are due on the simulated clock),
  and, when a position batch went out with the servo on, waits (at most `reply_timeout_s`
  of wall time) for the driver's 4 torque frames before the next step: the PD always acts on
  the newest positions, exactly one CAN cycle old, however slow the host is. Likewise, with
  the Z1 client attached (`attach_arm_client`), each step waits (as long) until the client
  has sent the commands of all its ticks due by then and they have arrived (the client in
  turn waits for the reply to its last command), so the arm's set-points reach the world on
  the client's 2 ms ticks on a loaded host too. What arrived while waiting acts from the
  next step.
- Lockstep with the control loop. `advance_to(t)` lets the world run up to `t` and waits
  there until that step, its exchange with the devices included, is done: the station's
  control loop calls it once per control period, so each policy step sees the world and
  the drivers at the same simulated time whatever the host's speed (without it the world
  runs freely).
- Real time at most. The world never runs ahead of the wall clock; when the host cannot keep
  up it runs slower (real-time factor < 1, reported by `stats()`) instead of taking larger
  steps, so a loaded machine slows the episode down but does not change its outcome. After
  a hiccup it catches up at most `max_lag_s` (briefly running faster than real time).
- Held until the episode begins. Until `begin()` the world's clock and both emulators run
  but the plant does not move: the robot and the object stay at rest where they were placed
  (as on a stand), so the drivers start up (the Z1 from PASSIVE, in which the arm would sag
  under its weight for as long as start-up takes in wall time) against the same still robot
  however long that takes. `begin()` pauses at the next multiple of BEGIN_GRID_S (rounded
  to the devices' common period: the CAN position period, the Z1 tick, the plant step and
  the control period) and lets the plant move from there: every episode starts from the
  same state at the same time and phase of every device loop, so the same seed gives the
  same episode (as long as no reply is later than `reply_timeout_s`). A free-running world
  (the wall-clock world of systems/emulated_world.py) is let go by `hold_until(condition)`
  instead: the plant moves from the first step at which `condition()` holds.
The hand's own joints are gravity compensated (as in the simulated scene); the arm joints
carry the arm's and the hand's weight; the object is not compensated.
"""

from __future__ import annotations

import collections
import math
import threading
import time
from collections.abc import Callable

import can
import numpy as np
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator

from dexdrake.hardware.allegro_emulator import AllegroEmulator, EmulatorConfig
from dexdrake.hardware.safety import HardwareError, period_stats
from dexdrake.hardware.z1_emulator import ArmCommand, Z1Emulator, Z1EmulatorConfig
from dexdrake.hardware.z1_model import z1_model
from dexdrake.hardware.z1_udp import ArmFSMState, Z1Config, free_udp_port
from dexdrake.systems.scenario import Scenario


# The episode begins at a multiple of this (rounded up to the devices' common period):
# start-up takes 0.2-0.3 s of world time, wall-clock dependent; beginning at the same time
# in every run keeps even the rounding of the drivers' time differences the same.
BEGIN_GRID_S = 1.0
# The world services its devices every tick: the device loops' periods are whole
# milliseconds (CAN positions 3 ms, Z1 2 ms), so at most one CAN cycle and one Z1 tick fall
# due per tick and each gets its own exchange, whatever the plant step.
DEVICE_TICK_S = 0.001


class _PlantFingers:
    """The Allegro emulator's `JointDynamics`: the PWM goes to the world, the state comes back."""

    def __init__(self, q: np.ndarray):
        self.pwm = np.zeros(len(q))
        self.q, self.dq = q.copy(), np.zeros(len(q))

    def step(self, pwm: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        self.pwm = np.asarray(pwm, float).copy()
        return self.q.copy(), self.dq.copy()


class _PlantArm:
    """The Z1 emulator's `ArmDynamics`: the command goes to the world, the state comes back."""

    def __init__(self, q: np.ndarray):
        n = len(q)
        self.command = ArmCommand(ArmFSMState.PASSIVE, q.copy(), np.zeros(n), np.zeros(n),
                                  np.zeros(n), np.zeros(n))
        self.q, self.dq, self.tau = q.copy(), np.zeros(n), np.zeros(n)

    def step(self, command: ArmCommand, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        self.command = command
        return self.q.copy(), self.dq.copy(), self.tau.copy()


class HilWorld:
    """The world plant and both device emulators, stepped in lockstep by one thread.

    `start()` / `stop()` or a context manager. `hand_emulator` answers on `hand_bus`;
    `arm_emulator` binds the scenario's controller port (0: a free port, see its `.port`
    after `start()`) and sends to `arm_client_port` (the scenario's, or a free one probed). Give the drivers `clock=world.clock` so that they run on the same
    simulated time (module doc)."""

    def __init__(self, scenario: Scenario, scene, hand_bus: can.BusABC, q0: np.ndarray, placement):
        """`scene`: the scenario's grasp scene (systems/scene.py) built with the HIL joint
        drive; the robot starts at rest at q0 (policy order), the object at `placement`."""
        self.scenario = scenario
        self.world = w = scene
        self.n_arm = len(w.hand.arm_joints)
        self.bus_perm = w.hand.hardware_permutation()  # q_bus = q_policy[perm]
        self._simulator = Simulator(w.diagram)
        self._context = self._simulator.get_mutable_context()
        self._plant_context = w.plant.GetMyMutableContextFromRoot(self._context)
        w.set_initial_state(self._plant_context, placement, q0)
        self._inputs = [w.diagram.GetInputPort(name) for name in ("desired_state", "actuation", "generalized_force")]
        self._net_actuation = w.diagram.GetOutputPort("net_actuation")
        self.placement = placement
        self._fingers = _PlantFingers(q0[self.bus_perm])
        self._arm = _PlantArm(q0[: self.n_arm])
        h, a = scenario.drivers.hand, scenario.drivers.arm
        self.hand_emulator = AllegroEmulator(
            hand_bus, h.device_id, EmulatorConfig(q0=tuple(q0[self.bus_perm]), seed=scenario.seed,
                                                  lower=h.lower, upper=h.upper),
            clock=self.clock, dynamics=self._fingers)
        # the controller sends to the client's fixed port: 0 (or none given) probes a free one
        self.arm_client_port = a.local_port or free_udp_port(a.host)
        self.arm_emulator = Z1Emulator(Z1EmulatorConfig(host=a.host, port=a.controller_port,
                                                        client_port=self.arm_client_port,
                                                        q0=tuple(q0[: self.n_arm]), seed=scenario.seed),
                                       clock=self.clock, dynamics=self._arm)
        self._desired = np.zeros(2 * w.hand.num_actuators)
        self._actuation = np.zeros(w.hand.num_actuators)
        self._arm_model = z1_model()
        self._weight = np.zeros(w.plant.num_velocities())  # generalized forces: the arm's load
        self._lock = threading.Lock()
        self._q = q0.copy()
        self._object_pose = RigidTransform()
        self._running = threading.Event()
        self._stepped = threading.Condition()  # notified after every world step
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None  # what ended the world thread, if anything
        self._t = 0.0  # the clock: it moves at a step's start, before the devices' exchange
        self._completed = 0.0  # the time of the last step completed, exchange included
        self._horizon = math.inf  # the world pauses here (advance_to)
        self._held = True  # the plant does not move until begin() or hold_until's condition
        self._let_go: Callable[[], bool] | None = None  # hold_until's condition
        self.steps = 0
        self.late_replies = 0  # hand cycles whose torques did not come within reply_timeout_s
        self.late_arm_commands = 0  # Z1 ticks whose command did not come within reply_timeout_s
        self._arm_period = 1.0 / Z1Config.rate_hz  # the Z1 client's tick (it sends one command)
        # the world's tick: DEVICE_TICK_S, or the plant step where that is finer (a divisor of both)
        self._tick = math.gcd(round(scenario.time_step * 1e6), round(DEVICE_TICK_S * 1e6)) / 1e6
        self.arm_client = None  # the Z1 client (attach_arm_client), for the lockstep
        self._wall0: float | None = None
        self._step_walls: collections.deque[float] = collections.deque(maxlen=20000)
        self._push_inputs()
        self._simulator.Initialize()
        self._publish()

    # -------------------------------------------------------------- state access
    def clock(self) -> float:
        """The simulated time now (s): the clock of the emulators, drivers and control loop."""
        return self._t

    @property
    def time(self) -> float:
        return self._t

    def object_pose(self) -> RigidTransform:
        """The object's pose in the world now (a copy)."""
        with self._lock:
            return RigidTransform(self._object_pose)

    def robot_positions(self) -> np.ndarray:
        """The robot's joint positions in policy order now."""
        with self._lock:
            return self._q.copy()

    def stats(self) -> dict[str, float]:
        """Steps, simulated and wall time, real-time factor, lag behind the wall clock,
        world step period statistics (ms of wall time) and late hand replies."""
        wall = 0.0 if self._wall0 is None else time.monotonic() - self._wall0
        out = {"steps": float(self.steps), "sim_time_s": self._t, "wall_s": wall,
               "real_time_factor": self._t / wall if wall > 0 else float("nan"),
               "lag_s": max(wall - self._t, 0.0), "late_replies": float(self.late_replies),
               "late_arm_commands": float(self.late_arm_commands)}
        step = period_stats(list(self._step_walls))
        out.update(step_p50_ms=step["p50_ms"], step_p99_ms=step["p99_ms"], step_max_ms=step["max_ms"])
        return out

    def attach_arm_client(self, client) -> None:
        """Step in lockstep with the Z1 client (hardware/z1_udp.Z1Arm, started on this
        world's clock): every step waits (at most `reply_timeout_s` of wall time) until the
        client has sent the commands of all its ticks due by then and they have arrived."""
        self.arm_client = client

    def begin(self, control_period: float) -> None:
        """Pause at the next multiple of BEGIN_GRID_S rounded to the common period of the
        device loops and `control_period` (module doc), then let the plant move from there
        on the next `advance_to`; the world stays paused."""
        periods = (self.scenario.time_step, self._arm_period, control_period,
                   self.hand_emulator.periods.position_ms / 1e3)  # 0 ms: not streaming
        common = math.lcm(*(round(p * 1e6) for p in periods if p > 0)) / 1e6
        grid = common * math.ceil(BEGIN_GRID_S / common)  # a start time the same in every run
        self.advance_to(math.ceil(self._t / grid - 1e-9) * grid)
        with self._stepped:
            self._held = False
            self._simulator.Initialize()  # the plant's context time moved on while held

    def hold_until(self, condition: Callable[[], bool]) -> None:
        """Free-running world: keep the plant held (module doc) until `condition()`, checked
        by the world thread before every step, is true; the plant moves from that step on."""
        self._let_go = condition

    def advance_to(self, t: float, stall_timeout_s: float = 5.0) -> None:
        """Let the world run up to simulated time `t`, pause there, and return when it has
        arrived (see wait_until for the errors). `release()` lets it run freely again."""
        with self._stepped:
            self._horizon = t
            self._stepped.notify_all()
        self.wait_until(t, stall_timeout_s)

    def release(self) -> None:
        """Let the world run freely (no pause point)."""
        with self._stepped:
            self._horizon = math.inf
            self._stepped.notify_all()

    def wait_until(self, t: float, stall_timeout_s: float = 5.0) -> None:
        """Block until the simulated time reaches `t`; HardwareError if the world thread died
        or its time did not move for `stall_timeout_s` of wall time."""
        if t > self._horizon + 1e-9:
            raise HardwareError(f"HIL world: waiting for t={t:.3f} s beyond its pause point "
                                f"{self._horizon:.3f} s (use advance_to)")
        last, since = self._completed, time.monotonic()
        with self._stepped:
            while self._completed < t - 1e-9:  # the step, its replies included, is done
                if self.error is not None or not self._running.is_set():
                    raise HardwareError(f"HIL world stopped at t={self._t:.3f} s: {self.error!r}")
                now = time.monotonic()
                if self._completed != last:
                    last, since = self._completed, now
                elif now - since > stall_timeout_s:
                    raise HardwareError(f"HIL world made no progress for {stall_timeout_s} s "
                                        f"at t={self._t:.3f} s")
                self._stepped.wait(0.05)

    # -------------------------------------------------------------- exchange
    def _push_inputs(self) -> None:
        w, n_arm = self.world, self.n_arm
        n = w.hand.num_actuators
        cmd = self._arm.command
        q_d, dq_d, tau_ff = cmd.q_d, cmd.dq_d, cmd.tau_ff
        arm = np.arange(n_arm)
        if cmd.fsm == ArmFSMState.PASSIVE:  # damping only: hold wherever the arm is
            q_now = w.plant.GetPositions(self._plant_context)[w.q_index]
            q_d, dq_d, tau_ff = q_now[:n_arm], np.zeros(n_arm), np.zeros(n_arm)
        self._desired[:] = 0.0
        self._desired[arm] = q_d
        self._desired[n + arm] = dq_d
        self._actuation[:] = 0.0
        self._actuation[arm] = tau_ff
        q_arm = w.plant.GetPositions(self._plant_context)[w.q_index[:n_arm]]
        self._weight[w.v_index[:n_arm]] = -self._arm_model.gravity(q_arm)
        tau_fingers = np.zeros(n - n_arm)
        tau_fingers[self.bus_perm - n_arm] = self._fingers.pwm * self.scenario.torque_per_pwm
        self._actuation[n_arm:] = tau_fingers
        for port, value in zip(self._inputs, (self._desired, self._actuation, self._weight)):
            port.FixValue(self._context, value)

    def _publish(self) -> None:
        w, n_arm = self.world, self.n_arm
        q = w.plant.GetPositions(self._plant_context)[w.q_index]
        v = w.plant.GetVelocities(self._plant_context)[w.v_index]
        tau = self._net_actuation.Eval(self._context)
        self._arm.q, self._arm.dq, self._arm.tau = q[:n_arm], v[:n_arm], tau[:n_arm]
        self._fingers.q, self._fingers.dq = q[self.bus_perm], v[self.bus_perm]
        pose = w.object_pose(self._plant_context)
        with self._lock:
            self._q = q
            self._object_pose = RigidTransform(pose)
        self._t = self._context.get_time()

    def step(self) -> None:
        """One lockstep world step (module doc); the world thread calls it in a loop."""
        t_next = (self.steps + 1) * self._tick  # a multiple of the tick (no drift from summing)
        if self._held and self._let_go is not None and self._let_go():
            self._held, self._let_go = False, None
            self._simulator.Initialize()  # the plant's context time moved on while held
        if self._held:  # the clock runs, the plant stays at rest (module doc)
            self._context.SetTime(t_next)
        else:
            self._push_inputs()
            self._simulator.AdvanceTo(t_next)
        self._publish()
        now = self._t
        hand, arm = self.hand_emulator, self.arm_emulator
        arm.poll(now)
        hand.poll(now)
        if hand.torque_pending and hand.servo_on:
            deadline = time.monotonic() + self.scenario.hil.reply_timeout_s
            while hand.torque_pending and (left := deadline - time.monotonic()) > 0:
                hand.poll(now, left)
            if hand.torque_pending:
                self.late_replies += 1
        client = self.arm_client
        if client is not None and client.next_tick < math.inf:  # wait for its ticks due by now
            deadline = time.monotonic() + self.scenario.hil.reply_timeout_s

            def waiting() -> bool:
                return client.next_tick <= now + 1e-9 or arm.commands_received < client.commands_sent

            while waiting() and (left := deadline - time.monotonic()) > 0:
                arm.poll(now, min(left, 1e-3))
            if waiting():
                self.late_arm_commands += 1
        # An emulator hands what it received to its dynamics hook at its next poll: poll
        # once more so that the frames that came while waiting act from the next step, not
        # (depending on which poll of the wait they came in) one step later.
        arm.poll(now)
        hand.poll(now)
        self.steps += 1

    # -------------------------------------------------------------- thread
    def start(self) -> None:
        """Open the Z1 emulator's port and start the world thread."""
        if self._thread is not None:
            raise HardwareError("HIL world: already started")
        self.arm_emulator.open()
        self._running.set()
        self._thread = threading.Thread(target=self._run, name="hil-world", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread, let the emulators read what the drivers sent last (their safe
        stop), and close the Z1 emulator's port."""
        self._running.clear()
        self.release()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for _ in range(3):
            self.hand_emulator.poll(self._t, 0.002)
            self.arm_emulator.poll(self._t, 0.002)
        self.arm_emulator.close()

    def __enter__(self) -> HilWorld:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        h, max_lag = self._tick, self.scenario.hil.max_lag_s
        self._wall0 = anchor = time.monotonic() - self._t  # wall time of simulated t = 0
        try:
            while self._running.is_set():
                if self._t + h > self._horizon + 1e-9:  # paused for the control loop
                    with self._stepped:
                        self._stepped.wait_for(lambda: self._t + h <= self._horizon + 1e-9
                                               or not self._running.is_set(), 0.01)
                    continue
                ahead = self._t + h - (time.monotonic() - anchor)
                if ahead > 0:  # never run ahead of the wall clock
                    time.sleep(ahead)
                elif ahead < -max_lag:  # behind by more than max_lag: run slower than real time
                    anchor -= ahead + max_lag
                self.step()
                self._step_walls.append(time.monotonic())
                with self._stepped:
                    self._completed = self._t
                    self._stepped.notify_all()
        except BaseException as err:  # the drivers' watchdogs see the world stop
            self.error = err
            raise
        finally:
            with self._stepped:
                self._stepped.notify_all()
