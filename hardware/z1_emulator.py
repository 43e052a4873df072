"""An emulated `z1_controller` on loopback UDP (for tests and hardware-in-loop).

From the spec (specs/z1.md): it binds the controller port (8071 by default) and sends
each RecvState to the client's fixed port (`client_port`, the SDK's 8072 by default),
never to the command's source address; it silently drops (no reply; counted in
`packet_errors`) every command that is not exactly 147 bytes or whose head is not FE FF,
and anything else that does not parse; LOWCMD is entered only from PASSIVE, with the
torque law tau = kp*25.6*(q_d - q) + kd*0.0128*(dq_d - dq) + tau_ff; the arm carries the
weight of itself and its payload (the model's gravity), which LOWCMD does not compensate.
Assumptions where the spec is silent, each the less convenient one for the client:
  it never times out on its own: on command silence it keeps executing the last command
    (a client that stops talking leaves the arm doing what it was last told);
  it answers each valid command with one state and sends nothing unasked;
  LOWCMD and JOINTCTRL are left only to PASSIVE; JOINTCTRL is entered from PASSIVE and
    follows the commanded positions only while `track` is set (else it holds), with the
    controller's default gains and its own gravity compensation; other states are refused;
  PASSIVE is joint damping only (the arm sags under its weight).
The joints move with a pluggable `ArmDynamics` model stepped every tick with the
controller's current `ArmCommand`; the default, `SimpleArmDynamics`, integrates
I * ddq = clip(tau, +-effort) - g(q) - b * dq inside hard joint stops.
A hardware-in-the-loop world plugs its plant in instead (systems/hil_world.py).
Run it in its own thread (`start()`), or `open()` it and call `poll(now)` from yours.
Fault injection: stall replies, corrupt replies, report a motor error or a motor
temperature, drop to PASSIVE and stay there a while (`force_passive`, as the
controller's own protection or another program would).
"""

from __future__ import annotations

import collections
import contextlib
import math
import select
import socket
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from dexdrake.hardware.safety import HardwareError
from dexdrake.hardware.z1_model import KD_SCALE, KP_SCALE, NUM_ARM_JOINTS, z1_model
from dexdrake.hardware.z1_udp import (
    COMMAND_HEAD,
    CONTROLLER_PORT,
    SDK_PORT,
    NUM_MOTOR_SLOTS,
    ArmFSMState,
    JointState,
    MotorState,
    PacketError,
    RecvState,
    SendCmd,
    default_joint_limits,
)

# z1.md kinematics: joint origins (m, in the parent) and axes, joint1..joint6
_ORIGINS = np.array([[0, 0, 0.0585], [0, 0, 0.045], [-0.35, 0, 0], [0.218, 0, 0.057],
                     [0.07, 0, 0], [0.0492, 0, 0]])
_AXES = "zyyyzx"


def _rot(axis: str, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
            "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def flange_posture(q: Sequence[float]) -> tuple[float, ...]:
    """(rx, ry, rz, x, y, z) of link06 in link00: roll-pitch-yaw (R = Rz Ry Rx) and position."""
    rot, pos = np.eye(3), np.zeros(3)
    for origin, axis, angle in zip(_ORIGINS, _AXES, q):
        pos = pos + rot @ origin
        rot = rot @ _rot(axis, angle)
    rx = math.atan2(rot[2, 1], rot[2, 2])
    ry = math.atan2(-rot[2, 0], math.hypot(rot[2, 1], rot[2, 2]))
    rz = math.atan2(rot[1, 0], rot[0, 0])
    return (rx, ry, rz, *pos.tolist())


@dataclass(frozen=True)
class ArmCommand:
    """What the controller tracks now: its state and the LOWCMD law's terms (6 joints).
    `kp`, `kd` are the raw LOWCMD gains (scaled by 25.6 and 0.0128 in the law)."""

    fsm: ArmFSMState
    q_d: np.ndarray
    dq_d: np.ndarray
    tau_ff: np.ndarray
    kp: np.ndarray
    kd: np.ndarray

    def torque(self, q: np.ndarray, dq: np.ndarray, passive_damping: float,
               effort: np.ndarray) -> np.ndarray:
        """Motor torques at (q, dq): damping in PASSIVE, else the LOWCMD law; clipped to effort."""
        if self.fsm == ArmFSMState.PASSIVE:
            tau = -passive_damping * dq
        else:
            tau = self.kp * KP_SCALE * (self.q_d - q) + self.kd * KD_SCALE * (self.dq_d - dq) + self.tau_ff
        return np.clip(tau, -effort, effort)


class ArmDynamics(Protocol):
    """The arm's joints as the controller emulator sees them."""

    def step(self, command: ArmCommand, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Track `command` for `dt` seconds; return (q, dq, tau) after it."""
        ...


class SimpleArmDynamics:
    """Independent joints: I * ddq = tau - gravity(q) - b * dq inside hard stops, sub-stepped
    at physics_dt_s (`gravity`: the torques that hold the arm; None: weightless)."""

    def __init__(self, q0: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                 inertia: Sequence[float], damping: float, passive_damping: float,
                 effort: Sequence[float], physics_dt_s: float = 0.0005,
                 gravity: Callable[[np.ndarray], np.ndarray] | None = None):
        self.lower, self.upper = np.asarray(lower, float), np.asarray(upper, float)
        self.q = np.clip(np.asarray(q0, float), self.lower, self.upper)
        self.dq = np.zeros(NUM_ARM_JOINTS)
        self.tau = np.zeros(NUM_ARM_JOINTS)
        self.inertia, self.effort = np.asarray(inertia, float), np.asarray(effort, float)
        self.damping, self.passive_damping, self.physics_dt_s = damping, passive_damping, physics_dt_s
        self.gravity = gravity

    def step(self, command: ArmCommand, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        steps = max(1, int(math.ceil(dt / self.physics_dt_s)))
        h = dt / steps
        load = np.zeros(NUM_ARM_JOINTS) if self.gravity is None else self.gravity(self.q)
        for _ in range(steps):
            self.tau = command.torque(self.q, self.dq, self.passive_damping, self.effort)
            self.dq = self.dq + h * (self.tau - load - self.damping * self.dq) / self.inertia
            self.q = self.q + h * self.dq
            low, high = self.q < self.lower, self.q > self.upper
            self.q = np.clip(self.q, self.lower, self.upper)
            self.dq[(low & (self.dq < 0)) | (high & (self.dq > 0))] = 0.0
        return self.q.copy(), self.dq.copy(), self.tau.copy()


@dataclass(frozen=True)
class Z1EmulatorConfig:
    host: str = "127.0.0.1"
    port: int = CONTROLLER_PORT  # 0: an ephemeral port (tests)
    client_port: int = SDK_PORT  # every state goes to this port on `host`
    inertia: Sequence[float] = (0.15, 0.3, 0.15, 0.05, 0.03, 0.02)  # kg m^2, reflected
    damping: float = 0.5  # N m s / rad, always present
    passive_damping: float = 5.0  # N m s / rad, PASSIVE mode
    gravity: bool = True  # the arm and its payload weigh what the model says (else weightless)
    physics_dt_s: float = 0.0005
    q0: Sequence[float] | None = None
    lower: Sequence[float] | None = None
    upper: Sequence[float] | None = None
    seed: int = 0


class Z1Emulator:
    """The controller side, in a thread: `start()` / `stop()` or a context manager (or
    `open()` / `close()` and `poll(now)` from the caller's thread). `dynamics` moves the
    joints (default: `SimpleArmDynamics` with the config's inertia, damping and effort)."""

    _ENTRY = {ArmFSMState.LOWCMD: {ArmFSMState.PASSIVE, ArmFSMState.LOWCMD},
              ArmFSMState.JOINTCTRL: {ArmFSMState.PASSIVE, ArmFSMState.JOINTCTRL}}

    def __init__(self, config: Z1EmulatorConfig | None = None,
                 clock: Callable[[], float] = time.monotonic, dynamics: ArmDynamics | None = None):
        self.config = cfg = config or Z1EmulatorConfig()
        self._clock = clock
        model = z1_model()  # effort limits, JOINTCTRL gains and gravity of the real arm
        self._model = model
        lo, hi = (default_joint_limits() if cfg.lower is None or cfg.upper is None
                  else (cfg.lower, cfg.upper))
        self.lower, self.upper = np.asarray(lo, float), np.asarray(hi, float)
        q0 = np.zeros(NUM_ARM_JOINTS) if cfg.q0 is None else np.asarray(cfg.q0, float)
        if q0.shape != (NUM_ARM_JOINTS,):
            raise HardwareError(f"Z1 emulator q0 needs {NUM_ARM_JOINTS} values")
        q0 = np.clip(q0, self.lower, self.upper)
        self._effort = model.limits.effort.copy()
        self._lock = threading.Lock()
        self._q, self._dq, self._tau = q0, np.zeros(NUM_ARM_JOINTS), np.zeros(NUM_ARM_JOINTS)
        self.dynamics: ArmDynamics = dynamics or SimpleArmDynamics(
            q0, self.lower, self.upper, cfg.inertia, cfg.damping, cfg.passive_damping, self._effort,
            cfg.physics_dt_s, model.gravity if cfg.gravity else None)
        self._last_tick: float | None = None
        self.fsm = ArmFSMState.PASSIVE
        self._q_d = q0.copy()
        self._dq_d = np.zeros(NUM_ARM_JOINTS)
        self._tau_ff = np.zeros(NUM_ARM_JOINTS)
        self._kp = np.zeros(NUM_ARM_JOINTS)
        self._kd = np.zeros(NUM_ARM_JOINTS)
        self.rejected_transitions: collections.Counter[str] = collections.Counter()
        self.packet_errors: collections.Counter[str] = collections.Counter()
        self.commands_received = 0
        # the last valid commands as received: bytes, which the garbage collector never walks
        # (decoded, 10000 commands are ~90k objects; one full collection over them stops the
        # process for tens of ms, longer than a client's watchdog); `commands()` decodes them
        self.log: collections.deque[bytes] = collections.deque(maxlen=10000)
        self.motor_temperature_c = 25  # what every motor reports (int8)
        self.stall_until = -math.inf
        self.passive_until = -math.inf
        self.corrupt_replies = False
        self.motor_error: tuple[int, int] | None = None  # (joint index, flags)
        self._rng = np.random.default_rng(cfg.seed)
        self._sock: socket.socket | None = None
        self._running = threading.Event()
        self._thread: threading.Thread | None = None

    # --------------------------------------------------------------- control
    @property
    def port(self) -> int:
        if self._sock is None:
            raise HardwareError("Z1 emulator: not started")
        return self._sock.getsockname()[1]

    @property
    def q(self) -> np.ndarray:
        with self._lock:
            return self._q.copy()

    def start(self) -> None:
        """Open the socket and run `poll` in a thread."""
        self.open()
        self._running.set()
        self._thread = threading.Thread(target=self._run, name="z1-emulator", daemon=True)
        self._thread.start()

    def open(self) -> None:
        """Bind the controller port (without starting a thread)."""
        if self._sock is not None:
            raise HardwareError("Z1 emulator: already open")
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((self.config.host, self.config.port))
        except OSError as err:
            sock.close()
            raise HardwareError(f"Z1 emulator: cannot bind {self.config.host}:{self.config.port}: {err}") from err
        sock.setblocking(False)
        self._sock = sock
        self._last_tick = None

    @property
    def running(self) -> bool:
        """True while the emulator's thread runs (started and not ended by an error)."""
        return self._thread is not None and self._thread.is_alive()

    def stop(self) -> None:
        self._running.clear()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        self.close()

    def close(self) -> None:
        """Close the socket."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> Z1Emulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def force_passive(self, seconds: float) -> None:
        """Drop to PASSIVE now and refuse every other state for `seconds`, as something
        outside the client would (the controller's own protection, another program)."""
        with self._lock:
            self.fsm = ArmFSMState.PASSIVE
            self.passive_until = self._clock() + seconds

    def commands(self, start: int = 0) -> list[SendCmd]:
        """The logged commands from index `start` of `log` on, decoded."""
        return [SendCmd.unpack(data) for data in list(self.log)[start:]]

    def stall(self, seconds: float) -> None:
        """Send no replies for `seconds` (commands are still read and obeyed)."""
        self.stall_until = self._clock() + seconds

    # --------------------------------------------------------------- state machine
    def _enter(self, new: ArmFSMState, now: float) -> None:
        if new == self.fsm:
            return
        if new == ArmFSMState.PASSIVE:
            self.fsm = new
        elif new in self._ENTRY and self.fsm in self._ENTRY[new] and now >= self.passive_until:
            self.fsm = new
            self._q_d, self._dq_d = self._q.copy(), np.zeros(NUM_ARM_JOINTS)
            self._tau_ff = self._own_gravity(self._q_d)
            self._kp, self._kd = self._model.limits.kp.copy(), self._model.limits.kd.copy()
        else:
            self.rejected_transitions[f"{self.fsm.name}->{new.name}"] += 1

    def _own_gravity(self, q: np.ndarray) -> np.ndarray:
        """JOINTCTRL: the controller compensates the gravity its model expects."""
        return self._model.gravity(q) if self.config.gravity else np.zeros(NUM_ARM_JOINTS)

    def _apply(self, cmd: SendCmd, now: float) -> None:
        with self._lock:
            self._enter(cmd.state, now)
            joints = cmd.joints[:NUM_ARM_JOINTS]
            if self.fsm == cmd.state == ArmFSMState.LOWCMD:
                self._q_d = np.array([j.Pos for j in joints])
                self._dq_d = np.array([j.W for j in joints])
                self._tau_ff = np.array([j.T for j in joints])
                self._kp = np.array([j.K_P for j in joints])
                self._kd = np.array([j.K_W for j in joints])
            elif self.fsm == cmd.state == ArmFSMState.JOINTCTRL and cmd.track:
                self._q_d = np.clip([j.Pos for j in joints], self.lower, self.upper)
                self._dq_d = np.array([j.W for j in joints])
                self._tau_ff = self._own_gravity(self._q_d)
            self._tau = self._torque()  # the reply reports the torque of the new command

    def command(self) -> ArmCommand:
        """The command the controller is tracking now (a copy)."""
        with self._lock:
            return self._command()

    def _command(self) -> ArmCommand:
        return ArmCommand(self.fsm, self._q_d.copy(), self._dq_d.copy(), self._tau_ff.copy(),
                          self._kp.copy(), self._kd.copy())

    def _torque(self) -> np.ndarray:
        return self._command().torque(self._q, self._dq, self.config.passive_damping, self._effort)

    def _integrate(self, dt: float, now: float) -> None:
        with self._lock:
            command = self._command()
        q, dq, tau = self.dynamics.step(command, dt)
        with self._lock:
            self._q, self._dq, self._tau = (np.asarray(v, float).copy() for v in (q, dq, tau))

    def _reply_bytes(self) -> bytes:
        with self._lock:
            q, dq, tau, fsm = self._q.copy(), self._dq.copy(), self._tau.copy(), self.fsm
        joints = []
        for i in range(NUM_MOTOR_SLOTS):
            motor = MotorState(temperature=self.motor_temperature_c)
            if self.motor_error is not None and self.motor_error[0] == i:
                motor = MotorState(self.motor_temperature_c, error=self.motor_error[1])
            if i < NUM_ARM_JOINTS:
                joints.append(JointState(float(tau[i]), float(dq[i]), 0.0, float(q[i]), (motor, MotorState())))
            else:
                joints.append(JointState())
        data = RecvState(fsm, tuple(joints), flange_posture(q)).pack()
        if self.corrupt_replies:
            kind = int(self._rng.integers(3))
            if kind == 0:
                data = data[: int(self._rng.integers(len(data)))]
            elif kind == 1:
                data = data[:2] + (99).to_bytes(4, "little") + data[6:]
            else:
                data = data[:6] + b"\xff\xff\xc0\x7f" + data[10:]  # NaN torque of joint 1
        return data

    def poll(self, now: float, timeout: float = 0.0) -> None:
        """One tick at time `now` (of the emulator's clock): step the dynamics by the time
        since the last tick (at most 50 ms), then answer the commands that arrive within
        `timeout` seconds (wall)."""
        if self._sock is None:
            raise HardwareError("Z1 emulator: not open")
        if self._last_tick is None:
            self._last_tick = now
        self._integrate(min(now - self._last_tick, 0.05), now)
        self._last_tick = now
        ready, _, _ = select.select([self._sock], [], [], timeout)
        if not ready:
            return
        while True:
            try:
                data = self._sock.recv(4096)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self.packet_errors["socket"] += 1
                break
            try:
                cmd = SendCmd.unpack(data)
            except PacketError as err:
                self.packet_errors[err.kind] += 1
                continue
            if cmd.head != COMMAND_HEAD:  # the vendor controller drops it without a word
                self.packet_errors["head"] += 1
                continue
            self.commands_received += 1
            self.log.append(data)
            self._apply(cmd, now)
            if now < self.stall_until:
                continue
            with contextlib.suppress(OSError):
                self._sock.sendto(self._reply_bytes(), (self.config.host, self.config.client_port))

    def _run(self) -> None:
        while self._running.is_set():
            self.poll(self._clock(), 0.001)
