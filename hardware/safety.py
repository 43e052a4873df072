"""Safety building blocks shared by every hardware driver.

Joint-limit clamps with non-finite rejection (the one bad-command rule of
dexdrake/command_guard.py), a rate limiter on commanded targets, a
watchdog fed by received frames, a latch that keeps the first fault, and a context manager
that routes Ctrl-C, SIGTERM and exceptions to the driver's safe stop, plus the loop-period
statistics every driver reports. Pure Python + numpy;
every time-dependent piece takes an injectable monotonic clock so tests can drive time.
"""

from __future__ import annotations

import contextlib
import math
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from dexdrake.command_guard import CommandGuard
from dexdrake.errors import DexdrakeError

Clock = Callable[[], float]

# a joint measured faster than its velocity limit times (1 + this) is an overspeed fault: the
# margin covers tracking that overshoots targets moving at the limit itself, and the noise of
# a speed computed from the times of frames with some frames lost
OVERSPEED_TOLERANCE = 0.5
MIN_PLAUSIBLE_TEMPERATURE_C = -40  # a colder temperature reading is a broken sensor: a fault


class HardwareError(DexdrakeError):
    """A hardware driver or device problem a user can act on."""


def _vector(values: Sequence[float] | np.ndarray | float, n: int, name: str) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=float)
    except (TypeError, ValueError):  # strings, None, ragged lists: the driver's own error
        raise HardwareError(f"{name}: expected {n} numbers, got {values!r}") from None
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise HardwareError(f"{name}: expected {n} values, got shape {arr.shape}")
    return arr


def measured_velocity_limits(device: str, value: float | None, model_velocity: np.ndarray,
                             where: str = "the model") -> np.ndarray:
    """Per-joint speeds (rad/s) a measured joint may reach: the model's velocity limits, or one
    value for every joint, which must lie in (0, the slowest joint's limit]."""
    vmax = float(np.min(model_velocity))
    if value is None:
        return np.asarray(model_velocity, dtype=float).copy()
    if not (math.isfinite(value) and 0 < value <= vmax + 1e-9):
        raise HardwareError(f"{device} max_measured_velocity {value:g} rad/s must be in (0, {vmax:g}], "
                            f"the joints' velocity limit in {where}")
    return np.full(len(model_velocity), float(value))


def check_limit_margin(device: str, margin: float, lower: np.ndarray, upper: np.ndarray) -> None:
    """A margin (rad) kept inside the joint limits must be >= 0 and leave every joint a range."""
    if not (math.isfinite(margin) and 0 <= margin and np.all(upper - lower > 2 * margin)):
        raise HardwareError(f"{device} limit_margin_rad {margin:g} must be >= 0 and leave every joint a "
                            f"range (narrowest {float(np.min(upper - lower)):g} rad)")


class JointLimits(CommandGuard):
    """The one bad-command rule (dexdrake/command_guard.py) on a driver's position commands,
    with the held command its own: `apply(q)` returns the command to send, `q` clipped into
    [lower, upper], or, when `q` has a non-finite element, the last safe command
    (`last_rejected` is then set until the next accepted command); `non_finite` and
    `clipped` count them. A command of the wrong size is the caller's error (HardwareError).
    """

    def __init__(self, lower: Sequence[float] | np.ndarray, upper: Sequence[float] | np.ndarray,
                 initial: Sequence[float] | np.ndarray | None = None):
        lo, hi = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
        if lo.ndim != 1 or lo.shape != hi.shape:
            raise HardwareError(f"limits: lower {lo.shape} and upper {hi.shape} must be equal 1-D")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise HardwareError("limits: lower and upper must be finite")
        if np.any(lo > hi):
            raise HardwareError(f"limits: lower > upper at joints {np.flatnonzero(lo > hi).tolist()}")
        super().__init__(lo, hi)
        start = np.clip(0.0, lo, hi) if initial is None else _vector(initial, lo.size, "initial")
        self._last_safe = np.clip(start, lo, hi) if np.all(np.isfinite(start)) else np.clip(0.0, lo, hi)
        self.last_rejected = False

    @property
    def size(self) -> int:
        return self.lower.size

    @property
    def last_safe(self) -> np.ndarray:
        return self._last_safe.copy()

    def reset(self, q: Sequence[float] | np.ndarray) -> None:
        """Make (the clamped, finite) `q` the command held on the next rejection."""
        q = _vector(q, self.size, "reset")
        if not np.all(np.isfinite(q)):
            raise HardwareError("limits: reset value must be finite")
        self._last_safe = np.clip(q, self.lower, self.upper)

    def apply(self, q: Sequence[float] | np.ndarray) -> np.ndarray:
        """The safe version of command `q` (clamped, or the last safe one if non-finite)."""
        held = self.non_finite
        self._last_safe = self(_vector(q, self.size, "command"), self._last_safe)
        self.last_rejected = self.non_finite > held
        return self._last_safe.copy()


class RateLimiter:
    """Moves an output toward a target by at most `max_rate` (units/s) per step."""

    def __init__(self, max_rate: Sequence[float] | np.ndarray | float, initial: Sequence[float] | np.ndarray):
        init = np.asarray(initial, dtype=float)
        if init.ndim != 1 or not np.all(np.isfinite(init)):
            raise HardwareError("rate limiter: initial must be a finite 1-D vector")
        self.max_rate = _vector(max_rate, init.size, "max_rate")
        if np.any(~np.isfinite(self.max_rate)) or np.any(self.max_rate <= 0):
            raise HardwareError("rate limiter: max_rate must be finite and > 0")
        self._out = init.copy()

    @property
    def output(self) -> np.ndarray:
        return self._out.copy()

    def reset(self, q: Sequence[float] | np.ndarray) -> None:
        """Jump the output to `q` (e.g. the measured position when the loop starts)."""
        q = _vector(q, self._out.size, "reset")
        if not np.all(np.isfinite(q)):
            raise HardwareError("rate limiter: reset value must be finite")
        self._out = q.copy()

    def step(self, target: Sequence[float] | np.ndarray, dt: float,
             rate: np.ndarray | None = None) -> np.ndarray:
        """Advance the output toward the finite `target` over `dt` seconds, at `rate` (per
        element, at most `max_rate`; default `max_rate`), and return it."""
        target = _vector(target, self._out.size, "target")
        if not np.all(np.isfinite(target)):
            raise HardwareError("rate limiter: target must be finite (clamp it first)")
        if not (np.isfinite(dt) and dt >= 0):
            raise HardwareError(f"rate limiter: dt must be finite and >= 0, got {dt}")
        limit = self.max_rate if rate is None else np.minimum(rate, self.max_rate)
        self._out = rate_limited(self._out, target, limit, dt)
        return self._out.copy()


def rate_limited(output: np.ndarray, target: np.ndarray, max_rate: np.ndarray | float, dt: float) -> np.ndarray:
    """`output` moved toward `target` by at most `max_rate * dt` per element: one step of
    the drivers' target rate limit (RateLimiter), also modelled in simulation
    (systems/target_limits.py)."""
    step = np.asarray(max_rate, dtype=float) * dt
    return output + np.minimum(np.maximum(target - output, -step), step)  # np.clip's value, a third of its cost


def paced_rate(reference: np.ndarray, target: np.ndarray, max_rate: np.ndarray | float,
               period: float) -> np.ndarray:
    """The rate (per element) that takes `reference` to a new `target` in `period` seconds,
    at most `max_rate`: a set-point that comes every `period` followed evenly over it rather
    than at the limit and then held (a velocity that steps from 0 to the limit and back
    within a period, which kicks a PD given that velocity). Used by the Z1 client and its
    model in simulation (systems/target_limits.py)."""
    return np.minimum(np.abs(np.asarray(target, float) - reference) / period, max_rate)


class Watchdog:
    """Expires when `feed()` has not been called for more than `timeout` seconds.

    The timer starts at construction (or `reset()`), so a stream that never starts expires too.
    """

    def __init__(self, timeout: float, clock: Clock = time.monotonic):
        if not (np.isfinite(timeout) and timeout > 0):
            raise HardwareError(f"watchdog: timeout must be > 0 s, got {timeout}")
        self.timeout = float(timeout)
        self._clock = clock
        self._last = clock()
        self.feeds = 0

    def reset(self, now: float | None = None) -> None:
        """Restart the timer without counting a feed."""
        self._last = self._clock() if now is None else now

    def feed(self, now: float | None = None) -> None:
        """Record that a packet/frame arrived."""
        self._last = self._clock() if now is None else now
        self.feeds += 1

    def since_last(self, now: float | None = None) -> float:
        return (self._clock() if now is None else now) - self._last

    def expired(self, now: float | None = None) -> bool:
        return self.since_last(now) > self.timeout


@dataclass(frozen=True)
class Fault:
    reason: str
    time: float


class FaultLatch:
    """Keeps the first fault; once tripped it stays tripped until `reset()`. Thread safe."""

    def __init__(self, clock: Clock = time.monotonic):
        self._clock = clock
        self._lock = threading.Lock()
        self._fault: Fault | None = None
        self.trips = 0

    def trip(self, reason: str) -> bool:
        """Latch `reason` if nothing is latched yet; True when this call latched it."""
        with self._lock:
            self.trips += 1
            if self._fault is not None:
                return False
            self._fault = Fault(reason, self._clock())
            return True

    @property
    def tripped(self) -> bool:
        return self._fault is not None

    @property
    def fault(self) -> Fault | None:
        return self._fault

    @property
    def reason(self) -> str | None:
        return None if self._fault is None else self._fault.reason

    def reset(self) -> None:
        """Clear the latch (an explicit operator action)."""
        with self._lock:
            self._fault = None


@contextmanager
def safe_stop_on_exit(stop: Callable[[], None],
                      signals: Sequence[int] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[None]:
    """Run the body; on any exit (normal, exception, Ctrl-C, SIGTERM) call `stop()` once,
    to its end, whatever signals come meanwhile.

    In the main thread SIGINT/SIGTERM handlers are installed for the duration. The first
    signal raises KeyboardInterrupt inside the body; every later one is only counted, so
    no signal (any number, any spacing) can abort the stop. A signal that came only while
    the stop ran raises KeyboardInterrupt after it. The previous handlers are restored
    afterwards; exceptions are re-raised after the stop.
    """
    armed = [True]  # the handler raises at most once, and never once the stop has begun
    received: list[int] = []

    def _handler(signum: int, _frame: object) -> None:
        received.append(signum)
        if armed[0]:
            armed[0] = False
            raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")

    previous: dict[int, object] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in signals:
            previous[sig] = signal.signal(sig, _handler)
    interrupted = False
    try:
        yield
    finally:
        try:
            try:
                interrupted = not armed[0]  # a signal already raised in the body
                armed[0] = False
            finally:  # runs even if the one KeyboardInterrupt lands on the lines above
                stop()
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
    if received and not interrupted:
        raise KeyboardInterrupt(f"signal {signal.Signals(received[0]).name} during the safe stop")


class SafeStopContext:
    """Mixin for drivers with `start()` and `stop()`: `with driver:` starts it and, on any
    exit (normal, exception, Ctrl-C, SIGTERM), runs its safe stop (`safe_stop_on_exit`)."""

    _exit_stack: contextlib.ExitStack | None = None

    def __enter__(self):
        stack = contextlib.ExitStack()
        stack.enter_context(safe_stop_on_exit(self.stop))
        try:
            self.start()
        except BaseException:
            stack.close()
            raise
        self._exit_stack = stack
        return self

    def __exit__(self, *exc: object) -> None:
        if self._exit_stack is not None:
            stack, self._exit_stack = self._exit_stack, None
            stack.close()


def period_stats(times: Sequence[float]) -> dict[str, float]:
    """Rate and period statistics (mean/p50/p99/max, in ms) of a sequence of timestamps."""
    t = np.asarray(times, dtype=float)
    if t.size < 2:
        return {"cycles": float(t.size), "rate_hz": 0.0, "mean_ms": math.nan, "p50_ms": math.nan,
                "p99_ms": math.nan, "max_ms": math.nan}
    dt = np.diff(t) * 1e3
    rate = float(1e3 / dt.mean()) if dt.mean() > 0 else math.inf  # a clock that did not move
    return {"cycles": float(t.size), "rate_hz": rate, "mean_ms": float(dt.mean()),
            "p50_ms": float(np.percentile(dt, 50)), "p99_ms": float(np.percentile(dt, 99)),
            "max_ms": float(dt.max())}
