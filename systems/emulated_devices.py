"""The devices of an `emulated_process` scenario: emulators in processes of their own (an
`emulated_world` scenario's run in one world process: systems/emulated_world.py).

`running_emulators(scenario)` starts the Allegro firmware emulator on the scenario's
python-can bus (one that crosses processes: `udp_multicast`) and the Z1 controller emulator
on UDP (hardware/emulator_process.py), each in its own process, in real time on the wall
clock, and yields the scenario with its free ports filled in (`port: 0` entries: the CAN
bus's UDP port, the Z1 controller's port and the client's port, which the emulator sends
every state to, as the real controller sends to the SDK's fixed port). The real mode's
code path (dry run, supervised episode) then runs against them unchanged. Leaving the
context stops both emulators (after the drivers' safe stop, which the caller owns) and
fills `Emulators.final` with the state each device was left in.

The emulated world is simple and stated as such: each emulator moves its joints with its
own dynamics (the hand's PWM double integrator, the arm's LOWCMD law against its inertia
and gravity), both starting at zero joint angles; there is no object in their world (the
camera of such a scenario sees a static scene: systems/station.py).
"""

from __future__ import annotations

import contextlib
import dataclasses as dc
import functools
from collections.abc import Iterator
from dataclasses import dataclass, field

from dexdrake.hardware.emulator_process import EmulatorProcess, allegro_emulator, z1_emulator
from dexdrake.systems.scenario import Scenario


@dataclass
class Emulators:
    """The running emulator processes (or the world process, "world", and its `WorldView`,
    `world`) and, once stopped, their devices' last states."""

    processes: dict[str, EmulatorProcess] = field(default_factory=dict)
    world: object = None

    @property
    def final(self) -> dict[str, dict | None]:
        """{"hand": ..., "arm": ...}: each device's last state (None: not reported)."""
        out = {name: proc.final for name, proc in self.processes.items() if name != "world"}
        if "world" in self.processes:  # one process reports both devices
            final = self.processes["world"].final or {}
            out.update(hand=final.get("hand"), arm=final.get("arm"))
        return out

    @property
    def pids(self) -> list[int]:
        return [proc.pid for proc in self.processes.values() if proc.pid is not None]


def resolve_ports(scenario: Scenario) -> Scenario:
    """`scenario` with the `0` ports of its CAN bus and of the Z1 client replaced by free
    ones (the Z1 controller's `0` is the emulator's own bind, reported when it starts)."""
    from dexdrake.hardware.z1_udp import free_udp_port

    h, a = scenario.drivers.hand, scenario.drivers.arm
    hand = dc.replace(h, port=free_udp_port("") if h.port == 0 else h.port)
    arm = dc.replace(a, local_port=free_udp_port(a.host) if a.local_port == 0 else a.local_port)
    return dc.replace(scenario, drivers=dc.replace(scenario.drivers, hand=hand, arm=arm))


@contextlib.contextmanager
def running_emulators(scenario: Scenario, emulators: Emulators | None = None) -> Iterator[Scenario]:
    """Start the emulators of an `emulated_process` scenario (module docstring); yields the
    scenario with the ports they use. `emulators` (optional) receives the processes."""
    from dexdrake.hardware.allegro_emulator import EmulatorConfig
    from dexdrake.hardware.z1_emulator import Z1EmulatorConfig
    from dexdrake.hardware.z1_udp import CONTROLLER_PORT, SDK_PORT
    from dexdrake.systems.station import can_bus_args

    emulators = emulators if emulators is not None else Emulators()
    scenario = resolve_ports(scenario)
    arm = scenario.drivers.arm
    client = SDK_PORT if arm.local_port is None else arm.local_port
    controller = CONTROLLER_PORT if arm.controller_port is None else arm.controller_port
    with contextlib.ExitStack() as stack:
        # each emulator stands for a device with its own processor: it runs at its driver
        # entry's realtime priority (0: normal scheduling)
        hand = EmulatorProcess(functools.partial(allegro_emulator, can_bus_args(scenario), EmulatorConfig()),
                               scenario.drivers.hand.realtime_priority or 0, name="allegro-emulator")
        emulators.processes["hand"] = hand
        stack.enter_context(hand)
        z1 = EmulatorProcess(functools.partial(z1_emulator, Z1EmulatorConfig(host=arm.host, port=controller,
                                                                              client_port=client)),
                             arm.realtime_priority or 0, name="z1-emulator")
        emulators.processes["arm"] = z1
        stack.enter_context(z1)
        yield dc.replace(scenario, drivers=dc.replace(
            scenario.drivers, arm=dc.replace(arm, local_port=client, controller_port=z1.report)))
