"""Allegro Hand v4 over CAN (python-can): frame codec and a host-side PD driver.

Protocol facts are from specs/allegro_v4.md: CAN 2.0A, id = (msg_id << 2) | device_id,
little-endian payloads. Arrays are in CAN bus order: index j0..j3, middle, ring, thumb.
The firmware does not implement position set-points, so `AllegroHand` runs a 333 Hz PD
loop on the host: it waits for the 4 position frames of a cycle, low-pass filters the
position, differentiates it, computes PD torques in PWM counts with the vendor gains,
clamps them to the per-joint PWM limits and sends 4 torque frames. Targets are clamped
`limit_margin_rad` inside the joint limits and rate limited.
Nothing says the firmware stops when the host goes quiet (specs/allegro_v4.md), so every
fault path ends on the host's side: zero torque and servo off (`_trip`). Faults: a finger
without a valid position frame for `watchdog_timeout_s` (each finger watched on its own),
a joint measured faster than its velocity limit (timed by the frames' receive
timestamps where the interface sets them), a hot joint or palm (any reading above
`max_temperature_c`, or below -40 C), a status fault bit, temperatures of a finger or the
status not heard for their timeouts (polled by RTR), a failing loop. `stop()` sends zero
torque before anything else. `reset_fault()` re-runs the whole start sequence (after a
power loss the hand streams nothing until told) and re-arms at the measured position (the
set-point from before it dropped). `probe()` asks info and serial only.
"""

from __future__ import annotations

import collections
import contextlib
import math
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from functools import cache

import can
import numpy as np

from dexdrake.hands import allegro_units as units
from dexdrake.hardware.safety import (
    MIN_PLAUSIBLE_TEMPERATURE_C,
    OVERSPEED_TOLERANCE,
    FaultLatch,
    check_limit_margin,
    measured_velocity_limits,
    SafeStopContext,
    HardwareError,
    JointLimits,
    RateLimiter,
    period_stats,
)

NUM_FINGERS = 4
NUM_JOINTS = units.NUM_JOINTS

# status bits (message 0x10)
STATUS_SERVO_ON = 0x01
STATUS_JOINT_OVER_TEMP = 0x02
STATUS_TEMP_THROTTLING = 0x04
STATUS_JOINT_COMM_TIMEOUT = 0x08
STATUS_PALM_OVER_TEMP = 0x10
STATUS_FAULT_BITS = STATUS_JOINT_OVER_TEMP | STATUS_JOINT_COMM_TIMEOUT | STATUS_PALM_OVER_TEMP
_STATUS_VALID_BITS = 0x1F


class Msg(IntEnum):
    """Allegro v4 message ids (before the `<< 2 | device_id` shift)."""

    STATUS = 0x10
    POSITION = 0x20  # .. 0x23, one per finger
    IMU = 0x30
    TEMPERATURE = 0x38  # .. 0x3B
    SERVO_ON = 0x40
    SERVO_OFF = 0x41
    TORQUE = 0x60  # .. 0x63
    INFO = 0x80
    SET_PERIOD = 0x81
    SERIAL = 0x88
    SET_POSITION = 0xE0  # .. 0xE3, not implemented in firmware


_PER_FINGER = (Msg.POSITION, Msg.TEMPERATURE, Msg.TORQUE, Msg.SET_POSITION)


class FrameError(HardwareError):
    """A CAN frame that is not a valid Allegro message; `kind` names what was wrong."""

    def __init__(self, kind: str, detail: str):
        self.kind = kind
        super().__init__(f"bad Allegro frame ({kind}): {detail}")


# ----------------------------------------------------------------------------- frames
@dataclass(frozen=True)
class ServoOn:
    pass


@dataclass(frozen=True)
class ServoOff:
    pass


@dataclass(frozen=True)
class Torque:
    finger: int
    pwm: tuple[int, int, int, int]


@dataclass(frozen=True)
class SetPosition:
    finger: int
    counts: tuple[int, int, int, int]


@dataclass(frozen=True)
class SetPeriod:
    position_ms: int
    imu_ms: int = 0
    temperature_ms: int = 0
    status_ms: int | None = None  # None: the 6-byte form the drivers send


@dataclass(frozen=True)
class Info:
    hw_version: int
    fw_version: int
    left_hand: bool
    palm_temperature_c: int
    status: int


@dataclass(frozen=True)
class Serial:
    text: str


@dataclass(frozen=True)
class Position:
    finger: int
    counts: tuple[int, int, int, int]


@dataclass(frozen=True)
class Imu:
    values: tuple[int, int, int, int]


@dataclass(frozen=True)
class Temperature:
    finger: int
    celsius: tuple[int, int, int, int]


@dataclass(frozen=True)
class Status:
    bits: int


@dataclass(frozen=True)
class Request:
    """An RTR request for message `msg` (finger for per-finger messages, else None)."""

    msg: Msg
    finger: int | None = None


Frame = (ServoOn | ServoOff | Torque | SetPosition | SetPeriod | Info | Serial | Position | Imu
         | Temperature | Status | Request)

_RTR_REPLY_DLC = {Msg.STATUS: 1, Msg.POSITION: 8, Msg.IMU: 8, Msg.TEMPERATURE: 4, Msg.INFO: 7,
                  Msg.SERIAL: 8}


def can_id(msg_id: int, device_id: int = 0) -> int:
    """The 11-bit arbitration id of `msg_id` for `device_id` (0..3)."""
    _check_device(device_id)
    return (int(msg_id) << 2) | device_id


def _check_device(device_id: int) -> None:
    if not 0 <= device_id <= 3:
        raise HardwareError(f"Allegro device_id must be 0..3, got {device_id}")


def _check_finger(finger: int) -> None:
    if not 0 <= finger < NUM_FINGERS:
        raise HardwareError(f"finger must be 0..3, got {finger}")


def _int16x4(values: Sequence[int], name: str) -> bytes:
    vals = [int(v) for v in values]
    if len(vals) != 4 or any(not -32768 <= v <= 32767 for v in vals):
        raise HardwareError(f"{name}: need 4 int16 values, got {list(values)}")
    return struct.pack("<4h", *vals)


def _message(msg_id: int, device_id: int, data: bytes = b"", rtr: bool = False,
             dlc: int | None = None) -> can.Message:
    return can.Message(arbitration_id=can_id(msg_id, device_id), is_extended_id=False,
                       is_remote_frame=rtr, data=b"" if rtr else data,
                       dlc=len(data) if dlc is None else dlc)


def encode(frame: Frame, device_id: int = 0) -> can.Message:
    """The CAN message for `frame` addressed to/from `device_id`."""
    match frame:
        case ServoOn():
            return _message(Msg.SERVO_ON, device_id)
        case ServoOff():
            return _message(Msg.SERVO_OFF, device_id)
        case Torque(finger, pwm):
            _check_finger(finger)
            return _message(Msg.TORQUE + finger, device_id, _int16x4(pwm, "torque PWM"))
        case SetPosition(finger, counts):
            _check_finger(finger)
            return _message(Msg.SET_POSITION + finger, device_id, _int16x4(counts, "set position"))
        case SetPeriod(p, i, t, s):
            periods = [p, i, t] + ([] if s is None else [s])
            if any(not 0 <= int(v) <= 0xFFFF for v in periods):
                raise HardwareError(f"periods must be uint16 ms, got {periods}")
            return _message(Msg.SET_PERIOD, device_id, struct.pack(f"<{len(periods)}H", *periods))
        case Info(hw, fw, left, temp, status):
            if not (0 <= hw <= 0xFFFF and 0 <= fw <= 0xFFFF and 0 <= temp <= 255
                    and 0 <= status <= 255):
                raise HardwareError(f"info fields out of range: {frame}")
            return _message(Msg.INFO, device_id, struct.pack("<HHBBB", hw, fw, int(left), temp, status))
        case Serial(text):
            raw = text.encode("ascii")
            if len(raw) > 8:
                raise HardwareError(f"serial is at most 8 ASCII characters, got {text!r}")
            return _message(Msg.SERIAL, device_id, raw.ljust(8, b"\0"))
        case Position(finger, counts):
            _check_finger(finger)
            return _message(Msg.POSITION + finger, device_id, _int16x4(counts, "position"))
        case Imu(values):
            return _message(Msg.IMU, device_id, _int16x4(values, "IMU"))
        case Temperature(finger, celsius):
            _check_finger(finger)
            if len(celsius) != 4 or any(not -128 <= int(c) <= 127 for c in celsius):
                raise HardwareError(f"temperatures must be 4 int8, got {celsius}")
            return _message(Msg.TEMPERATURE + finger, device_id, struct.pack("<4b", *celsius))
        case Status(bits):
            if not 0 <= bits <= _STATUS_VALID_BITS:
                raise HardwareError(f"status bits must be 0..0x1F, got {bits:#x}")
            return _message(Msg.STATUS, device_id, bytes([bits]))
        case Request(msg, finger):
            base = Msg(msg)
            if base not in _RTR_REPLY_DLC:
                raise HardwareError(f"message {base.name} cannot be requested by RTR")
            if (base in _PER_FINGER) != (finger is not None):
                raise HardwareError(f"{base.name}: finger must be given exactly for per-finger messages")
            if finger is not None:
                _check_finger(finger)
            return _message(base + (finger or 0), device_id, rtr=True, dlc=_RTR_REPLY_DLC[base])
    raise HardwareError(f"not an Allegro frame: {frame!r}")


def _split_id(arb_id: int) -> tuple[Msg, int | None, int]:
    """(base message, finger or None, device) of an arbitration id; FrameError if unknown."""
    msg_id, device = arb_id >> 2, arb_id & 0x3
    for base in _PER_FINGER:
        if base <= msg_id < base + NUM_FINGERS:
            return base, msg_id - base, device
    try:
        return Msg(msg_id), None, device
    except ValueError:
        raise FrameError("unknown_id", f"id {arb_id:#05x} (message {msg_id:#04x})") from None


_DLC = {Msg.STATUS: (1,), Msg.POSITION: (8,), Msg.IMU: (8,), Msg.TEMPERATURE: (4,),
        Msg.SERVO_ON: (0,), Msg.SERVO_OFF: (0,), Msg.TORQUE: (8,), Msg.INFO: (7,),
        Msg.SET_PERIOD: (6, 8), Msg.SERIAL: (8,), Msg.SET_POSITION: (8,)}


def decode(msg: can.Message, device_id: int = 0) -> Frame:
    """The Allegro frame in `msg`; raises FrameError (with a `kind`) for anything invalid.

    Checks: standard 11-bit id, known message id, device id, DLC, and value ranges
    (status reserved bits, hand type, serial is ASCII). Temperatures are passed on as
    read: an implausible one is the driver's fault to raise, not a frame to drop.
    """
    if msg.is_extended_id or msg.arbitration_id > 0x7FF:
        raise FrameError("id", f"extended or out-of-range id {msg.arbitration_id:#x}")
    if msg.is_error_frame:
        raise FrameError("error_frame", "CAN error frame")
    base, finger, device = _split_id(msg.arbitration_id)
    if device != device_id:
        raise FrameError("device", f"device {device}, expected {device_id}")
    if msg.is_remote_frame:
        if base not in _RTR_REPLY_DLC:
            raise FrameError("rtr", f"{base.name} cannot be requested by RTR")
        return Request(base, finger)
    data = bytes(msg.data)
    if msg.dlc not in _DLC[base] or len(data) != msg.dlc:
        raise FrameError("dlc", f"{base.name} with DLC {msg.dlc} / {len(data)} data bytes, "
                         f"expected {_DLC[base]}")
    match base:
        case Msg.SERVO_ON:
            return ServoOn()
        case Msg.SERVO_OFF:
            return ServoOff()
        case Msg.TORQUE:
            return Torque(finger, struct.unpack("<4h", data))
        case Msg.SET_POSITION:
            return SetPosition(finger, struct.unpack("<4h", data))
        case Msg.SET_PERIOD:
            vals = struct.unpack(f"<{len(data) // 2}H", data)
            return SetPeriod(*vals[:3], status_ms=vals[3] if len(vals) == 4 else None)
        case Msg.INFO:
            hw, fw, hand, temp, status = struct.unpack("<HHBBB", data)
            if hand > 1 or status & ~_STATUS_VALID_BITS:
                raise FrameError("range", f"info hand type {hand} / status {status:#x}")
            return Info(hw, fw, bool(hand), temp, status)
        case Msg.SERIAL:
            text = data.rstrip(b"\0")
            if not all(32 <= b < 127 for b in text):
                raise FrameError("range", f"serial is not printable ASCII: {data!r}")
            return Serial(text.decode("ascii"))
        case Msg.POSITION:
            return Position(finger, struct.unpack("<4h", data))
        case Msg.IMU:
            return Imu(struct.unpack("<4h", data))
        case Msg.TEMPERATURE:  # every int8 is a reading: the driver judges its value
            return Temperature(finger, struct.unpack("<4b", data))
        case Msg.STATUS:
            if data[0] & ~_STATUS_VALID_BITS:
                raise FrameError("range", f"status reserved bits set: {data[0]:#04x}")
            return Status(data[0])
    raise FrameError("unknown_id", f"{base.name}")  # unreachable: every Msg is matched above


# ----------------------------------------------------------------------------- driver
def default_joint_limits() -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) in bus order from the `allegro` hand description's model file."""
    lo, hi, _ = _model_limits()
    return lo.copy(), hi.copy()


@cache
def _model_limits() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lower, upper, velocity) in bus order from the `allegro` description's model file."""
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    from dexdrake.hands.description import load_hand

    hand = load_hand("allegro")
    plant = MultibodyPlant(0.0)
    (robot,) = Parser(plant).AddModels(str(hand.model_path))
    joints = [plant.GetJointByName(name, robot) for name in hand.hardware_joints]
    return (np.array([j.position_lower_limits()[0] for j in joints]),
            np.array([j.position_upper_limits()[0] for j in joints]),
            np.array([j.velocity_upper_limits()[0] for j in joints]))


@dataclass(frozen=True)
class AllegroConfig:
    """Driver settings. Arrays are 16 values in bus order; None means the vendor default
    (gains and PWM limits: dexdrake/hands/allegro_units.py) or the model's joint limits.
    They may be lowered from there, never raised (`check_allegro_config`)."""

    position_period_ms: int = 3
    temperature_period_ms: int = 100
    status_poll_s: float = 0.1  # RTR status + temperature request interval
    temperature_timeout_s: float = 0.5  # no temperature of a finger for this long: fault
    status_timeout_s: float = 0.5  # no status reply for this long: fault
    watchdog_timeout_s: float = 0.05  # no valid position frame of a finger for this long: fault
    reply_timeout_s: float = 0.2  # for the RTR info/serial replies during start()
    filter_cutoff_hz: float = 80.0  # first-order low-pass on position before differentiating
    max_target_rate: float = 3.0  # rad/s on position targets
    limit_margin_rad: float = 0.02  # targets stay this far inside the joint limits
    max_measured_velocity: float | None = None  # rad/s (x 1.5) a joint may reach; None: the model's
    velocity_window_s: float = 0.1  # the measured speed is the mean over at least this long
    # time the measured speed by the frames' receive timestamps (python-can's
    # Message.timestamp, set by the interface when the frame came; frames without one use the
    # driver's clock); off where the driver's clock is a simulated one (HIL)
    receive_timestamps: bool = True
    max_temperature_c: float = 70.0  # joint or palm temperature that stops the hand
    position_margin_rad: float = 0.3  # measured positions beyond limits +- margin are rejected
    kp: Sequence[float] | None = None  # PWM per rad
    kd: Sequence[float] | None = None  # PWM per rad/s
    pwm_limit: Sequence[float] | None = None
    lower: Sequence[float] | None = None
    upper: Sequence[float] | None = None


@dataclass(frozen=True)
class AllegroSettings:
    """A config resolved against the vendor's and the model's limits (bus order)."""

    kp: np.ndarray
    kd: np.ndarray
    pwm_limit: np.ndarray
    lower: np.ndarray  # the joint limits (measured positions are judged against these)
    upper: np.ndarray
    target_lower: np.ndarray  # the limits less the margin: targets are clamped into these
    target_upper: np.ndarray
    max_measured_velocity: np.ndarray  # rad/s, per joint (x 1.5: a faster measured joint trips)


def check_allegro_config(cfg: AllegroConfig) -> AllegroSettings:
    """Resolve `cfg`; HardwareError naming the limit a value exceeds: gains above the vendor
    gains, PWM limits above the vendor's, joint limits outside the model's, a target rate
    or velocity limit above the joints' velocity limit, a margin that leaves no range, or no
    way to hear the temperatures."""
    lo_m, hi_m, vel = _model_limits()

    def capped(values, ceiling: np.ndarray, name: str, what: str) -> np.ndarray:
        arr = ceiling.copy() if values is None else _array(values, name)
        if np.any(arr < 0):
            raise HardwareError(f"Allegro {name} must be >= 0, got {arr.tolist()}")
        if np.any(arr > ceiling):
            i = int(np.flatnonzero(arr > ceiling)[0])
            raise HardwareError(f"Allegro {name}[{i}] = {arr[i]:g} exceeds {what} {ceiling[i]:g}")
        return arr

    kp = capped(cfg.kp, units.KP_VENDOR, "kp", "the vendor gain")
    kd = capped(cfg.kd, units.KD_VENDOR, "kd", "the vendor gain")
    pwm = capped(cfg.pwm_limit, units.PWM_LIMITS, "pwm_limit", "the vendor PWM limit")
    lower = lo_m.copy() if cfg.lower is None else _array(cfg.lower, "lower")
    upper = hi_m.copy() if cfg.upper is None else _array(cfg.upper, "upper")
    if np.any(lower < lo_m - 1e-6) or np.any(upper > hi_m + 1e-6):
        raise HardwareError(f"Allegro joint limits {lower.tolist()} .. {upper.tolist()} reach outside "
                            f"the model's {lo_m.tolist()} .. {hi_m.tolist()}")
    vmax = float(np.min(vel))
    if not (math.isfinite(cfg.max_target_rate) and 0 < cfg.max_target_rate <= vmax):
        raise HardwareError(f"Allegro max_target_rate {cfg.max_target_rate:g} rad/s must be in "
                            f"(0, {vmax:g}], the joints' velocity limit in the model")
    max_measured_velocity = measured_velocity_limits("Allegro", cfg.max_measured_velocity, vel)
    m = cfg.limit_margin_rad
    check_limit_margin("Allegro", m, lower, upper)
    for name in ("watchdog_timeout_s", "temperature_timeout_s", "status_timeout_s", "reply_timeout_s",
                 "velocity_window_s"):
        value = getattr(cfg, name)
        if not (math.isfinite(value) and value > 0):
            raise HardwareError(f"Allegro {name} must be > 0, got {value}")
    if not cfg.status_poll_s > 0:
        raise HardwareError(f"Allegro status_poll_s must be > 0 (status and temperatures are "
                            f"polled with it), got {cfg.status_poll_s}")
    return AllegroSettings(kp, kd, pwm, lower, upper, lower + m, upper - m, max_measured_velocity)


@dataclass(frozen=True)
class AllegroInfo:
    hw_version: int
    fw_version: int
    left_hand: bool
    palm_temperature_c: int
    status: int
    serial: str


@dataclass(frozen=True)
class AllegroState:
    t: float  # host monotonic time of the last complete position cycle
    q: np.ndarray  # filtered joint positions (rad)
    dq: np.ndarray  # joint velocities (rad/s)
    tau_pwm: np.ndarray  # last commanded PWM
    status: int | None  # last status bits received
    fault: str | None  # latched fault reason
    q_target: np.ndarray = field(default_factory=lambda: np.zeros(NUM_JOINTS))
    temperature_c: np.ndarray = field(default_factory=lambda: np.full(NUM_JOINTS, np.nan))


class _Stats:
    def __init__(self, window: int = 20000):
        self.cycle_times: collections.deque[float] = collections.deque(maxlen=window)
        self.frame_errors: collections.Counter[str] = collections.Counter()
        self.duplicates = 0
        self.ignored = 0


class AllegroHand(SafeStopContext):
    """Allegro v4 driver on any python-can bus: start sequence, host PD loop, safety.

    Use as a context manager (`with AllegroHand(bus) as hand:`), which starts the hand and
    guarantees the safe stop on exit, exception, Ctrl-C or SIGTERM.
    """

    def __init__(self, bus: can.BusABC, device_id: int = 0, config: AllegroConfig | None = None,
                 clock: Callable[[], float] = time.monotonic):
        _check_device(device_id)
        self.bus, self.device_id = bus, device_id
        self.config = cfg = config or AllegroConfig()
        self._clock = clock
        n = NUM_JOINTS
        st = check_allegro_config(cfg)
        self.kp, self.kd, self.pwm_limit = st.kp, st.kd, st.pwm_limit
        self.settings = st
        self.limits = JointLimits(st.target_lower, st.target_upper)
        self._rate = RateLimiter(cfg.max_target_rate, initial=self.limits.last_safe)
        self.fault = FaultLatch(clock)
        self._stats = _Stats()
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._target = self.limits.last_safe
        self._has_command = False  # until commanded, the loop holds the measured position
        self._raw = np.zeros(n)
        self._fresh = [False] * NUM_FINGERS
        self._heard = [False] * NUM_FINGERS  # a valid position of each finger since (re)start
        self._t_position = np.full(NUM_FINGERS, clock())  # each finger's last valid position frame
        self._t_speed = np.zeros(NUM_FINGERS)  # start of each finger's speed window, its q
        self._q_speed = np.zeros(n)
        self._n_speed = np.zeros(NUM_FINGERS)  # and the frames since
        self._speed_stamped = [False] * NUM_FINGERS  # each window timed by receive timestamps
        self._t_status = clock()  # the last status reply
        self._q = np.zeros(n)
        self._dq = np.zeros(n)
        self._tau = np.zeros(n)
        self._temps = np.full(n, np.nan)
        self._t_temps = np.full(NUM_FINGERS, -math.inf)  # when each finger's temperatures came
        self._status: int | None = None
        self._t_cycle: float | None = None
        self._initialised = False
        self._faulted_stop_done = False
        self._halted = False  # set by stop(): no torque but zero is sent from then on
        self._thread: threading.Thread | None = None
        self._running = threading.Event()
        self._reset_request = threading.Event()
        self.info: AllegroInfo | None = None

    # --------------------------------------------------------------- bus helpers
    def _send(self, frame: Frame) -> None:
        with self._send_lock:
            self.bus.send(encode(frame, self.device_id))

    def _recv(self, timeout: float) -> Frame | None:
        """The next valid frame for this device, or None on timeout; bad frames are counted."""
        return self._receive(timeout)[0]

    def _receive(self, timeout: float) -> tuple[Frame | None, float | None]:
        """`_recv`, with the frame's receive timestamp (s, the interface's clock; None when
        the interface sets none or `receive_timestamps` is off). A message the transport
        cannot deliver (python-can raises, e.g. a datagram udp_multicast cannot unpack) is
        counted as a bad frame."""
        try:
            msg = self.bus.recv(timeout)
        except can.CanError as err:
            self._stats.frame_errors[f"bus:{type(err).__name__}"] += 1
            return None, None
        if msg is None:
            return None, None
        try:
            frame = decode(msg, self.device_id)
        except FrameError as err:
            self._stats.frame_errors[err.kind] += 1
            return None, None
        stamped = self.config.receive_timestamps and msg.timestamp > 0
        return frame, (msg.timestamp if stamped else None)

    def _await(self, kind: type, timeout: float) -> Frame:
        """The next frame of `kind`; meanwhile status and temperature frames are still
        checked for faults and positions for range (other frames are dropped)."""
        deadline = self._clock() + timeout
        while (left := deadline - self._clock()) > 0:
            frame = self._recv(left)
            if isinstance(frame, kind):
                return frame
            if isinstance(frame, (Status, Temperature)):
                self._handle(frame)
            elif isinstance(frame, Position):
                self._position_in_range(frame.finger, units.counts_to_rad(np.asarray(frame.counts, float)))
        raise HardwareError(f"Allegro: no {kind.__name__} reply within {timeout} s "
                            f"(device {self.device_id}; is the hand powered and the bus up?)")

    # --------------------------------------------------------------- session
    def start(self) -> AllegroInfo:
        """Vendor start sequence (flush, servo off, info, serial, periodic read, servo on)."""
        if self._thread is not None:
            raise HardwareError("Allegro: already started")
        if self.fault.tripped:
            raise HardwareError(f"Allegro: fault latched ({self.fault.reason}); call reset_fault() first")
        while self.bus.recv(0.0) is not None:  # flush
            pass
        self._halted = False
        with self._lock:
            self._has_command = False
        self._start_sequence()
        self._running.set()
        self._thread = threading.Thread(target=self._loop, name="allegro-pd", daemon=True)
        self._thread.start()
        return self.info

    def _start_sequence(self) -> None:
        """Servo off, info, serial, periodic read, servo on; the loop's first cycle then starts
        from the measured position (HardwareError when the hand does not answer, is too hot or
        its info reports a fault)."""
        cfg = self.config
        with self._lock:
            self._initialised = False
            self._fresh = [False] * NUM_FINGERS
            self._heard = [False] * NUM_FINGERS
        self._send(ServoOff())
        self._send(Request(Msg.INFO))
        info = self._await(Info, cfg.reply_timeout_s)
        self._send(Request(Msg.SERIAL))
        serial = self._await(Serial, cfg.reply_timeout_s)
        self.info = AllegroInfo(info.hw_version, info.fw_version, info.left_hand,
                                info.palm_temperature_c, info.status, serial.text)
        if info.palm_temperature_c > cfg.max_temperature_c:
            raise HardwareError(f"Allegro: palm at {info.palm_temperature_c} C at start "
                                f"(limit {cfg.max_temperature_c} C)")
        if info.status & STATUS_FAULT_BITS:  # never switch on a hand that already reports a fault
            raise HardwareError(f"Allegro: hand status {info.status:#04x} reports a fault at start")
        self._send(SetPeriod(cfg.position_period_ms, 0, cfg.temperature_period_ms))
        if self.fault.tripped:  # the hand reported a fault during the sequence: stay off
            raise HardwareError(f"Allegro: fault during start: {self.fault.reason}")
        self._send(ServoOn())
        now = self._clock()
        self._t_position[:] = now
        self._t_temps[:] = now
        self._t_status = now

    def stop(self) -> None:
        """Safe stop: zero torque first (from then on the loop sends no other torque), then
        the loop thread ends, the stream stops (period 0) and the servo goes off (the
        vendor's stop sequence). Run it to the end: `with hand:` shields it from signals."""
        self._running.clear()
        with contextlib.suppress(can.CanError):
            with self._send_lock:
                self._halted = True
            self._send_zero_torque()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        with contextlib.suppress(can.CanError):
            self._send(SetPeriod(0, 0, 0))
            self._send(ServoOff())

    def probe(self, timeout_s: float = 0.3) -> AllegroInfo:
        """Ask the hand who it is and nothing else: RTR info and serial requests, queries the
        firmware answers without acting on them; every other frame heard is ignored (no servo,
        torque, period or safe-stop frame is ever sent, so a hand another program drives is
        left alone). HardwareError when a reply does not come within `timeout_s`."""
        if self._thread is not None:
            raise HardwareError("Allegro: probe() is for a hand that is not started")
        replies: dict[type, Frame] = {}
        for msg, kind in ((Msg.INFO, Info), (Msg.SERIAL, Serial)):
            self._send(Request(msg))
            deadline = self._clock() + timeout_s
            while kind not in replies and (left := deadline - self._clock()) > 0:
                frame = self._recv(left)
                if isinstance(frame, kind):
                    replies[kind] = frame
            if kind not in replies:
                raise HardwareError(f"Allegro: no {kind.__name__} reply within {timeout_s} s (device "
                                    f"{self.device_id}; powered? bitrate 1 Mbit/s?)")
        info, serial = replies[Info], replies[Serial]
        return AllegroInfo(info.hw_version, info.fw_version, info.left_hand, info.palm_temperature_c,
                           info.status, serial.text)

    @property
    def running(self) -> bool:
        """True while the PD loop thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    # --------------------------------------------------------------- commands and state
    def command_positions(self, q_rad: Sequence[float] | np.ndarray) -> np.ndarray:
        """Set the 16 joint targets (bus order, rad); returns the clamped target used.

        Non-finite commands are rejected (the last safe target is held, counted in stats).
        """
        with self._lock:
            self._target = self.limits.apply(q_rad)
            self._has_command = True
            return self._target.copy()

    def reset_fault(self) -> None:
        """Clear a latched fault: re-run the start sequence and hold the position measured
        after it (every finger heard anew) until the next `command_positions`; the set-point
        commanded before this call is dropped now.

        While running, the loop thread does the reset (a hand that does not answer trips
        again); when stopped, only the latch clears (`start()` runs the sequence).
        """
        with self._lock:
            self._has_command = False
        if self.running:
            self._reset_request.set()
        else:
            self.fault.reset()
            self._faulted_stop_done = False

    def state(self) -> AllegroState:
        with self._lock:
            return AllegroState(
                t=math.nan if self._t_cycle is None else self._t_cycle, q=self._q.copy(),
                dq=self._dq.copy(), tau_pwm=self._tau.copy(), status=self._status,
                fault=self.fault.reason, q_target=self._rate.output,
                temperature_c=self._temps.copy())

    def stats(self) -> dict[str, object]:
        """Loop rate/jitter (period mean/p50/p99/max in ms) and error counters."""
        out: dict[str, object] = period_stats(list(self._stats.cycle_times))
        out.update(frame_errors=dict(self._stats.frame_errors), duplicates=self._stats.duplicates,
                   ignored_frames=self._stats.ignored,
                   rejected_commands=self.limits.non_finite, clamped_commands=self.limits.clipped,
                   fault=self.fault.reason)
        return out

    def loop_times(self, since: float = -math.inf) -> np.ndarray:
        """The PD cycles' times (the clock's s) after `since`, of the last 20000 kept."""
        times = np.fromiter(list(self._stats.cycle_times), float)
        return times[times > since]

    # --------------------------------------------------------------- loop
    def _send_zero_torque(self) -> None:
        for f in range(NUM_FINGERS):
            self._send(Torque(f, (0, 0, 0, 0)))

    def _trip(self, reason: str) -> None:
        """Latch a fault and put the hand in safe stop (zero torque, servo off) once."""
        self.fault.trip(reason)
        if not self._faulted_stop_done:
            self._faulted_stop_done = True
            with contextlib.suppress(can.CanError):
                self._send_zero_torque()
                self._send(ServoOff())
            with self._lock:
                self._tau = np.zeros(NUM_JOINTS)

    def _loop(self) -> None:
        """The loop thread: bus errors are counted; any other error ends in safe stop."""
        try:
            self._loop_body()
        except Exception as err:  # a dead loop must never leave torques applied
            self._trip(f"driver loop failed: {err!r}")
            raise

    def _loop_body(self) -> None:
        next_poll = self._clock()
        while self._running.is_set():
            now = self._clock()
            try:
                if now >= next_poll:
                    next_poll = now + self.config.status_poll_s
                    self._send(Request(Msg.STATUS))
                    for f in range(NUM_FINGERS):
                        self._send(Request(Msg.TEMPERATURE, f))
                self._iterate(now)
            except can.CanError as err:
                self._stats.frame_errors[f"bus:{type(err).__name__}"] += 1

    def _iterate(self, now: float) -> None:
        """One pass: pending reset, staleness of every stream, then at most one received frame."""
        if self._reset_request.is_set():
            self._reset_request.clear()
            self._do_reset()
        if not self.fault.tripped:
            self._check_staleness(now)
        frame, stamp = self._receive(0.005)
        if frame is not None:
            self._handle(frame, stamp)

    def _check_staleness(self, now: float) -> None:
        """Trip on the first stream older than its limit: each finger's valid position
        frames (the watchdog), each finger's temperatures, the status replies."""
        cfg = self.config
        silent = now - self._t_position
        if np.max(silent) > cfg.watchdog_timeout_s:
            f = int(np.argmax(silent))
            who = "" if np.all(silent > cfg.watchdog_timeout_s) else f"finger {f} "
            self._trip(f"{who}position stream silent for {silent[f] * 1e3:.0f} ms")
            return
        stale = now - self._t_temps
        if np.max(stale) > cfg.temperature_timeout_s:
            f = int(np.argmax(stale))
            self._trip(f"finger {f} temperature not heard for {stale[f] * 1e3:.0f} ms")
            return
        if now - self._t_status > cfg.status_timeout_s:
            self._trip(f"status not heard for {(now - self._t_status) * 1e3:.0f} ms")

    def _do_reset(self) -> None:
        self.fault.reset()
        self._faulted_stop_done = False
        try:
            self._start_sequence()
        except HardwareError as err:
            self._trip(f"reset failed: {err}")

    def _handle(self, frame: Frame, stamp: float | None = None) -> None:
        """Act on one frame; `stamp`: its receive timestamp (`_receive`), if any."""
        match frame:
            case Position(finger, counts):
                self._on_position(finger, counts, stamp)
            case Temperature(finger, celsius):
                with self._lock:
                    self._temps[4 * finger: 4 * finger + 4] = celsius
                self._t_temps[finger] = self._clock()
                if max(celsius) > self.config.max_temperature_c:
                    self._trip(f"finger {finger} joint temperature {max(celsius)} C")
                elif min(celsius) < MIN_PLAUSIBLE_TEMPERATURE_C:
                    self._trip(f"finger {finger} joint temperature {min(celsius)} C: a broken sensor")
            case Status(bits):
                with self._lock:
                    self._status = bits
                self._t_status = self._clock()
                if bits & STATUS_FAULT_BITS:
                    self._trip(f"hand status {bits:#04x} reports a fault")
            case _:
                self._stats.ignored += 1

    def _position_in_range(self, finger: int, q: np.ndarray) -> bool:
        """False (and counted) for positions beyond the joint limits +- the margin."""
        sl = slice(4 * finger, 4 * finger + 4)
        m = self.config.position_margin_rad
        if np.any(q < self.settings.lower[sl] - m) or np.any(q > self.settings.upper[sl] + m):
            self._stats.frame_errors["range"] += 1
            return False
        return True

    def _on_position(self, finger: int, counts: tuple[int, ...], stamp: float | None = None) -> None:
        """A finger's position frame: range-checked, then its speed checked (`_check_speed`,
        at its receive timestamp `stamp` when it has one); the batch's PD cycle runs once all
        4 fingers are in (or a finger repeats), never before every finger was heard since the
        start."""
        q = units.counts_to_rad(np.asarray(counts, dtype=float))
        sl = slice(4 * finger, 4 * finger + 4)
        if not self._position_in_range(finger, q):
            return
        now = self._clock()
        self._check_speed(finger, q, now, stamp)
        self._t_position[finger] = now
        if self._fresh[finger]:  # a new batch began before the last one completed (drop)
            self._stats.duplicates += 1
            self._fresh = [False] * NUM_FINGERS
            if all(self._heard):
                self._cycle(self._clock())
        self._raw[sl] = q
        self._fresh[finger] = self._heard[finger] = True
        if all(self._fresh):
            self._fresh = [False] * NUM_FINGERS
            self._cycle(self._clock())

    def _check_speed(self, finger: int, q: np.ndarray, now: float, stamp: float | None = None) -> None:
        """Trip when a joint's mean speed over a window of at least `velocity_window_s`
        exceeds max_measured_velocity * (1 + OVERSPEED_TOLERANCE): the speed is |q - q0| / T,
        T = max(t - t0, n * period), n frames since q0 at t0. t is the frame's receive
        timestamp `stamp` (when the frame came, however late the loop reads it), else the
        host's time `now`; a window is timed on one of the two clocks (a change starts a new
        one). The frames' count bounds frames read late in a burst (their host times crowd
        together), the clock frames the hand dropped."""
        sl = slice(4 * finger, 4 * finger + 4)
        t, stamped = (now, False) if stamp is None else (stamp, True)
        same_clock = self._speed_stamped[finger] == stamped
        self._n_speed[finger] += 1
        span = max(t - self._t_speed[finger],
                   self._n_speed[finger] * self.config.position_period_ms / 1e3)
        if self._heard[finger] and same_clock and span < self.config.velocity_window_s:
            return
        if self._heard[finger] and same_clock and not self.fault.tripped:
            speed = np.abs(q - self._q_speed[sl]) / span
            over = speed > self.settings.max_measured_velocity[sl] * (1 + OVERSPEED_TOLERANCE)
            if np.any(over):
                j = int(np.argmax(over))
                self._trip(f"joint {4 * finger + j} measured at {speed[j]:.1f} rad/s "
                           f"(limit {self.settings.max_measured_velocity[4 * finger + j]:g} rad/s)")
        self._t_speed[finger], self._q_speed[sl], self._n_speed[finger] = t, q, 0
        self._speed_stamped[finger] = stamped

    def _cycle(self, now: float) -> None:
        """One PD step after a complete set of 4 position frames. The first cycle after
        start or reset holds the measured position and answers with zero torque."""
        self._stats.cycle_times.append(now)
        with self._lock:
            if not self._initialised:
                self._q = self._raw.copy()
                self._dq = np.zeros(NUM_JOINTS)
                self._rate.reset(np.clip(self._q, self.limits.lower, self.limits.upper))
                if not self._has_command:
                    self._target = self._rate.output
                    self.limits.reset(self._target)
                self._t_cycle = now
                self._initialised = True
                if self.fault.tripped:
                    return
                pwm = np.zeros(NUM_JOINTS)
            else:
                dt = max(now - self._t_cycle, 1e-4)
                alpha = dt / (dt + 1.0 / (2 * math.pi * self.config.filter_cutoff_hz))
                q_new = self._q + alpha * (self._raw - self._q)
                self._dq = (q_new - self._q) / dt
                self._q, self._t_cycle = q_new, now
                if self.fault.tripped:
                    return
                q_ref = self._rate.step(self._target, dt)
                pwm = self.kp * (q_ref - self._q) - self.kd * self._dq
                pwm = np.clip(np.rint(pwm), -self.pwm_limit, self.pwm_limit)
            self._tau = pwm
        with self._send_lock:  # after stop() has sent zero torque, nothing else goes out
            if not self._halted:
                for f in range(NUM_FINGERS):
                    self.bus.send(encode(Torque(f, tuple(int(v) for v in pwm[4 * f: 4 * f + 4])),
                                         self.device_id))


def _array(values: Sequence[float], name: str) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise HardwareError(f"Allegro {name}: need {NUM_JOINTS} numbers (bus order), got {values!r}") from None
    if arr.shape != (NUM_JOINTS,) or not np.all(np.isfinite(arr)):
        raise HardwareError(f"Allegro {name}: need {NUM_JOINTS} finite values (bus order), got {arr}")
    return arr
