"""Emulators in their own processes (hardware/emulator_process.py), real time on real
transports: drivers in processes of their own follow targets against them, and a factory
that fails is reported to the parent."""

import contextlib
import functools
import gc

import numpy as np
import pytest

from dexdrake.hardware.allegro_can import AllegroConfig, default_joint_limits
from dexdrake.hardware.allegro_emulator import EmulatorConfig
from dexdrake.hardware.driver_process import DriverProcess, ProcessConfig, allegro_on_bus, z1_client
from dexdrake.hardware.emulator_process import EmulatorProcess, allegro_emulator, z1_emulator
from dexdrake.hardware.safety import HardwareError
from dexdrake.hardware.z1_emulator import Z1EmulatorConfig
from dexdrake.hardware.z1_udp import Z1Config, free_udp_port

from test_driver_process import _multicast_bus_args
from waiting import wait_for

PROC = ProcessConfig(heartbeat_timeout_s=5.0)


def test_drivers_in_their_processes_follow_targets_against_emulator_processes():
    bus = _multicast_bus_args()
    lo, hi = default_joint_limits()
    hand_target = lo + 0.4 * (hi - lo)
    arm_target = np.array([0.0, 0.3, -0.3, 0.0, 0.0, 0.0])
    client = free_udp_port()
    with EmulatorProcess(functools.partial(allegro_emulator, bus, EmulatorConfig())), \
            EmulatorProcess(functools.partial(z1_emulator, Z1EmulatorConfig(port=0, client_port=client))) as arm_emulator:
        hand_cfg = AllegroConfig(watchdog_timeout_s=1.0, temperature_timeout_s=3.0, reply_timeout_s=2.0)
        arm_cfg = Z1Config(local_port=client, controller_port=arm_emulator.report, watchdog_timeout_s=1.0,
                           mode_timeout_s=5.0)
        with DriverProcess(functools.partial(allegro_on_bus, bus, 0, hand_cfg), PROC, "Allegro hand") as hand, \
                DriverProcess(functools.partial(z1_client, arm_cfg), PROC, "Z1 arm") as arm:
            hand.command_positions(hand_target)
            arm.command_positions(arm_target)
            assert wait_for(lambda: np.allclose(hand.state().q, hand_target, atol=0.05), 20.0)
            assert wait_for(lambda: np.allclose(arm.state().q, arm_target, atol=0.02), 20.0)
            assert hand.state().fault is None and arm.state().fault is None


def _heap_report(stack: contextlib.ExitStack) -> tuple[None, object]:
    """A factory whose device reports, at the end, how many objects its process froze."""
    return None, lambda: {"frozen": gc.get_freeze_count()}


def test_the_emulators_process_freezes_its_heap_once_built():
    """A full garbage collection stops the emulator while it walks the tracked objects:
    those of the imports and of the emulator built are frozen out of its reach."""
    with EmulatorProcess(_heap_report) as emulator:
        pass
    assert emulator.final["frozen"] > 10_000


def test_an_emulator_that_cannot_start_is_reported():
    taken = EmulatorProcess(functools.partial(z1_emulator, Z1EmulatorConfig(port=0)))
    with taken:
        clash = EmulatorProcess(functools.partial(z1_emulator, Z1EmulatorConfig(port=taken.report)))
        with pytest.raises(HardwareError, match="emulator process did not start: HardwareError: "
                                                "Z1 emulator: cannot bind"):
            clash.start()
