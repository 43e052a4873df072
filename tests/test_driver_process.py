"""Drivers in their own processes (hardware/driver_process.py): the proxy follows targets
and reports state and faults; the child safe-stops the device when the parent stops it, is
hit by repeated Ctrl-C, dies or hangs; no process is left behind.

The emulators run in the test process: the Z1 over UDP on a free port, the Allegro on
python-can's udp_multicast interface (a free port), which crosses processes. An Allegro
emulator keeps its servo on and its last PWM when the host goes silent (the spec), so a
servo found off proves the child's safe stop ran."""

import dataclasses
import functools
import gc
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from dexdrake.hardware.allegro_can import AllegroConfig, default_joint_limits
from dexdrake.hardware.allegro_emulator import AllegroEmulator, EmulatorConfig
from dexdrake.hardware.can_bus import open_can_bus
from dexdrake.hardware.driver_process import (
    DriverProcess, ProcessConfig, StateCodec, allegro_on_bus, z1_client,
)
from dexdrake.hardware.safety import HardwareError
from dexdrake.hardware.z1_emulator import Z1Emulator, Z1EmulatorConfig
from dexdrake.hardware.z1_udp import ArmFSMState, Z1Config, Z1State, free_udp_port

from waiting import wait_for

# generous timeouts: the emulators share this (possibly loaded) process; the tests are about
# what happens, not how fast
HAND = AllegroConfig(watchdog_timeout_s=1.0, temperature_timeout_s=3.0, reply_timeout_s=2.0)
PROC = ProcessConfig(heartbeat_timeout_s=5.0)


def _z1(emu: Z1Emulator) -> Z1Config:
    return Z1Config(local_port=emu.config.client_port, controller_port=emu.port, watchdog_timeout_s=1.0,
                    mode_timeout_s=5.0)


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", 0))
        return s.getsockname()[1]


def _multicast_bus_args() -> dict:
    from can.interfaces.udp_multicast import UdpMulticastBus

    return dict(interface="udp_multicast", channel=UdpMulticastBus.DEFAULT_GROUP_IPv4,
                port=_free_udp_port(), receive_own_messages=False)


@pytest.fixture
def z1_emulator():
    with Z1Emulator(Z1EmulatorConfig(port=0, client_port=free_udp_port())) as emu:
        yield emu


@pytest.fixture
def allegro_emulator():
    args = _multicast_bus_args()
    bus = open_can_bus(args)
    try:
        with AllegroEmulator(bus, config=EmulatorConfig()) as emu:
            yield emu, args
    finally:
        bus.shutdown()


def _gone(pid: int) -> bool:
    """True when process `pid` has exited (a zombie awaiting its reaper counts as exited)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True


def test_state_codec_round_trips_a_driver_state():
    st = Z1State(1.5, ArmFSMState.LOWCMD, np.arange(6.0), -np.arange(6.0), np.ones(6), np.zeros(6),
                 "fault", np.full(6, 0.5))
    codec = StateCodec(st)
    back = codec.decode(codec.encode(st), "reported")
    assert back.fsm is ArmFSMState.LOWCMD and back.t == 1.5 and back.fault == "reported"
    np.testing.assert_array_equal(back.q, st.q)
    np.testing.assert_array_equal(back.q_target, st.q_target)


def test_z1_in_its_process_follows_targets_and_stops_in_passive(z1_emulator):
    emu = z1_emulator
    arm = DriverProcess(functools.partial(z1_client, _z1(emu)), PROC, "Z1 arm")
    with arm:
        pid = arm.pid
        assert arm.running and arm.state().fault is None
        target = np.array([0.0, 0.3, -0.3, 0.0, 0.0, 0.0])
        arm.command_positions(target)
        # the driver's reading lags the emulator's joints by a reply: both settle at the target
        assert wait_for(lambda: np.allclose(arm.state().q, target, atol=0.02)
                        and np.allclose(emu.q, target, atol=0.02), 15.0)
        assert arm.stats()["cycles"] > 10
        times = arm.loop_times()  # the child's tick times, on the clock every process shares
        assert times.size > 10 and np.all(np.diff(times) > 0) and times[-1] <= time.monotonic()
        assert np.all(arm.loop_times(times[-1]) > times[-1])
        with pytest.raises(HardwareError, match="6 joint targets"):
            arm.command_positions(np.zeros(5))
        sent = emu.commands_received
    assert not arm.running and _gone(pid)
    assert emu.commands_received > sent and emu.fsm == ArmFSMState.PASSIVE
    assert arm.stats()["cycles"] > 10  # the final report of the child
    assert arm.loop_times().size == 0
    with pytest.raises(HardwareError, match="not running"):
        arm.command_positions(target)


def _may_run_realtime() -> bool:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except OSError:
        return False
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    return True


def test_a_realtime_priority_is_set_in_the_child_or_refused_at_start(z1_emulator):
    cfg = ProcessConfig(heartbeat_timeout_s=5.0, realtime_priority=20)
    arm = DriverProcess(functools.partial(z1_client, _z1(z1_emulator)), cfg, "Z1 arm")
    if not _may_run_realtime():
        with pytest.raises(HardwareError, match="cannot run at SCHED_FIFO priority 20"):
            arm.start()
        return
    with arm:
        assert os.sched_getscheduler(arm.pid) == os.SCHED_FIFO
        assert os.sched_getparam(arm.pid).sched_priority == 20
    with pytest.raises(HardwareError, match="0..99"):
        ProcessConfig(realtime_priority=100)


def test_a_fault_in_the_child_reaches_the_parent(z1_emulator):
    emu = z1_emulator
    with DriverProcess(functools.partial(z1_client, _z1(emu)), PROC, "Z1 arm") as arm:
        assert arm.state().fault is None
        emu.stall(5.0)
        assert wait_for(lambda: arm.state().fault is not None, 10.0)
        assert "no Z1 state" in arm.state().fault


def test_a_reset_fault_clears_the_parents_view_too(z1_emulator):
    """After reset_fault() the parent reports no fault once the child's driver has cleared
    it: the fault the child had is not reported again on the way (its driver's loop thread
    clears the latch on its next pass); one still latched after the grace is."""
    emu = z1_emulator
    with DriverProcess(functools.partial(z1_client, _z1(emu)), PROC, "Z1 arm") as arm:
        for _ in range(3):
            emu.stall(1.5)
            assert wait_for(lambda: arm.state().fault is not None, 10.0)
            assert wait_for(lambda: emu.stall_until < time.monotonic(), 10.0)  # replies are back
            arm.reset_fault()
            assert wait_for(lambda: arm.state().fault is None and arm.state().fsm == ArmFSMState.LOWCMD, 5.0)
            time.sleep(0.5)  # past the grace: no late report of the old fault
            assert arm.state().fault is None
        emu.stall(3.0)
        assert wait_for(lambda: arm.state().fault is not None, 10.0)
        arm.reset_fault()  # the replies are still stalled: the watchdog trips again
        assert wait_for(lambda: arm.state().fault is not None, 5.0)


def test_a_target_written_before_reset_fault_is_never_applied_after_it(z1_emulator):
    """A target the parent wrote while the arm was faulted, just before reset_fault(), is
    dropped with the reset: the child's driver re-arms holding the position the arm sagged
    to; the next target is followed."""
    emu = z1_emulator
    with DriverProcess(functools.partial(z1_client, _z1(emu)), PROC, "Z1 arm") as arm:
        up = np.array([0.0, 1.0, -1.0, 0.0, 0.0, 0.0])
        arm.command_positions(up)
        assert wait_for(lambda: np.allclose(emu.q, up, atol=0.02), 15.0)
        emu.stall(1.5)
        assert wait_for(lambda: arm.state().fault is not None, 10.0)
        assert wait_for(lambda: emu.stall_until < time.monotonic() and np.max(np.abs(emu.q - up)) > 0.3, 10.0)
        time.sleep(0.3)  # replies are back
        arm.command_positions(up)
        arm.reset_fault()
        assert wait_for(lambda: arm.state().fault is None and arm.state().fsm == ArmFSMState.LOWCMD, 5.0)
        q_sag = emu.q
        time.sleep(0.5)
        assert arm.state().fault is None
        np.testing.assert_allclose(arm.state().q_target, q_sag, atol=0.05)
        np.testing.assert_allclose(emu.q, q_sag, atol=0.05)
        arm.command_positions(up)
        assert wait_for(lambda: np.allclose(emu.q, up, atol=0.02), 15.0)


def test_a_driver_that_cannot_start_raises_in_the_parent_and_leaves_no_process():
    quiet = _multicast_bus_args()  # nobody answers on this bus
    hand = DriverProcess(functools.partial(allegro_on_bus, quiet, 0, HAND), PROC, "Allegro hand")
    with pytest.raises(HardwareError, match="did not start: HardwareError: Allegro: no Info reply"):
        hand.start()
    assert _gone(hand.pid) and not hand.running


def test_allegro_in_its_process_stops_with_servo_off(allegro_emulator):
    emu, args = allegro_emulator
    lo, hi = default_joint_limits()
    with DriverProcess(functools.partial(allegro_on_bus, args, 0, HAND), PROC, "Allegro hand") as hand:
        pid = hand.pid
        assert wait_for(lambda: emu.servo_on, 5.0)
        target = lo + 0.4 * (hi - lo)
        hand.command_positions(target)
        assert wait_for(lambda: np.allclose(emu.q, target, atol=0.05), 20.0)
        assert np.isfinite(hand.state().t) and hand.state().fault is None
    assert _gone(pid) and not emu.servo_on and not np.any(emu.pwm)


_PARENT = """
import functools, sys, time
from dexdrake.hardware.allegro_can import AllegroConfig
from dexdrake.hardware.driver_process import DriverProcess, ProcessConfig, allegro_on_bus
if __name__ == "__main__":
    args = dict(interface="udp_multicast", channel={channel!r}, port={port}, receive_own_messages=False)
    config = AllegroConfig(watchdog_timeout_s=1.0, temperature_timeout_s=3.0, reply_timeout_s=2.0)
    with DriverProcess(functools.partial(allegro_on_bus, args, 0, config),
                       ProcessConfig(heartbeat_timeout_s=1.0), name="Allegro hand") as hand:
        print(hand.pid, flush=True)
        while True:
            time.sleep(0.01)
"""


@pytest.fixture
def parent_script(allegro_emulator, tmp_path):
    """(emulator, Popen of a parent process holding an Allegro DriverProcess, child pid)."""
    emu, args = allegro_emulator
    script = tmp_path / "parent.py"
    script.write_text(textwrap.dedent(_PARENT.format(channel=args["channel"], port=args["port"])))
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True,
                            start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        child = int(proc.stdout.readline())
        assert wait_for(lambda: emu.servo_on, 10.0)
        yield emu, proc, child
    finally:
        with __import__("contextlib").suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)


def test_repeated_ctrl_c_ends_in_the_childs_safe_stop(parent_script):
    emu, proc, child = parent_script
    for _ in range(3):  # a terminal's Ctrl-C reaches the whole process group
        os.killpg(proc.pid, signal.SIGINT)
        time.sleep(0.001)
    assert proc.wait(20) != 0  # the interrupt is re-raised once the stop is done
    assert wait_for(lambda: _gone(child), 10.0)
    assert not emu.servo_on and not np.any(emu.pwm)


@pytest.mark.parametrize("end", [signal.SIGKILL, signal.SIGSTOP], ids=["parent_dies", "parent_hangs"])
def test_the_child_stops_the_device_when_the_parent_is_lost(parent_script, end):
    emu, proc, child = parent_script
    os.kill(proc.pid, end)
    assert wait_for(lambda: not emu.servo_on, 10.0)
    assert not np.any(emu.pwm)
    assert wait_for(lambda: _gone(child), 10.0)


def test_a_parent_that_stops_in_the_middle_of_a_command_write_is_still_lost(z1_emulator):
    """A parent frozen halfway through writing a target (the sequence left odd) and no longer
    beating: the child neither spins on the half-written target nor keeps the arm going."""
    from dexdrake.hardware import driver_process as dp

    arm = DriverProcess(functools.partial(z1_client, _z1(z1_emulator)),
                        ProcessConfig(heartbeat_timeout_s=0.3), "Z1 arm")
    with arm:
        arm._beating.clear()  # the parent's heartbeat stops ...
        arm._buf[dp._COMMAND] += 1.0  # ... halfway through a write
        assert wait_for(lambda: not arm._process.is_alive(), 10.0)
        assert "parent heartbeat lost" in arm.state().fault


def test_the_scenarios_heartbeat_timeout_reaches_the_driver_process(z1_emulator):
    """A scenario's drivers.arm.heartbeat_timeout_s (2 s) is the child's: a parent that stops
    beating keeps its arm past the default 0.5 s, and loses it after 2 s."""
    from dexdrake.systems.scenario import parse_scenario, process_config

    scenario = parse_scenario("drivers: {hand: {kind: hardware}, arm: {kind: hardware, heartbeat_timeout_s: 2.0}, "
                              "camera: {kind: k4a}}")
    arm = DriverProcess(functools.partial(z1_client, _z1(z1_emulator)), process_config(scenario.drivers.arm),
                        "Z1 arm")
    with arm:
        arm._beating.clear()  # the parent's heartbeat stops
        time.sleep(1.0)
        assert arm.running and arm.state().fault is None
        assert wait_for(lambda: not arm._process.is_alive(), 10.0)
        age_ms = int(arm.state().fault.removeprefix("parent heartbeat lost for ").removesuffix(" ms"))
        assert age_ms >= 2000


class _BrokenDriver:
    """A driver whose command path raises; `stop()` leaves a marker file (its safe stop)."""

    def __init__(self, marker: str):
        self.marker, self.running = marker, False

    def start(self) -> None:
        self.running = True

    def stop(self) -> None:
        self.running = False
        Path(self.marker).write_text("stopped")

    def state(self) -> Z1State:
        return Z1State(0.0, ArmFSMState.LOWCMD, np.zeros(6), np.zeros(6), np.zeros(6), np.zeros(6), None)

    def command_positions(self, q) -> None:
        raise RuntimeError("command path broken")

    def stats(self) -> dict:
        return {}


def _broken_driver(marker: str, stack) -> _BrokenDriver:
    return _BrokenDriver(marker)


def test_a_failing_supervision_ends_in_the_safe_stop_and_is_reported(tmp_path):
    marker = tmp_path / "stopped"
    with DriverProcess(functools.partial(_broken_driver, str(marker)), PROC, "broken") as proxy:
        proxy.command_positions(np.zeros(6))
        assert wait_for(lambda: not proxy.running, 10.0)
        assert "driver process failed: RuntimeError('command path broken')" in proxy.state().fault
    assert marker.read_text() == "stopped"


class _HeapReporter(_BrokenDriver):
    """A driver whose stats() tell how many objects were frozen when it started."""

    def start(self) -> None:
        super().start()
        self.frozen_at_start = gc.get_freeze_count()

    def stats(self) -> dict:
        return {"frozen_at_start": self.frozen_at_start}


def _heap_reporter(marker: str, stack) -> _HeapReporter:
    return _HeapReporter(marker)


def test_the_child_freezes_its_heap_before_the_driver_starts(tmp_path):
    """A full garbage collection stops the driver's loop threads while it walks the tracked
    objects: those of the imports (tens of thousands) are frozen out of its reach first."""
    with DriverProcess(functools.partial(_heap_reporter, str(tmp_path / "stopped")), PROC, "heap") as proxy:
        assert proxy.stats()["frozen_at_start"] > 10_000


class _LockReporter(_BrokenDriver):
    """A driver whose stats() tell how much of its process's memory was locked when it started (kB)."""

    def start(self) -> None:
        super().start()
        status = dict(line.split(":", 1) for line in open("/proc/self/status").read().splitlines())
        self.locked_kb = int(status["VmLck"].split()[0])

    def stats(self) -> dict:
        return {"locked_kb": self.locked_kb}


def _lock_reporter(marker: str, stack) -> _LockReporter:
    return _LockReporter(marker)


def test_a_realtime_child_locks_its_memory(tmp_path):
    """With a realtime priority the child's pages are locked in RAM (none reclaimed and faulted
    back in under its loops); without, nothing is locked."""
    factory = functools.partial(_lock_reporter, str(tmp_path / "stopped"))
    with DriverProcess(factory, dataclasses.replace(PROC, realtime_priority=10), "locked") as proxy:
        assert proxy.stats()["locked_kb"] > 10_000
    with DriverProcess(factory, PROC, "unlocked") as proxy:
        assert proxy.stats()["locked_kb"] == 0


def test_a_killed_driver_process_is_a_fault_and_stop_still_cleans_up(z1_emulator):
    with DriverProcess(functools.partial(z1_client, _z1(z1_emulator)), PROC, "Z1 arm") as arm:
        os.kill(arm.pid, signal.SIGKILL)
        assert wait_for(lambda: arm.state().fault is not None, 10.0)
        assert "exited with code -9" in arm.state().fault and not arm.running
    assert _gone(arm.pid)
