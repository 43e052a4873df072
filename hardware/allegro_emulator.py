"""An Allegro Hand v4 firmware emulator on a python-can bus (for tests and hardware-in-loop).

It answers RTR info / serial / status / temperature / position / IMU requests, streams
position (and temperature/status) frames at the periods the host sets, obeys servo on/off
and integrates simple per-joint dynamics from the torque frames:
    ddq = accel_per_pwm * pwm - damping * dq,  q kept inside the joint limits,
with zero torque when the servo is off or no torque frame arrived for `torque_timeout_s`.
Fault injection: stall the stream, drop or corrupt outgoing frames, report over-temperature.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

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
    torque_timeout_s: float = 0.05
    physics_dt_s: float = 0.0005
    temperature_c: int = 35
    over_temperature_c: int = 95
    q0: Sequence[float] | None = None
    lower: Sequence[float] | None = None
    upper: Sequence[float] | None = None
    seed: int = 0


@dataclass
class _Injection:
    stall_until: float = -np.inf
    drop_rate: float = 0.0
    corrupt_rate: float = 0.0
    over_temperature: bool = False
    silent: bool = False  # answer nothing at all (not even RTR)
    counts: collections.Counter = field(default_factory=collections.Counter)


class AllegroEmulator:
    """The hand side of the bus, run in a thread: `start()` / `stop()` or a context manager."""

    def __init__(self, bus: can.BusABC, device_id: int = 0, config: EmulatorConfig | None = None,
                 clock: Callable[[], float] = time.monotonic):
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
        self._pwm = np.zeros(NUM_JOINTS)
        self._last_torque = -np.inf
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
        self._running.set()
        self._thread = threading.Thread(target=self._run, name="allegro-emulator", daemon=True)
        self._thread.start()

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

    def set_over_temperature(self, on: bool = True) -> None:
        """Report joint over-temperature (status bit 1, hot temperature frames)."""
        self.inject.over_temperature = on

    @property
    def q(self) -> np.ndarray:
        with self._lock:
            return self._q.copy()

    @property
    def pwm(self) -> np.ndarray:
        with self._lock:
            return self._pwm.copy()

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
        self.inject.counts[f"corrupt_{kind}"] += 1
        arb, data = msg.arbitration_id, bytes(msg.data)
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
                self._send(Status(self.status_bits()))
            case Msg.POSITION:
                self._send(self._position(req.finger))
            case Msg.TEMPERATURE:
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
            case Torque(finger, pwm):
                with self._lock:
                    self._pwm[4 * finger: 4 * finger + 4] = pwm
                self._last_torque = now

    # --------------------------------------------------------------- thread
    def _integrate(self, dt: float, now: float) -> None:
        cfg = self.config
        active = self.servo_on and now - self._last_torque <= cfg.torque_timeout_s
        with self._lock:
            if not active:
                self._pwm[:] = 0.0
            steps = max(1, int(np.ceil(dt / cfg.physics_dt_s)))
            h = dt / steps
            for _ in range(steps):
                self._dq += h * (cfg.accel_per_pwm * self._pwm - cfg.damping * self._dq)
                self._q += h * self._dq
                low, high = self._q < self.lower, self._q > self.upper
                self._q = np.clip(self._q, self.lower, self.upper)
                self._dq[(low & (self._dq < 0)) | (high & (self._dq > 0))] = 0.0

    def _run(self) -> None:
        last = self._clock()
        due = {"position": last, "temperature": last, "status": last}
        while self._running.is_set():
            now = self._clock()
            self._integrate(min(now - last, 0.05), now)
            last = now
            streaming = now >= self.inject.stall_until and not self.inject.silent
            p = self.periods
            for name, period_ms in (("position", p.position_ms),
                                    ("temperature", p.temperature_ms),
                                    ("status", p.status_ms or 0)):
                if period_ms <= 0:
                    due[name] = now
                    continue
                if now < due[name]:
                    continue
                due[name] = max(due[name] + period_ms / 1e3, now - period_ms / 1e3)
                if not streaming:
                    continue
                if name == "position":
                    for f in range(NUM_FINGERS):
                        self._send(self._position(f), periodic=True)
                elif name == "temperature":
                    for f in range(NUM_FINGERS):
                        self._send(Temperature(f, self._temperatures(f)), periodic=True)
                else:
                    self._send(Status(self.status_bits()), periodic=True)
            wait = min([d for d in due.values() if d > now] + [now + 0.001]) - now
            msg = self.bus.recv(max(wait, 0.0))
            while msg is not None:
                self._handle(msg, self._clock())
                msg = self.bus.recv(0.0)
