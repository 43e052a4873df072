"""Tests for the shared hardware safety pieces (pure Python, injected clocks)."""

import math
import os
import signal
import time
import warnings

import numpy as np
import pytest

from dexdrake.hardware.safety import (
    FaultLatch,
    HardwareError,
    JointLimits,
    RateLimiter,
    Watchdog,
    period_stats,
    safe_stop_on_exit,
)


class FakeClock:
    def __init__(self, t: float = 0.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def test_joint_limits_clamp_and_hold_on_nan():
    lim = JointLimits([-1.0, 0.0], [1.0, 2.0])
    np.testing.assert_array_equal(lim.apply([5.0, -3.0]), [1.0, 0.0])
    assert lim.clipped == 1
    np.testing.assert_array_equal(lim.apply([0.5, 1.5]), [0.5, 1.5])
    held = lim.apply([np.nan, 1.0])
    np.testing.assert_array_equal(held, [0.5, 1.5])
    assert lim.non_finite == 1 and lim.last_rejected
    np.testing.assert_array_equal(lim.apply([np.inf, -np.inf]), [0.5, 1.5])
    assert lim.non_finite == 2
    lim.apply([0.0, 0.0])
    assert not lim.last_rejected


def test_joint_limits_initial_hold_is_inside_limits():
    lim = JointLimits([0.2, 0.3], [1.0, 1.0])
    np.testing.assert_array_equal(lim.apply([np.nan, np.nan]), [0.2, 0.3])


@pytest.mark.parametrize(
    "lower, upper",
    [([0.0, 1.0], [1.0, 0.0]), ([0.0], [1.0, 2.0]), ([np.nan], [1.0])],
)
def test_joint_limits_reject_bad_limits(lower, upper):
    with pytest.raises(HardwareError):
        JointLimits(lower, upper)


def test_joint_limits_wrong_command_size():
    with pytest.raises(HardwareError, match="expected 2"):
        JointLimits([0, 0], [1, 1]).apply([0.5, 0.5, 0.5])


def test_rate_limiter_bounds_step_and_converges():
    rl = RateLimiter([1.0, 2.0], initial=[0.0, 0.0])
    out = rl.step([10.0, -10.0], dt=0.1)
    np.testing.assert_allclose(out, [0.1, -0.2])
    for _ in range(200):
        out = rl.step([0.5, -0.5], dt=0.01)
    np.testing.assert_allclose(out, [0.5, -0.5])
    with pytest.raises(HardwareError):
        rl.step([np.nan, 0.0], dt=0.01)
    with pytest.raises(HardwareError):
        RateLimiter(0.0, initial=[0.0])


def test_watchdog_expires_after_timeout_and_feed_rearms():
    clock = FakeClock()
    wd = Watchdog(0.05, clock=clock)
    clock.t = 0.04
    assert not wd.expired()
    clock.t = 0.051
    assert wd.expired()
    wd.feed()
    assert not wd.expired()
    assert wd.expired(now=0.2)
    assert wd.feeds == 1


def test_fault_latch_keeps_first_reason_until_reset():
    clock = FakeClock(3.0)
    latch = FaultLatch(clock)
    assert not latch.tripped
    assert latch.trip("watchdog")
    assert not latch.trip("over-temperature")
    assert latch.reason == "watchdog" and latch.fault.time == 3.0 and latch.trips == 2
    latch.reset()
    assert not latch.tripped and latch.reason is None


def test_safe_stop_runs_on_exception_and_normal_exit():
    calls = []
    with pytest.raises(RuntimeError):
        with safe_stop_on_exit(lambda: calls.append("stop")):
            raise RuntimeError("boom")
    assert calls == ["stop"]
    with safe_stop_on_exit(lambda: calls.append("stop")):
        pass
    assert calls == ["stop", "stop"]


def test_safe_stop_on_sigint_and_restores_handler():
    before = signal.getsignal(signal.SIGINT)
    calls = []
    with pytest.raises(KeyboardInterrupt):
        with safe_stop_on_exit(lambda: calls.append("stop")):
            os.kill(os.getpid(), signal.SIGINT)
    assert calls == ["stop"]
    assert signal.getsignal(signal.SIGINT) is before


def test_period_stats():
    s = period_stats([0.0, 0.002, 0.004, 0.010])
    assert s["cycles"] == 4 and s["max_ms"] == pytest.approx(6.0)
    assert s["mean_ms"] == pytest.approx(10 / 3) and s["rate_hz"] == pytest.approx(300.0)
    assert s["p50_ms"] == pytest.approx(2.0)
    assert period_stats([1.0])["rate_hz"] == 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clock that did not move: no division warning
        still = period_stats([2.0, 2.0, 2.0])
    assert still["rate_hz"] == math.inf and still["max_ms"] == 0.0


def test_fuzzed_can_frames_are_counted_and_faults_latched(load_script):
    """A small run of scripts/fuzz_hardware.py (the volume run: 100k frames)."""
    fuzz = load_script("fuzz_hardware")
    result = fuzz.fuzz_can(2000, seed=3)
    assert fuzz.passed(result), result
    assert result["bad"] > 500 and result["counted_bad"] == result["bad"]
    assert result["must_fault"] > 10 and sum(result["faults_latched"].values()) > 0
    for kind in ("device", "dlc", "unknown_id", "range", "rtr"):
        assert result["frame_errors"].get(kind, 0) > 0, result["frame_errors"]


def test_fuzzed_udp_datagrams_are_counted_and_faults_latched(load_script):
    fuzz = load_script("fuzz_hardware")
    result = fuzz.fuzz_udp(1000, seed=3)
    assert fuzz.passed(result), result
    assert result["client_bad"] > 100 and result["emulator_bad"] > 100
    assert result["client_fault"] > 0 and any("motor error" in k for k in result["faults_latched"])
    assert {"size", "head", "nonfinite"} <= set(result["emulator_packet_errors"])


def test_fuzzing_the_driver_and_emulator_processes_over_real_transports(load_script):
    """The default placement of scripts/fuzz_hardware.py: every process survives, every bad
    frame and datagram is counted, every due fault comes and is timed."""
    fuzz = load_script("fuzz_hardware")
    can_result = fuzz.fuzz_can_processes(400, seed=3)
    assert fuzz.passed(can_result), can_result
    assert can_result["frame_errors"].get("bus:CanOperationError", 0) > 0  # undeliverable on the transport
    assert can_result["time_to_safe_stop"]["timed"] > 0
    udp_result = fuzz.fuzz_udp_processes(400, seed=3)
    assert fuzz.passed(udp_result), udp_result
    assert udp_result["emulator_bad"] > 50 and udp_result["time_to_safe_stop"]["timed"] > 0


# ------------------------------------------------------------------ edges (from surviving mutants)
def test_vectors_broadcast_scalars_and_name_bad_input():
    rl = RateLimiter(0.5, initial=[0.0, 0.0, 0.0])
    np.testing.assert_array_equal(rl.max_rate, [0.5, 0.5, 0.5])
    with pytest.raises(HardwareError, match=r"^max_rate: expected 3 values, got shape \(2,\)$"):
        RateLimiter([1.0, 1.0], initial=[0.0, 0.0, 0.0])
    with pytest.raises(HardwareError, match=r"^command: expected 2 numbers, got 'ab'$"):
        JointLimits([0, 0], [1, 1]).apply("ab")
    with pytest.raises(HardwareError, match="expected 2 numbers"):
        JointLimits([0, 0], [1, 1]).apply([None, [1]])


def test_joint_limits_initial_reset_and_copies():
    lim = JointLimits([-1.0, -1.0], [1.0, 1.0], initial=[5.0, -0.5])
    np.testing.assert_array_equal(lim.last_safe, [1.0, -0.5])  # clamped into the limits
    np.testing.assert_array_equal(JointLimits([0.5], [1.0], initial=[np.nan]).last_safe, [0.5])
    held = lim.last_safe
    held[:] = 9.0  # a copy: the driver's hold value is not changed through it
    np.testing.assert_array_equal(lim.apply([np.nan, 0.0]), [1.0, -0.5])
    lim.reset([-3.0, 0.25])
    np.testing.assert_array_equal(lim.apply([np.nan, 0.0]), [-1.0, 0.25])
    with pytest.raises(HardwareError, match="reset value must be finite"):
        lim.reset([np.inf, 0.0])
    out = lim.apply([0.5, 0.5])
    out[:] = 7.0
    np.testing.assert_array_equal(lim.apply([np.nan, np.nan]), [0.5, 0.5])
    assert lim.size == 2 and lim.clipped == 0 and lim.non_finite == 3
    with pytest.raises(HardwareError, match="must be equal 1-D"):
        JointLimits(np.zeros((2, 2)), np.ones((2, 2)))
    with pytest.raises(HardwareError, match=r"lower > upper at joints \[1\]"):
        JointLimits([0.0, 1.0], [1.0, 0.5])
    with pytest.raises(HardwareError, match="finite"):
        JointLimits([0.0], [np.inf])


def test_rate_limiter_reset_and_refusals():
    rl = RateLimiter([1.0, 1.0], initial=[0.0, 0.0])
    rl.reset([0.3, -0.3])
    np.testing.assert_allclose(rl.step([0.3, -0.3], dt=0.1), [0.3, -0.3])  # at the target: stays
    np.testing.assert_allclose(rl.step([0.32, -0.5], dt=0.1), [0.32, -0.4])  # within the step: reached
    np.testing.assert_allclose(rl.step([0.32, -0.4], dt=0.0), [0.32, -0.4])
    out = rl.output
    out[:] = 5.0
    np.testing.assert_allclose(rl.output, [0.32, -0.4])
    for bad in ({"dt": -0.01}, {"dt": np.nan}, {"dt": np.inf}):
        with pytest.raises(HardwareError, match=r"^rate limiter: dt must be finite and >= 0, got "):
            rl.step([0.0, 0.0], **bad)
    with pytest.raises(HardwareError, match="reset value must be finite"):
        rl.reset([np.nan, 0.0])
    for initial in ([[0.0]], [np.nan]):
        with pytest.raises(HardwareError, match=r"^rate limiter: initial must be a finite 1-D vector$"):
            RateLimiter(1.0, initial=initial)
    for rate in (np.inf, -1.0, [1.0, 0.0]):
        with pytest.raises(HardwareError, match=r"^rate limiter: max_rate must be finite and > 0$"):
            RateLimiter(rate, initial=[0.0, 0.0])


def test_watchdog_boundary_reset_and_bad_timeouts():
    clock = FakeClock(0.0)
    wd = Watchdog(0.05, clock=clock)
    clock.t = 0.05
    assert not wd.expired() and wd.since_last() == 0.05  # expires only after the timeout
    clock.t = 10.2
    assert wd.expired()
    wd.reset()
    assert not wd.expired() and wd.feeds == 0
    wd.reset(now=10.0)
    assert wd.since_last(now=10.03) == pytest.approx(0.03) and wd.expired()
    wd.feed(now=10.2)
    assert wd.since_last() == 0.0 and wd.feeds == 1
    for timeout in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(HardwareError, match=r"^watchdog: timeout must be > 0 s, got "):
            Watchdog(timeout, clock=clock)


def test_safe_stop_on_sigterm_and_restores_even_if_stop_fails():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt, match="SIGTERM"):
        with safe_stop_on_exit(lambda: None):
            os.kill(os.getpid(), signal.SIGTERM)
    assert signal.getsignal(signal.SIGTERM) is before

    def failing_stop():
        raise RuntimeError("stop failed")

    with pytest.raises(RuntimeError, match="stop failed"):
        with safe_stop_on_exit(failing_stop):
            assert signal.getsignal(signal.SIGINT) is not before
    assert signal.getsignal(signal.SIGTERM) is before


def test_safe_stop_context_starts_stops_and_stops_after_a_failed_start():
    from dexdrake.hardware.safety import SafeStopContext

    class Driver(SafeStopContext):
        def __init__(self, fail=False):
            self.calls, self.fail = [], fail

        def start(self):
            self.calls.append("start")
            if self.fail:
                raise HardwareError("no device")

        def stop(self):
            self.calls.append("stop")

    driver = Driver()
    with driver as entered:
        assert entered is driver and driver.calls == ["start"]
    assert driver.calls == ["start", "stop"]
    driver.__exit__(None, None, None)  # a second exit stops nothing more
    assert driver.calls == ["start", "stop"]
    failing = Driver(fail=True)
    with pytest.raises(HardwareError, match="no device"):
        with failing:
            pass
    assert failing.calls == ["start", "stop"]


def test_period_stats_percentiles_and_empty():
    times = np.cumsum([0.0] + [0.002] * 98 + [0.012])
    s = period_stats(times)
    assert s["cycles"] == 100 and s["p50_ms"] == pytest.approx(2.0) and s["max_ms"] == pytest.approx(12.0)
    assert 2.0 < s["p99_ms"] < 12.0
    empty = period_stats([])
    assert empty["cycles"] == 0 and empty["rate_hz"] == 0.0
    assert all(np.isnan(empty[k]) for k in ("mean_ms", "p50_ms", "p99_ms", "max_ms"))


def test_joint_limits_more_edges():
    """Initial holds below the lower limit and for limits that exclude 0, equal limits (a
    locked joint), a reset above the upper limit, counts over several commands."""
    lim = JointLimits([-1.0, -1.0], [1.0, 1.0], initial=[-5.0, 0.5])
    assert lim.last_rejected is False
    np.testing.assert_array_equal(lim.last_safe, [-1.0, 0.5])
    np.testing.assert_array_equal(JointLimits([-2.0], [-1.0], initial=[np.nan]).last_safe, [-1.0])
    np.testing.assert_array_equal(JointLimits([-2.0], [-1.0]).last_safe, [-1.0])
    locked = JointLimits([0.5, 0.0], [0.5, 1.0])
    np.testing.assert_array_equal(locked.apply([0.0, 0.5]), [0.5, 0.5])
    with pytest.raises(HardwareError, match=r"^limits: lower > upper at joints \[1\]$"):
        JointLimits([0.0, 1.0, 0.5], [1.0, 0.5, 0.5])
    with pytest.raises(HardwareError, match="^limits: lower and upper must be finite$"):
        JointLimits([0.0], [np.inf])
    lim.reset([0.0, 3.0])
    np.testing.assert_array_equal(lim.apply([np.nan, 0.0]), [0.0, 1.0])
    lim.apply([2.0, 0.0])
    lim.apply([0.0, -2.0])
    assert lim.clipped == 2
    for bad, name in (("reset", "reset"), ("apply", "command")):
        with pytest.raises(HardwareError, match=rf"^{name}: expected 2 values, got shape \(3,\)$"):
            getattr(lim, bad)([0.0, 0.0, 0.0])
    with pytest.raises(HardwareError, match=r"^initial: expected 2 values"):
        JointLimits([0, 0], [1, 1], initial=[0.0])
    with pytest.raises(HardwareError, match="^limits: reset value must be finite$"):
        lim.reset([np.nan, 0.0])


def test_rate_limiter_and_watchdog_messages_and_counts():
    rl = RateLimiter(1.0, initial=[0.0, 0.0])
    for call, name in ((rl.reset, "reset"), (lambda v: rl.step(v, 0.1), "target")):
        with pytest.raises(HardwareError, match=rf"^{name}: expected 2 values"):
            call([0.0])
    with pytest.raises(HardwareError, match=r"^rate limiter: reset value must be finite$"):
        rl.reset([np.nan, 0.0])
    with pytest.raises(HardwareError, match=r"^rate limiter: target must be finite \(clamp it first\)$"):
        rl.step([np.inf, 0.0], 0.1)
    clock = FakeClock(10.2)
    wd = Watchdog(0.05, clock=clock)
    wd.feed(now=10.1)  # the given time, not the clock's
    assert wd.since_last() == pytest.approx(0.1) and wd.expired()
    wd.feed()
    assert wd.feeds == 2 and not wd.expired()


def test_period_stats_of_two_stamps():
    s = period_stats([0.0, 0.002])
    assert s["cycles"] == 2 and s["rate_hz"] == pytest.approx(500.0) and s["max_ms"] == pytest.approx(2.0)


def test_signals_during_the_safe_stop_never_cut_it_short():
    """Ctrl-C in the body raises once; any number of signals during the stop are only
    counted (the stop runs to its end); a signal that came only during the stop raises
    KeyboardInterrupt after it."""
    before = signal.getsignal(signal.SIGINT)
    calls = []

    def stop():
        calls.append("begin")
        for _ in range(5):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.001)
        calls.append("end")

    with pytest.raises(KeyboardInterrupt, match="signal SIGINT$"):
        with safe_stop_on_exit(stop):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)
    assert calls == ["begin", "end"] and signal.getsignal(signal.SIGINT) is before
    with pytest.raises(KeyboardInterrupt, match="during the safe stop"):
        with safe_stop_on_exit(stop):
            pass
    assert calls == ["begin", "end"] * 2 and signal.getsignal(signal.SIGINT) is before
