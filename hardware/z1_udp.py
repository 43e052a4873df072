"""Unitree Z1 arm over UDP: the SDK's packed wire structs and a 500 Hz client.

Wire formats (specs/z1.md, packed little-endian, from the SDK's public header):
JointCmd 20 B, SendCmd 147 B, JointState 22 B, RecvState 208 B; ArmFSMState is a 4-byte
enum in header order. The client plays the SDK side (binds 8072, sends to 8071 on
localhost by default): each 2 ms tick it sends one SendCmd and reads the RecvState replies.
The vendor controller silently drops a command that is not 147 bytes or whose head is not
FE FF, so every command carries that head.
Modes: LOWCMD (per-joint q, dq, tau_ff, kp, kd; the controller computes
tau = kp*25.6*(q_d - q) + kd*0.0128*(dq_d - dq) + tau_ff; tau_ff carries the gravity
feed-forward of the arm and its payload, from the model) and JOINTCTRL (joint targets,
`track` set so that the controller follows them).
Limits, gains and the payload come from the model file (hardware/z1_model.py); a config
beyond them is refused. Safety: targets clamped `limit_margin_rad` inside the joint limits,
a velocity limit on targets, torque clamped to the effort limits; a state watchdog, motor
error flags, motor temperatures, joints reported beyond their velocity limit and the
controller leaving the mode on its own (never re-armed: specs/z1.md) latch a fault and
command PASSIVE until `reset_fault()`, which re-arms at the position measured after it (the
old set-point and feed-forward dropped). `stop()` holds first, then commands PASSIVE.
`probe()` checks the ports without sending anything (the protocol has no pure query).
`OfficialZ1` wraps Unitree's own `unitree_arm_interface` binding when it is importable.
"""

from __future__ import annotations

import collections
import contextlib
import math
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from dexdrake.hardware.z1_model import NUM_ARM_JOINTS, Z1Limits, z1_model
from dexdrake.hardware.safety import (
    MIN_PLAUSIBLE_TEMPERATURE_C,
    OVERSPEED_TOLERANCE,
    FaultLatch,
    check_limit_margin,
    measured_velocity_limits,
    SafeStopContext,
    HardwareError,
    JointLimits,
    paced_rate,
    RateLimiter,
    Watchdog,
    period_stats,
)

NUM_MOTOR_SLOTS = 7  # 6 joints + gripper
SDK_PORT, CONTROLLER_PORT = 8072, 8071  # the SDK binds 8072; z1_controller binds 8071
COMMAND_HEAD = (0xFE, 0xFF)  # SendCmd.head: anything else is dropped by the controller
MODE_SETTLE_TICKS = 10  # the controller counts as in the mode once seen there after this many ticks in a
# row of requesting it: a PASSIVE the client itself sent before (a fault, a reset) may act later

# motor error flags and connection codes (Motor_State)
MOTOR_OVER_CURRENT, MOTOR_PHASE_LEAKAGE, MOTOR_OVER_HEAT, MOTOR_JUMPED = 0x01, 0x02, 0x04, 0x20


class ArmFSMState(IntEnum):
    """The controller's state machine, in the SDK header's order (LOWCMD = 16)."""

    INVALID = 0
    PASSIVE = 1
    JOINTCTRL = 2
    CARTESIAN = 3
    MOVEJ = 4
    MOVEL = 5
    MOVEC = 6
    TRAJECTORY = 7
    TOSTATE = 8
    SAVESTATE = 9
    TEACH = 10
    TEACHREPEAT = 11
    CALIBRATION = 12
    SETTRAJ = 13
    BACKTOSTART = 14
    NEXT = 15
    LOWCMD = 16


class PacketError(HardwareError):
    """A UDP packet that is not a valid Z1 struct; `kind` names what was wrong."""

    def __init__(self, kind: str, detail: str):
        self.kind = kind
        super().__init__(f"bad Z1 packet ({kind}): {detail}")


_JOINT_CMD = struct.Struct("<5f")
_SEND_HEAD = struct.Struct("<2Bi?")
_JOINT_STATE = struct.Struct("<4f" + "bBB" * 2)
_RECV_HEAD = struct.Struct("<2Bi")
_POSTURE = struct.Struct("<6d")
JOINT_CMD_SIZE = _JOINT_CMD.size
SEND_CMD_SIZE = _SEND_HEAD.size + NUM_MOTOR_SLOTS * _JOINT_CMD.size
JOINT_STATE_SIZE = _JOINT_STATE.size
RECV_STATE_SIZE = _RECV_HEAD.size + NUM_MOTOR_SLOTS * _JOINT_STATE.size + _POSTURE.size


def _finite(values: Sequence[float], what: str) -> None:
    if not all(math.isfinite(v) for v in values):
        raise PacketError("nonfinite", f"{what} has non-finite values {tuple(values)}")


def _state_enum(value: int) -> ArmFSMState:
    try:
        return ArmFSMState(value)
    except ValueError:
        raise PacketError("enum", f"ArmFSMState {value} outside 0..16") from None


@dataclass(frozen=True)
class JointCmd:
    """One motor command: feed-forward torque T, velocity W, position Pos, gains K_P, K_W."""

    T: float = 0.0
    W: float = 0.0
    Pos: float = 0.0
    K_P: float = 0.0
    K_W: float = 0.0

    def pack(self) -> bytes:
        vals = (self.T, self.W, self.Pos, self.K_P, self.K_W)
        _finite(vals, "JointCmd")
        return _JOINT_CMD.pack(*vals)

    @classmethod
    def unpack(cls, data: bytes) -> JointCmd:
        if len(data) != JOINT_CMD_SIZE:
            raise PacketError("size", f"JointCmd is {JOINT_CMD_SIZE} bytes, got {len(data)}")
        vals = _JOINT_CMD.unpack(data)
        _finite(vals, "JointCmd")
        return cls(*vals)


@dataclass(frozen=True)
class SendCmd:
    """SDK -> controller: head, requested state, track flag and 7 joint commands."""

    state: ArmFSMState
    joints: tuple[JointCmd, ...] = (JointCmd(),) * NUM_MOTOR_SLOTS
    track: bool = False
    head: tuple[int, int] = COMMAND_HEAD

    def pack(self) -> bytes:
        if len(self.joints) != NUM_MOTOR_SLOTS:
            raise PacketError("size", f"SendCmd needs {NUM_MOTOR_SLOTS} JointCmd, got {len(self.joints)}")
        state = _state_enum(int(self.state))
        return _SEND_HEAD.pack(*self.head, state, self.track) + b"".join(j.pack() for j in self.joints)

    @classmethod
    def unpack(cls, data: bytes) -> SendCmd:
        if len(data) != SEND_CMD_SIZE:
            raise PacketError("size", f"SendCmd is {SEND_CMD_SIZE} bytes, got {len(data)}")
        h0, h1, state, _ = _SEND_HEAD.unpack_from(data)
        track_byte = data[_SEND_HEAD.size - 1]
        if track_byte > 1:
            raise PacketError("range", f"SendCmd track byte {track_byte} is not a bool")
        off = _SEND_HEAD.size
        joints = tuple(JointCmd.unpack(data[off + i * JOINT_CMD_SIZE: off + (i + 1) * JOINT_CMD_SIZE])
                       for i in range(NUM_MOTOR_SLOTS))
        return cls(_state_enum(state), joints, bool(track_byte), (h0, h1))


@dataclass(frozen=True)
class MotorState:
    temperature: int = 25  # int8, C
    error: int = 0  # flags: 0x01 over-current, 0x02 phase leakage, 0x04 over-heat, 0x20 jumped
    connection: int = 0  # top 2 bits: 0 ok, 1 disconnected, 2 CRC error

    @property
    def link(self) -> int:
        return self.connection >> 6


@dataclass(frozen=True)
class JointState:
    """One joint: torque T, velocity W, acceleration Acc, position Pos; 2 motor states."""

    T: float = 0.0
    W: float = 0.0
    Acc: float = 0.0
    Pos: float = 0.0
    motors: tuple[MotorState, MotorState] = (MotorState(), MotorState())

    def pack(self) -> bytes:
        vals = (self.T, self.W, self.Acc, self.Pos)
        _finite(vals, "JointState")
        flat = [v for m in self.motors for v in (m.temperature, m.error, m.connection)]
        try:
            return _JOINT_STATE.pack(*vals, *flat)
        except struct.error as err:
            raise PacketError("range", f"motor state {self.motors}: {err}") from None

    @classmethod
    def unpack(cls, data: bytes) -> JointState:
        if len(data) != JOINT_STATE_SIZE:
            raise PacketError("size", f"JointState is {JOINT_STATE_SIZE} bytes, got {len(data)}")
        t, w, acc, pos, *m = _JOINT_STATE.unpack(data)
        _finite((t, w, acc, pos), "JointState")
        return cls(t, w, acc, pos, (MotorState(*m[:3]), MotorState(*m[3:])))


@dataclass(frozen=True)
class RecvState:
    """Controller -> SDK: head, current state, 7 joint states and the flange posture."""

    state: ArmFSMState
    joints: tuple[JointState, ...] = (JointState(),) * NUM_MOTOR_SLOTS
    posture: tuple[float, float, float, float, float, float] = (0.0,) * 6  # rx, ry, rz, x, y, z
    head: tuple[int, int] = (0xFE, 0xEF)  # not checked by the SDK side

    def pack(self) -> bytes:
        if len(self.joints) != NUM_MOTOR_SLOTS or len(self.posture) != 6:
            raise PacketError("size", "RecvState needs 7 joint states and a 6-value posture")
        _finite(self.posture, "posture")
        return (_RECV_HEAD.pack(*self.head, _state_enum(int(self.state)))
                + b"".join(j.pack() for j in self.joints) + _POSTURE.pack(*self.posture))

    @classmethod
    def unpack(cls, data: bytes) -> RecvState:
        if len(data) != RECV_STATE_SIZE:
            raise PacketError("size", f"RecvState is {RECV_STATE_SIZE} bytes, got {len(data)}")
        h0, h1, state = _RECV_HEAD.unpack_from(data)
        off = _RECV_HEAD.size
        joints = tuple(JointState.unpack(data[off + i * JOINT_STATE_SIZE: off + (i + 1) * JOINT_STATE_SIZE])
                       for i in range(NUM_MOTOR_SLOTS))
        posture = _POSTURE.unpack_from(data, off + NUM_MOTOR_SLOTS * JOINT_STATE_SIZE)
        _finite(posture, "posture")
        return cls(_state_enum(state), joints, posture, (h0, h1))


# ----------------------------------------------------------------------------- client
def default_joint_limits() -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) of joint1..6 from the model file (hardware/z1_model.py)."""
    limits = z1_model().limits
    return limits.lower.copy(), limits.upper.copy()


@dataclass(frozen=True)
class Z1Config:
    """Client settings. None means the model's value (hardware/z1_model.py): gains, velocity
    limit and joint limits may be lowered from there, never raised (`check_z1_config`)."""

    host: str = "127.0.0.1"
    local_port: int = SDK_PORT  # the controller sends every state here (a real one: 8072 only)
    controller_port: int = CONTROLLER_PORT
    rate_hz: float = 500.0
    watchdog_timeout_s: float = 0.05
    mode: ArmFSMState = ArmFSMState.LOWCMD  # LOWCMD or JOINTCTRL
    kp: Sequence[float] | None = None  # raw LOWCMD gains
    kd: Sequence[float] | None = None
    # rad/s on targets, every joint: below the joints' limit (pi), so that a lunge and its impact on
    # the table stay below the overspeed trip (1.5 x the limit); training's scenario uses the same
    max_velocity: float = 2.0
    max_measured_velocity: float | None = None  # rad/s (x 1.5) a joint may reach; None: the model's
    limit_margin_rad: float = 0.02  # targets stay this far inside the joint limits
    # a motor reported hotter trips. Not in the spec (it names an over-heat flag, no
    # temperature): an assumption, the Allegro's limit
    max_motor_temperature_c: float = 70.0
    lower: Sequence[float] | None = None
    upper: Sequence[float] | None = None
    gravity_feedforward: bool = True  # LOWCMD: send the model's gravity torques as tau_ff
    # send the rate-limited reference's velocity as the desired velocity W (as the vendor's
    # LOWCMD example does); False: W = 0, the arm's PD damps towards rest and lags a ramp
    velocity_feedforward: bool = True
    # the period (s) the caller sends targets at: each new target is followed evenly over it
    # (hardware/safety.py paced_rate, at most max_velocity); None: at max_velocity, then held
    command_period_s: float | None = None
    # state() waits up to this long (wall) for the reply to the last command sent, if it has
    # not come yet (hardware-in-the-loop: a sample in lockstep with the world; 0: never waits)
    reply_wait_s: float = 0.0
    mode_timeout_s: float = 1.0  # how long start() waits for the controller to enter `mode`


@dataclass(frozen=True)
class Z1Settings:
    """A config resolved against the model's limits."""

    kp: np.ndarray
    kd: np.ndarray
    max_velocity: float  # on targets
    lower: np.ndarray  # the joint limits
    upper: np.ndarray
    effort: np.ndarray
    target_lower: np.ndarray  # the limits less the margin: targets are clamped into these
    target_upper: np.ndarray
    max_measured_velocity: np.ndarray  # per joint: a joint reported faster trips


def check_z1_config(cfg: Z1Config, limits: Z1Limits | None = None) -> Z1Settings:
    """Resolve `cfg` against the model's `limits`; HardwareError naming the limit a value
    exceeds (gains above the vendor defaults, a velocity above the joints' limit, joint
    limits outside the model's, a margin that leaves no range)."""
    lim = limits or z1_model().limits
    src = lim.source
    if cfg.mode not in (ArmFSMState.LOWCMD, ArmFSMState.JOINTCTRL):
        raise HardwareError(f"Z1 mode must be LOWCMD or JOINTCTRL, got {cfg.mode!r}")
    for name in ("rate_hz", "watchdog_timeout_s", "mode_timeout_s"):
        value = getattr(cfg, name)
        if not (math.isfinite(value) and value > 0):
            raise HardwareError(f"Z1 {name} must be > 0, got {value}")
    if not (math.isfinite(cfg.reply_wait_s) and cfg.reply_wait_s >= 0):
        raise HardwareError(f"Z1 reply_wait_s must be >= 0, got {cfg.reply_wait_s}")
    if cfg.command_period_s is not None and not (math.isfinite(cfg.command_period_s) and cfg.command_period_s > 0):
        raise HardwareError(f"Z1 command_period_s must be > 0, got {cfg.command_period_s}")

    def vec(values, default: np.ndarray, name: str) -> np.ndarray:
        arr = default.copy() if values is None else _vec6(values, name)
        if np.any(arr < 0):
            raise HardwareError(f"Z1 {name} must be >= 0, got {arr.tolist()}")
        return arr

    kp, kd = vec(cfg.kp, lim.kp, "kp"), vec(cfg.kd, lim.kd, "kd")
    for name, arr, top in (("kp", kp, lim.kp), ("kd", kd, lim.kd)):
        if np.any(arr > top + 1e-9):
            i = int(np.flatnonzero(arr > top + 1e-9)[0])
            raise HardwareError(f"Z1 {name}[{i}] = {arr[i]:g} exceeds the LOWCMD gain "
                                f"{top[i]:g} of joint{i + 1} in {src}")
    vmax = float(np.min(lim.velocity))
    velocity = float(cfg.max_velocity)
    if not (math.isfinite(velocity) and 0 < velocity <= vmax + 1e-9):
        raise HardwareError(f"Z1 max_velocity {velocity:g} rad/s must be in (0, {vmax:g}], "
                            f"the joints' velocity limit in {src}")
    lower = lim.lower.copy() if cfg.lower is None else _vec6(cfg.lower, "lower")
    upper = lim.upper.copy() if cfg.upper is None else _vec6(cfg.upper, "upper")
    if np.any(lower < lim.lower - 1e-6) or np.any(upper > lim.upper + 1e-6):
        raise HardwareError(f"Z1 joint limits {lower.tolist()} .. {upper.tolist()} reach outside "
                            f"the model's {lim.lower.tolist()} .. {lim.upper.tolist()} ({src})")
    measured = measured_velocity_limits("Z1", cfg.max_measured_velocity, lim.velocity, src)
    m = cfg.limit_margin_rad
    check_limit_margin("Z1", m, lower, upper)
    if not math.isfinite(cfg.max_motor_temperature_c):
        raise HardwareError(f"Z1 max_motor_temperature_c must be finite, got {cfg.max_motor_temperature_c}")
    return Z1Settings(kp, kd, velocity, lower, upper, lim.effort.copy(), lower + m, upper - m, measured)


@dataclass(frozen=True)
class Z1Probe:
    """What `Z1Arm.probe()` found: whether the controller's port is bound on this machine
    (None: not knowable, a remote host or no /proc/net/udp) and a state heard unasked."""

    controller_bound: bool | None
    state: RecvState | None


def udp_port_bound(port: int) -> bool | None:
    """Whether a local UDP socket (IPv4 or IPv6) is bound to `port`, read from the kernel's
    /proc/net/udp tables (nothing is sent or bound); None where they cannot be read."""
    found = None
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = open(table).read().splitlines()[1:]
        except OSError:
            continue
        found = bool(found) or any(int(line.split()[1].rsplit(":", 1)[1], 16) == port for line in lines)
    return found


@dataclass(frozen=True)
class Z1State:
    t: float
    fsm: ArmFSMState
    q: np.ndarray
    dq: np.ndarray
    tau: np.ndarray
    posture: np.ndarray
    fault: str | None
    q_target: np.ndarray = field(default_factory=lambda: np.zeros(NUM_ARM_JOINTS))


class Z1Arm(SafeStopContext):
    """Z1 client over UDP: 500 Hz send/receive thread, limits, watchdog, safe stop.

    Use as a context manager (`with Z1Arm(cfg) as arm:`): start() waits until the
    controller reports the configured mode; exit (or Ctrl-C, SIGTERM, an exception)
    commands PASSIVE and closes the socket.
    """

    def __init__(self, config: Z1Config | None = None, clock: Callable[[], float] = time.monotonic):
        self.config = cfg = config or Z1Config()
        self._clock = clock
        self.model = z1_model()
        self.settings = st = check_z1_config(cfg, self.model.limits)
        self.limits = JointLimits(st.target_lower, st.target_upper)
        self.kp, self.kd, self.effort = st.kp, st.kd, st.effort
        self._rate = RateLimiter(st.max_velocity, initial=self.limits.last_safe)
        self._pace = np.full(NUM_ARM_JOINTS, st.max_velocity)  # the reference's rate toward the target
        self._watchdog = Watchdog(cfg.watchdog_timeout_s, clock)
        self.fault = FaultLatch(clock)
        self._lock = threading.Lock()
        self._receiving = threading.Lock()  # one reader drains the socket at a time, in order
        self._send_lock = threading.Lock()
        self._halted = False  # set by stop(): the loop sends nothing from then on
        self._in_mode = False  # the controller reached the mode since (re)start
        self._requested = 0  # ticks in a row whose command requested the mode
        self._heard = False  # a state came since (re)start or reset: `_last` shows the arm now
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._running = threading.Event()
        self._reset_request = threading.Event()
        self._target = self.limits.last_safe
        self._dq_target = np.zeros(NUM_ARM_JOINTS)
        self._tau_ff = np.zeros(NUM_ARM_JOINTS)
        self._has_command = False
        self._dq_given = False
        self._last: RecvState | None = None
        self._t_state = math.nan
        self._initialised = False
        self._tick_times: collections.deque[float] = collections.deque(maxlen=20000)
        self.packet_errors: collections.Counter[str] = collections.Counter()
        self.packets_received = 0
        self.commands_sent = self._answered = 0  # commands sent; the count sent when a reply last came
        self._replies_flowing = True  # the last reply_wait_s wait was not in vain
        self.next_tick = math.inf  # clock time of the loop's next command (inf: not running)
        self.torque_clamped = 0  # ticks whose feed-forward torque hit an effort limit

    # --------------------------------------------------------------- session
    @property
    def local_port(self) -> int:
        if self._sock is None:
            raise HardwareError("Z1: not started")
        return self._sock.getsockname()[1]

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def probe(self, timeout_s: float = 0.3) -> Z1Probe:
        """Check the link without sending anything: the Z1 protocol has no pure query (every
        SendCmd names a state the controller enters, PASSIVE included: an arm another
        program holds would go limp), so this binds the client port (HardwareError when it
        is taken: another program is the controller's client), listens `timeout_s` for a
        state sent unasked, and reads whether the controller's port is bound locally."""
        if self._sock is not None:
            raise HardwareError("Z1: probe() is for an arm that is not started")
        cfg = self.config
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            try:
                sock.bind((cfg.host, cfg.local_port))
            except OSError as err:
                raise HardwareError(f"Z1: cannot bind UDP {cfg.host}:{cfg.local_port}: {err} "
                                    "(another program is the controller's client?)") from err
            state = None
            if select.select([sock], [], [], timeout_s)[0]:
                with contextlib.suppress(PacketError):
                    state = RecvState.unpack(sock.recv(4096))
        local = cfg.host in ("127.0.0.1", "localhost", "::1")
        return Z1Probe(udp_port_bound(cfg.controller_port) if local else None, state)

    def start(self) -> None:
        """Bind, start the loop (PASSIVE first, then the configured mode) and wait for it."""
        if self._thread is not None:
            raise HardwareError("Z1: already started")
        if self.fault.tripped:
            raise HardwareError(f"Z1: fault latched ({self.fault.reason}); call reset_fault() first")
        cfg = self.config
        with self._lock:
            self._forget_command()
            self._initialised, self._last = False, None
            self._in_mode = self._halted = self._heard = False
            self._requested = 0
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((cfg.host, cfg.local_port))
        except OSError as err:
            sock.close()
            raise HardwareError(f"Z1: cannot bind UDP {cfg.host}:{cfg.local_port}: {err}") from err
        sock.setblocking(False)
        self._sock = sock
        self._watchdog.reset()
        self._running.set()
        self._thread = threading.Thread(target=self._loop, name="z1-udp", daemon=True)
        self._thread.start()
        deadline = self._clock() + cfg.mode_timeout_s
        while self._clock() < deadline:
            st = self._last
            if st is not None and st.state == cfg.mode and self._initialised:
                return
            if self.fault.tripped:
                break
            time.sleep(0.002)
        reason = self.fault.reason or f"controller did not enter {cfg.mode.name}"
        self.stop()
        raise HardwareError(f"Z1: start failed: {reason} (is z1_controller running on "
                            f"{cfg.host}:{cfg.controller_port}?)")

    def stop(self) -> None:
        """Safe stop: hold first (the mode's command at the measured position, zero velocity;
        the loop sends nothing from then on), then the loop thread ends, then PASSIVE
        (the state every mode may go to) and the socket closes. The controller keeps
        executing the last command it got, so a stop cut short leaves the arm holding, not
        tracking an old target. Run it to the end: `with arm:` shields it from signals."""
        self._running.clear()
        self.next_tick = math.inf
        if self._sock is not None:
            with self._send_lock:
                self._halted = True
            with contextlib.suppress(OSError):
                self._send(self._hold())
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        if self._sock is not None:
            with contextlib.suppress(OSError):
                for _ in range(3):
                    self._send(SendCmd(ArmFSMState.PASSIVE))
            self._sock.close()
            self._sock = None

    # --------------------------------------------------------------- commands and state
    def command_positions(self, q: Sequence[float] | np.ndarray, dq: Sequence[float] | None = None,
                          tau_ff: Sequence[float] | None = None) -> np.ndarray:
        """Set joint targets (rad) with optional velocity and feed-forward torque (LOWCMD).

        Without `dq`, the velocity of the rate-limited reference is fed forward (zero with
        `velocity_feedforward` off).
        The target is clamped into the joint limits (non-finite targets are rejected and
        the last safe one is held) and followed at no more than `max_velocity`, evenly over
        `command_period_s` where set. `tau_ff` adds to the gravity feed-forward; their sum is
        clamped to the effort limits.
        """
        dq_t = np.zeros(NUM_ARM_JOINTS) if dq is None else _vec6(dq, "dq")
        self._dq_given = dq is not None
        tau = np.zeros(NUM_ARM_JOINTS) if tau_ff is None else _vec6(tau_ff, "tau_ff")
        vmax = self.settings.max_velocity
        dq_t = np.clip(dq_t, -vmax, vmax)
        with self._lock:
            self._target = self.limits.apply(q)
            self._pace_to_target()
            self._dq_target, self._tau_ff = dq_t, tau
            self._has_command = True
            return self._target.copy()

    def reset_fault(self) -> None:
        """Clear a latched fault and drop the set-point and feed-forward commanded before it.

        While running, the loop thread clears the latch, commands PASSIVE until it hears a
        state from the controller (the last one heard may be from before the arm sagged),
        then re-enters the mode holding the position measured when the controller takes it
        (zero velocity, no feed-forward but gravity's) until the next `command_positions`.
        When stopped, only the latch clears.
        """
        with self._lock:
            self._forget_command()
        if self.running:
            self._reset_request.set()
        else:
            self.fault.reset()

    def _pace_to_target(self) -> None:
        """The reference's rate toward the target from where it is now (under `_lock`)."""
        if self.config.command_period_s is not None:
            self._pace = paced_rate(self._rate.output, self._target, self.settings.max_velocity,
                                    self.config.command_period_s)

    def _forget_command(self) -> None:
        """No set-point and no feed-forward (under `_lock`): the loop holds the measured position."""
        self._has_command = self._dq_given = False
        self._dq_target = np.zeros(NUM_ARM_JOINTS)
        self._tau_ff = np.zeros(NUM_ARM_JOINTS)

    def state(self) -> Z1State:
        """The newest state the controller sent: replies already delivered to the socket
        are read first, so a reader never sees an older state than is there to read."""
        with contextlib.suppress(OSError, ValueError):
            self._receive_reply()
        with self._lock:
            st = self._last
            q_target = self._rate.output
        if st is None:
            nan = np.full(NUM_ARM_JOINTS, np.nan)
            return Z1State(math.nan, ArmFSMState.INVALID, nan, nan, nan, np.full(6, np.nan),
                           self.fault.reason, q_target)
        joints = st.joints[:NUM_ARM_JOINTS]
        return Z1State(self._t_state, st.state, np.array([j.Pos for j in joints]),
                       np.array([j.W for j in joints]), np.array([j.T for j in joints]),
                       np.array(st.posture), self.fault.reason, q_target)

    def stats(self) -> dict[str, object]:
        """Loop rate/jitter (period mean/p50/p99/max in ms) and packet counters."""
        out: dict[str, object] = period_stats(list(self._tick_times))
        out.update(packets_received=self.packets_received, packet_errors=dict(self.packet_errors),
                   rejected_commands=self.limits.non_finite, clamped_commands=self.limits.clipped,
                   torque_clamped=self.torque_clamped, fault=self.fault.reason)
        return out

    def loop_times(self, since: float = -math.inf) -> np.ndarray:
        """The loop's tick times (the clock's s) after `since`, of the last 20000 kept."""
        times = np.fromiter(list(self._tick_times), float)
        return times[times > since]

    # --------------------------------------------------------------- loop
    def _send(self, cmd: SendCmd, tick: bool = False) -> None:
        """Send `cmd`; a loop `tick`'s command is dropped once stop() has begun."""
        assert self._sock is not None
        with self._send_lock:
            if tick and self._halted:
                return
            self._sock.sendto(cmd.pack(), (self.config.host, self.config.controller_port))
            self.commands_sent += 1

    def _receive_reply(self) -> None:
        """Receive; then, with `reply_wait_s`, wait that long at most for the reply to the
        last command sent if it has not come yet (not again after a wait in vain until
        replies come again: a silent controller is the watchdog's business)."""
        sock = self._sock
        if sock is None:
            return
        self._receive()
        if self._answered < self.commands_sent and self.config.reply_wait_s > 0 and self._replies_flowing:
            select.select([sock], [], [], self.config.reply_wait_s)
            self._receive()
            self._replies_flowing = self._answered >= self.commands_sent

    def _receive(self) -> None:
        """Drain the socket; validate and keep the newest state (the loop thread and
        `state()` both call it)."""
        with self._receiving:
            self._drain()

    def _drain(self) -> None:
        sock = self._sock
        if sock is None:
            return
        while True:
            try:
                data = sock.recv(4096)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # e.g. ICMP port unreachable surfaced on loopback
                if sock.fileno() < 0:  # closed by stop()
                    return
                self.packet_errors["socket"] += 1
                continue
            try:
                st = RecvState.unpack(data)
            except PacketError as err:
                self.packet_errors[err.kind] += 1
                continue
            self.packets_received += 1
            self._answered, self._replies_flowing = self.commands_sent, True
            self._watchdog.feed()
            with self._lock:
                self._last, self._t_state, self._heard = st, self._clock(), True
            self._check_motors(st)

    def _check_motors(self, st: RecvState) -> None:
        """Trip on a motor error flag or link fault, a motor temperature above the limit (or
        below -40 C: a broken sensor), or a joint reported faster than its velocity limit
        (times 1 + OVERSPEED_TOLERANCE)."""
        cfg = self.config
        for i, joint in enumerate(st.joints[:NUM_ARM_JOINTS]):
            for m in joint.motors:
                if m.error or m.link:
                    self.fault.trip(f"joint{i + 1} motor error {m.error:#04x} link {m.link}")
                    return
                if m.temperature > cfg.max_motor_temperature_c:
                    self.fault.trip(f"joint{i + 1} motor temperature {m.temperature} C "
                                    f"(limit {cfg.max_motor_temperature_c:g} C)")
                    return
                if m.temperature < MIN_PLAUSIBLE_TEMPERATURE_C:
                    self.fault.trip(f"joint{i + 1} motor temperature {m.temperature} C: a broken sensor")
                    return
            if abs(joint.W) > self.settings.max_measured_velocity[i] * (1 + OVERSPEED_TOLERANCE):
                self.fault.trip(f"joint{i + 1} reported at {joint.W:.2f} rad/s "
                                f"(limit {self.settings.max_measured_velocity[i]:g} rad/s)")
                return

    def _fresh_state(self) -> RecvState | None:
        """The newest state, if one came since (re)start or reset."""
        with self._lock:
            return self._last if self._heard else None

    def _hold(self) -> SendCmd:
        """The mode's command at the measured position with zero velocity (LOWCMD: the
        configured gains and the gravity feed-forward); PASSIVE when there is nothing to hold
        (a fault, no state since (re)start or reset, or the controller not in the mode)."""
        st, mode = self._fresh_state(), self.config.mode
        if self.fault.tripped or st is None or st.state != mode:
            return SendCmd(ArmFSMState.PASSIVE)
        q = np.clip([j.Pos for j in st.joints[:NUM_ARM_JOINTS]], self.limits.lower, self.limits.upper)
        return self._mode_command(q, np.zeros(NUM_ARM_JOINTS), np.zeros(NUM_ARM_JOINTS))

    def _command(self, dt: float) -> SendCmd:
        """The command for this tick from the current state, target and safety status:
        PASSIVE until a state comes after (re)start or reset; while the controller is not
        in the mode (entering it, or after a reset), the reference, and the target until the
        caller sends one, follow the measured position."""
        st = self._fresh_state()
        if self.fault.tripped or st is None:
            return SendCmd(ArmFSMState.PASSIVE)
        mode = self.config.mode
        if st.state == mode and self._requested >= MODE_SETTLE_TICKS:
            self._in_mode = True  # (a PASSIVE this client sent just before may still act on the controller)
        elif st.state != mode and self._in_mode:  # only the client may take the arm out of the mode: never re-arm
            self.fault.trip(f"controller left {mode.name} for {st.state.name} on its own")
            return SendCmd(ArmFSMState.PASSIVE)
        if st.state not in (mode, ArmFSMState.PASSIVE):
            return SendCmd(ArmFSMState.PASSIVE)  # modes change only through PASSIVE
        q = np.clip([j.Pos for j in st.joints[:NUM_ARM_JOINTS]], self.limits.lower, self.limits.upper)
        with self._lock:
            if not self._initialised or st.state != mode:  # (re-)arming at the measured position
                self._rate.reset(q)
                if not self._has_command:
                    self._target = self._rate.output
                    self.limits.reset(self._target)
                self._pace_to_target()
                self._initialised = True
            if st.state != mode:  # request the mode, holding the measured position
                q_ref = self._rate.output
                dq_ref = np.zeros(NUM_ARM_JOINTS)
            else:
                q_prev = self._rate.output
                q_ref = self._rate.step(self._target, dt, self._pace)
                # feed the reference's own velocity forward unless the caller gave one
                if self._dq_given:
                    dq_ref = self._dq_target
                elif self.config.velocity_feedforward:
                    dq_ref = (q_ref - q_prev) / max(dt, 1e-4)
                else:
                    dq_ref = np.zeros(NUM_ARM_JOINTS)
            tau = self._tau_ff
        return self._mode_command(q_ref, dq_ref, tau)

    def _mode_command(self, q_ref: np.ndarray, dq_ref: np.ndarray, tau_ff: np.ndarray) -> SendCmd:
        """The configured mode's command for reference (q_ref, dq_ref): LOWCMD adds the
        gravity feed-forward to tau_ff and clamps the sum to the effort limits."""
        mode = self.config.mode
        if mode == ArmFSMState.LOWCMD:
            kp, kd, tau = self.kp, self.kd, tau_ff
            if self.config.gravity_feedforward:
                tau = tau + self.model.gravity(q_ref)
            clamped = np.clip(tau, -self.effort, self.effort)
            self.torque_clamped += int(np.any(clamped != tau))
            tau = clamped
        else:  # JOINTCTRL: the controller runs its own gains and gravity compensation
            kp = kd = tau = np.zeros(NUM_ARM_JOINTS)
        joints = tuple(JointCmd(T=float(tau[i]), W=float(dq_ref[i]), Pos=float(q_ref[i]),
                                K_P=float(kp[i]), K_W=float(kd[i])) for i in range(NUM_ARM_JOINTS))
        return SendCmd(mode, joints + (JointCmd(),), track=mode == ArmFSMState.JOINTCTRL)

    def _loop(self) -> None:
        """The loop thread: any error latches a fault and commands PASSIVE before exiting."""
        try:
            self._loop_body()
        except Exception as err:
            self.fault.trip(f"client loop failed: {err!r}")
            with contextlib.suppress(OSError):
                self._send(SendCmd(ArmFSMState.PASSIVE))
            raise

    def _loop_body(self) -> None:
        period = 1.0 / self.config.rate_hz
        # ticks on multiples of the period: on a simulated clock (HIL) the same phase against
        # the world's steps in every run, so that the same episode sends the same commands
        next_tick = self.next_tick = math.ceil(self._clock() / period - 1e-9) * period
        last_tick = next_tick
        while self._running.is_set():
            # until due (to the clock's rounding), or stopped (a paused clock would not move)
            while self._running.is_set() and (left := next_tick - self._clock()) > 1e-9:
                select.select([self._sock], [], [], left)
                self._receive()
            if not self._running.is_set():
                break
            now = self._clock()
            self._tick_times.append(now)
            if self._reset_request.is_set():
                self._reset_request.clear()
                with self._lock:  # reset_fault() dropped the command; states before are stale
                    self.fault.reset()
                    self._initialised = self._in_mode = self._heard = False
                    self._requested = 0
                self._watchdog.reset()
            self._receive_reply()  # the command of this tick acts on the newest state
            if not self.fault.tripped and self._watchdog.expired(now):
                self.fault.trip(f"no Z1 state for {self._watchdog.since_last(now) * 1e3:.0f} ms")
            command = self._command(now - last_tick)
            self._requested = self._requested + 1 if command.state == self.config.mode else 0
            try:
                self._send(command, tick=True)
            except OSError:
                self.packet_errors["socket"] += 1
            last_tick = now
            next_tick += period
            if next_tick < now - period:  # fell behind by more than a period: resync, on the grid
                next_tick = (math.floor(now / period + 1e-9) + 1) * period
            self.next_tick = next_tick


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port on `host` that is free now (bound and released): for a client and an
    emulated controller that must agree on the client's port before either binds."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((host, 0))
        return sock.getsockname()[1]


def _vec6(values: Sequence[float] | np.ndarray, name: str) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise HardwareError(f"Z1 {name}: need {NUM_ARM_JOINTS} numbers, got {values!r}") from None
    if arr.shape != (NUM_ARM_JOINTS,) or not np.all(np.isfinite(arr)):
        raise HardwareError(f"Z1 {name}: need {NUM_ARM_JOINTS} finite values, got {arr}")
    return arr


# ----------------------------------------------------------------------------- official SDK
class OfficialZ1:
    """Thin LOWCMD wrapper of Unitree's `unitree_arm_interface` (pybind11, SDK repo only).

    That module is not on PyPI and ships for Python 3.8 only; constructing this class
    without it raises a HardwareError that says so. Same limits as `Z1Arm`.
    """

    def __init__(self, has_gripper: bool = False, lower: Sequence[float] | None = None,
                 upper: Sequence[float] | None = None):
        try:
            import unitree_arm_interface  # type: ignore[import-not-found]
        except ImportError as err:
            raise HardwareError(
                "unitree_arm_interface is not importable: build it from Unitree's z1_sdk "
                "(pybind11, Python 3.8) and put its lib folder on sys.path, or use Z1Arm, "
                "which speaks the same UDP protocol") from err
        self._sdk = unitree_arm_interface
        lo, hi = default_joint_limits()  # each bound the caller gives replaces the model's
        self.limits = JointLimits(lo if lower is None else lower, hi if upper is None else upper)
        self.arm = unitree_arm_interface.ArmInterface(hasGripper=has_gripper)

    def start(self) -> np.ndarray:
        """Enter LOWCMD (from PASSIVE, as the SDK requires); returns the current q."""
        self.arm.setFsmLowcmd()
        q = np.asarray(self.arm.lowstate.getQ(), dtype=float)
        self.limits.reset(q)
        return q

    def step(self, q: Sequence[float], dq: Sequence[float] | None = None,
             tau: Sequence[float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Send one clamped LOWCMD command and return the measured (q, dq)."""
        q_safe = self.limits.apply(q)
        self.arm.setArmCmd(q_safe, np.zeros(NUM_ARM_JOINTS) if dq is None else _vec6(dq, "dq"),
                           np.zeros(NUM_ARM_JOINTS) if tau is None else _vec6(tau, "tau"))
        self.arm.sendRecv()
        return (np.asarray(self.arm.lowstate.getQ(), dtype=float),
                np.asarray(self.arm.lowstate.getQd(), dtype=float))

    def stop(self) -> None:
        """Back to PASSIVE."""
        self.arm.loopOff()
        self.arm.setFsm(self._sdk.ArmFSMState.PASSIVE)
