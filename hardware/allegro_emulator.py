"""An Allegro Hand v4 firmware emulator on a python-can bus (for tests and hardware-in-loop).

From the spec (specs/allegro_v4.md): it answers RTR info / serial / status / temperature /
position / IMU requests (info verbatim: the spec's real frame by default), streams position
(and temperature/status) frames at the periods the host sets, obeys servo on/off, and
applies the last torque frames' PWM while the servo is on (zero when it is off).
Assumptions where the spec is silent, each the less convenient one for the client:
  host silence does not stop it: the last PWM stays applied with the servo on, however
    long no torque frame comes (`torque_timeout_s` adds a cut-off only when a test asks);
  a power loss (`power_cycle()`) forgets the servo and every periodic stream: the hand
    streams nothing until told again;
  its joints move up to the spec's velocity limit (7 rad/s): a PD that overshoots runs
    them that fast, not slower.
The joints move with a pluggable `JointDynamics` model, stepped every tick with the
effective PWM. The default, `PwmJointDynamics`, is a per-joint double integrator:
    ddq = accel_per_pwm * pwm - damping * dq,  |dq| <= max_speed,  q inside the joint limits.
A hardware-in-the-loop world plugs its plant in instead (systems/hil_world.py).
Run it in its own thread (`start()`), or call `poll(now)` from a thread of yours.
Fault injection: stall the stream, drop or corrupt outgoing frames, report over-temperature,
never report temperatures or the status, never send some fingers' positions, lose power.
"""

from __future__ import annotations

import collections
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import can
import numpy as np

from dexdrake.hands import allegro_units as units
from dexdrake.hardware.allegro_can import (
    NUM_FINGERS,
    NUM_JOINTS,
    STATUS_JOINT_OVER_TEMP,
    STATUS_SERVO_ON,
    FrameError,
    Imu,
    Info,
    Msg,
    Position,
    Request,
    Serial,
    ServoOff,
    ServoOn,
    SetPeriod,
    Status,
    Temperature,
    Torque,
    can_id,
    decode,
    default_joint_limits,
    encode,
)
from dexdrake.hardware.safety import HardwareError

CORRUPTIONS = ("dlc", "device", "unknown_id", "range")


@dataclass(frozen=True)
class EmulatorConfig:
    """Emulated hand. `info` is replied verbatim (default: the spec's real frame
    `200 [7] 02 04 06 04 00 3C 05`); limits default to the `allegro` hand description."""

    info: Info = Info(hw_version=0x0402, fw_version=0x0406, left_hand=False,
                      palm_temperature_c=60, status=5)
    serial: str = "AH4EMU01"
    accel_per_pwm: float = 2.0  # rad/s^2 per PWM count
    damping: float = 5.0  # 1/s
    max_speed: float = 7.0  # rad/s: the joints move no faster (the spec's velocity limit)
    torque_timeout_s: float | None = None  # None: keep the last PWM on host silence (spec)
    physics_dt_s: float = 0.0005
    temperature_c: int = 35
    over_temperature_c: int = 95
    q0: Sequence[float] | None = None
    lower: Sequence[float] | None = None
    upper: Sequence[float] | None = None
    seed: int = 0


class JointDynamics(Protocol):
    """The hand's joints as the emulator sees them (16 values, bus order)."""

    def step(self, pwm: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Apply `pwm` (the effective PWM duty) for `dt` seconds; return (q, dq) after it."""
        ...


class PwmJointDynamics:
    """Per-joint double integrator ddq = accel_per_pwm * pwm - damping * dq inside hard stops,
    |dq| <= max_speed, integrated with sub-steps of at most `physics_dt_s`."""

    def __init__(self, q0: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                 accel_per_pwm: float = 2.0, damping: float = 5.0, physics_dt_s: float = 0.0005,
                 max_speed: float = 7.0):
        self.lower, self.upper = np.asarray(lower, float), np.asarray(upper, float)
        self.q = np.clip(np.asarray(q0, float), self.lower, self.upper)
        self.dq = np.zeros_like(self.q)
        self.accel_per_pwm, self.damping, self.physics_dt_s = accel_per_pwm, damping, physics_dt_s
        self.max_speed = max_speed

    def step(self, pwm: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        steps = max(1, int(np.ceil(dt / self.physics_dt_s)))
        h = dt / steps
        for _ in range(steps):
            self.dq = np.clip(self.dq + h * (self.accel_per_pwm * pwm - self.damping * self.dq),
                              -self.max_speed, self.max_speed)
            self.q = self.q + h * self.dq
            low, high = self.q < self.lower, self.q > self.upper
            self.q = np.clip(self.q, self.lower, self.upper)
            self.dq[(low & (self.dq < 0)) | (high & (self.dq > 0))] = 0.0
        return self.q.copy(), self.dq.copy()


@dataclass
class _Injection:
    stall_until: float = -np.inf
    drop_rate: float = 0.0
    corrupt_rate: float = 0.0
    over_temperature: bool = False
    silent: bool = False  # answer nothing at all (not even RTR)
    mute_temperature: bool = False  # never send temperature frames (periodic or RTR)
    mute_status: bool = False  # never answer a status request (nor stream status)
    mute_fingers: frozenset[int] = frozenset()  # never send these fingers' position frames
    counts: collections.Counter = field(default_factory=collections.Counter)


class AllegroEmulator:
    """The hand side of the bus, run in a thread: `start()` / `stop()` or a context manager
    (or driven by the caller through `poll(now)`). `dynamics` moves the joints (default:
    `PwmJointDynamics` with the config's accel_per_pwm, damping and physics_dt_s)."""

    def __init__(self, bus: can.BusABC, device_id: int = 0, config: EmulatorConfig | None = None,
                 clock: Callable[[], float] = time.monotonic, dynamics: JointDynamics | None = None):
        self.bus, self.device_id = bus, device_id
        self.config = cfg = config or EmulatorConfig()
        self._clock = clock
        if cfg.lower is None or cfg.upper is None:
            self.lower, self.upper = default_joint_limits()
        else:
            self.lower = np.asarray(cfg.lower, float)
            self.upper = np.asarray(cfg.upper, float)
        q0 = np.zeros(NUM_JOINTS) if cfg.q0 is None else np.asarray(cfg.q0, float)
        if q0.shape != (NUM_JOINTS,):
            raise HardwareError(f"emulator q0 needs {NUM_JOINTS} values, got {q0.shape}")
        self._lock = threading.Lock()
        self._q = np.clip(q0, self.lower, self.upper)
        self._dq = np.zeros(NUM_JOINTS)
        self.dynamics: JointDynamics = dynamics or PwmJointDynamics(
            self._q, self.lower, self.upper, cfg.accel_per_pwm, cfg.damping, cfg.physics_dt_s,
            cfg.max_speed)
        self._pwm = np.zeros(NUM_JOINTS)
        self._last_torque = -np.inf
        self._last_tick: float | None = None
        self._due = {"position": 0.0, "temperature": 0.0, "status": 0.0}
        self._torque_fingers: set[int] = set()
        self.position_batches = 0  # complete position batches streamed
        self.answered_batches = 0  # of those, answered by a full set of 4 torque frames
        self.servo_on = False
        self.periods = SetPeriod(0, 0, 0, 0)
        self.log: collections.deque = collections.deque(maxlen=10000)  # decoded frames received
        self.frame_errors: collections.Counter[str] = collections.Counter()
        self.inject = _Injection()
        self._rng = np.random.default_rng(cfg.seed)
        self._running = threading.Event()
        self._thread: threading.Thread | None = None

    # --------------------------------------------------------------- control
    def start(self) -> None:
        self._last_tick = None
        self._running.set()
        self._thread = threading.Thread(target=self._run, name="allegro-emulator", daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        """True while the emulator's thread runs (started and not ended by an error)."""
        return self._thread is not None and self._thread.is_alive()

    def stop(self) -> None:
        self._running.clear()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None

    def __enter__(self) -> AllegroEmulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stall(self, seconds: float) -> None:
        """Stop streaming periodic frames for `seconds` (RTR replies still work)."""
        self.inject.stall_until = self._clock() + seconds

    def power_cycle(self) -> None:
        """A power loss and restore: servo off, PWM zero, every periodic stream off."""
        with self._lock:
            self._pwm[:] = 0.0
        self.servo_on = False
        self.periods = SetPeriod(0, 0, 0, 0)

    def set_over_temperature(self, on: bool = True) -> None:
        """Report joint over-temperature (status bit 1, hot temperature frames)."""
        self.inject.over_temperature = on

    @property
    def q(self) -> np.ndarray:
        with self._lock:
            return self._q.copy()

    @property
    def dq(self) -> np.ndarray:
        with self._lock:
            return self._dq.copy()

    @property
    def pwm(self) -> np.ndarray:
        with self._lock:
            return self._pwm.copy()

    @property
    def torque_pending(self) -> bool:
        """True while the last streamed position batch has no full set of torque replies."""
        return self.answered_batches < self.position_batches

    def status_bits(self) -> int:
        return (STATUS_SERVO_ON if self.servo_on else 0) | (
            STATUS_JOINT_OVER_TEMP if self.inject.over_temperature else 0)

    # --------------------------------------------------------------- bus
    def _send(self, frame: object, periodic: bool = False) -> None:
        inj = self.inject
        if periodic and inj.drop_rate > 0 and self._rng.random() < inj.drop_rate:
            inj.counts["dropped"] += 1
            return
        msg = encode(frame, self.device_id)
        if periodic and inj.corrupt_rate > 0 and self._rng.random() < inj.corrupt_rate:
            msg = self._corrupt(msg)
        self.bus.send(msg)

    def _corrupt(self, msg: can.Message) -> can.Message:
        kind = CORRUPTIONS[self._rng.integers(len(CORRUPTIONS))]
        arb, data = msg.arbitration_id, bytes(msg.data)
        if kind == "range" and not Msg.POSITION <= arb >> 2 < Msg.POSITION + NUM_FINGERS:
            kind = "dlc"  # only a position has an invalid range (any int8 is a temperature)
        self.inject.counts[f"corrupt_{kind}"] += 1
        if kind == "dlc":
            data = data[: int(self._rng.integers(len(data)))]
        elif kind == "device":
            arb = (arb & ~0x3) | ((self.device_id + 1) & 0x3)
        elif kind == "unknown_id":
            arb = can_id(0x7A, self.device_id)
        else:
            data = b"\xff\x7f" * (len(data) // 2)  # 32767 counts: far outside every joint range
        return can.Message(arbitration_id=arb, is_extended_id=False, data=data, dlc=len(data))

    def _temperatures(self, finger: int) -> tuple[int, ...]:
        t = self.config.over_temperature_c if self.inject.over_temperature else self.config.temperature_c
        return (t,) * 4

    def _position(self, finger: int) -> Position:
        with self._lock:
            q = self._q[4 * finger: 4 * finger + 4]
        return Position(finger, tuple(int(c) for c in units.rad_to_counts(q)))

    def _reply(self, req: Request) -> None:
        match req.msg:
            case Msg.INFO:
                self._send(self.config.info)
            case Msg.SERIAL:
                self._send(Serial(self.config.serial))
            case Msg.STATUS:
                if not self.inject.mute_status:
                    self._send(Status(self.status_bits()))
            case Msg.POSITION:
                if req.finger not in self.inject.mute_fingers:
                    self._send(self._position(req.finger))
            case Msg.TEMPERATURE:
                if not self.inject.mute_temperature:
                    self._send(Temperature(req.finger, self._temperatures(req.finger)))
            case Msg.IMU:
                self._send(Imu((16384, 0, 0, 0)))

    def _handle(self, msg: can.Message, now: float) -> None:
        try:
            frame = decode(msg, self.device_id)
        except FrameError as err:
            self.frame_errors[err.kind] += 1
            return
        self.log.append(frame)
        match frame:
            case Request():
                if not self.inject.silent:
                    self._reply(frame)
            case ServoOn():
                self.servo_on = True
            case ServoOff():
                self.servo_on = False
            case SetPeriod():
                self.periods = frame
                self._anchor_periods(now)
            case Torque(finger, pwm):
                with self._lock:
                    self._pwm[4 * finger: 4 * finger + 4] = pwm
                self._last_torque = now
                self._torque_fingers.add(finger)
                if len(self._torque_fingers) == NUM_FINGERS:
                    self._torque_fingers.clear()
                    self.answered_batches = self.position_batches

    # --------------------------------------------------------------- tick
    def _integrate(self, dt: float, now: float) -> None:
        """Zero the PWM when the servo is off (or past the optional torque timeout), then
        step the dynamics."""
        timeout = self.config.torque_timeout_s
        active = self.servo_on and (timeout is None or now - self._last_torque <= timeout)
        with self._lock:
            if not active:
                self._pwm[:] = 0.0
            pwm = self._pwm.copy()
        q, dq = self.dynamics.step(pwm, dt)
        with self._lock:
            self._q = np.asarray(q, float).copy()
            self._dq = np.asarray(dq, float).copy()

    def _anchor_periods(self, now: float) -> None:
        """Stream each periodic frame on the multiples of its period (of the emulator's
        clock) from `now` on, whenever the host set the period: the phase of the stream does
        not depend on when the host's SetPeriod came."""
        p = self.periods
        for name, period_ms in (("position", p.position_ms), ("temperature", p.temperature_ms),
                                ("status", p.status_ms or 0)):
            if period_ms > 0:
                period = period_ms / 1e3
                self._due[name] = math.ceil(now / period - 1e-9) * period

    def _stream(self, now: float) -> None:
        streaming = now >= self.inject.stall_until and not self.inject.silent
        p = self.periods
        for name, period_ms in (("position", p.position_ms), ("temperature", p.temperature_ms),
                                ("status", p.status_ms or 0)):
            if period_ms <= 0:
                self._due[name] = now
                continue
            if now < self._due[name] - 1e-9:  # due: to the clock's rounding
                continue
            self._due[name] = max(self._due[name] + period_ms / 1e3, now - period_ms / 1e3)
            if not streaming:
                continue
            if name == "position":
                for f in range(NUM_FINGERS):
                    if f not in self.inject.mute_fingers:
                        self._send(self._position(f), periodic=True)
                self.position_batches += 1
                self._torque_fingers.clear()
            elif name == "temperature" and not self.inject.mute_temperature:
                for f in range(NUM_FINGERS):
                    self._send(Temperature(f, self._temperatures(f)), periodic=True)
            elif name == "status" and not self.inject.mute_status:
                self._send(Status(self.status_bits()), periodic=True)

    def poll(self, now: float, timeout: float = 0.0) -> None:
        """One emulator tick at time `now` (of the emulator's clock): step the dynamics by the
        time since the last tick (at most 50 ms), stream the frames that are due, then handle
        the frames received within `timeout` seconds (wall) or before the next frame is due."""
        if self._last_tick is None:
            self._last_tick = now
            self._due = dict.fromkeys(self._due, now)
        self._integrate(min(now - self._last_tick, 0.05), now)
        self._last_tick = now
        self._stream(now)
        due = [d for d in self._due.values() if d > now]
        wait = min([timeout] + [d - now for d in due])
        msg = self._receive(max(wait, 0.0))
        while msg is not None:
            self._handle(msg, self._clock())
            msg = self._receive(0.0)

    def _receive(self, timeout: float) -> can.Message | None:
        """The next message, or None; one the transport cannot deliver (python-can raises,
        e.g. a datagram udp_multicast cannot unpack) is counted in `frame_errors`."""
        try:
            return self.bus.recv(timeout)
        except can.CanError as err:
            self.frame_errors[f"bus:{type(err).__name__}"] += 1
            return None

    # --------------------------------------------------------------- thread
    def _run(self) -> None:
        while self._running.is_set():
            self.poll(self._clock(), 0.001)
