"""The wall-clock emulated world of an `emulated_world` scenario: the grasp scene's physics
behind the real mode's drivers, in a device process of its own.

`running_world(scenario, emulators)` starts one process (hardware/emulator_process.py, at
the hand entry's `realtime_priority`, SCHED_FIFO) that builds the scenario's grasp scene
with the HIL joint drive (hand on its arm, object, table: `station.start_world`, as the
simulated-clock HIL builds it) and runs it as a free-running `HilWorld`
(systems/hil_world.py) in real time on the wall clock: no `advance_to` lockstep with a
control loop, never ahead of the wall clock, slower than real time only when the host
cannot keep up (`real_time_factor` in its stats). Inside it the Allegro firmware emulator
serves the scenario's CAN bus (a bus that crosses processes: `udp_multicast`) and the Z1
controller emulator its UDP port, both on the world's clock, their joints the plant's
(`JointDynamics`, `ArmDynamics`). The world publishes, in a block of shared memory, the
object's true pose and its loop statistics every `PUBLISH_PERIOD_S`; `WorldView` reads
them in the policy's process: the rendered camera draws the object where it is now (it
moves when the hand lifts it; perception tracks it) and the episode scores lift and
success on it. The driver processes, perception and the supervised episode are the real
mode's, unchanged.

What comes from the devices' specs (specs/allegro_v4.md, specs/z1.md) is what the emulators
implement: CAN framing, periods, servo and FSM logic, watchdogs; the Z1's LOWCMD PD law and
gains. Assumptions of this world (besides those of the HIL world's docstring: the PWM ->
N*m scale, the fingers' reflected inertia, the arm's gravity load, the object not gravity
compensated):
- The robot starts at rest at the hand's pre-grasp pose, the object where the seed places
  it (`ObjectPlacement.from_seed`), and the plant is held there ("on a stand") until the
  drivers hold the robot: the hand's servo on and the arm out of PASSIVE. From then on it
  moves freely; after the drivers' safe stop the arm, PASSIVE, sags under its weight.
- The camera renders the table, a wall and the object at the world's pose when the frame
  is taken (at most `PUBLISH_PERIOD_S` old); the robot is not drawn, so it never occludes
  the object (as in the simulated-clock HIL).
- The world's clock is the emulators' clock; the drivers run on the host's wall clock. When
  the world runs slower than real time, the devices stream slower in wall time, as a device
  whose processor is overloaded would.
"""

from __future__ import annotations

import contextlib
import dataclasses as dc
import functools
import multiprocessing
import threading
from collections.abc import Callable, Iterator

import numpy as np
from pydrake.math import RigidTransform

from dexdrake.hardware.emulator_process import EmulatorProcess, allegro_final, z1_final
from dexdrake.systems.emulated_devices import Emulators, resolve_ports, running_emulators
from dexdrake.systems.scenario import Scenario

PUBLISH_PERIOD_S = 0.005  # how often the world process publishes the object's pose (s): the plant step
# the shared block: the object's pose [x, y, z, qw, qx, qy, qz], the world's time (s), then STATS
STATS = ("steps", "sim_time_s", "wall_s", "real_time_factor", "lag_s", "late_replies", "late_arm_commands",
         "step_p50_ms", "step_p99_ms", "step_max_ms")
STATS_PERIOD_S = 0.5  # how often the world's step statistics are refreshed in the block (s)
_SIZE = 8 + len(STATS)


class WorldView:
    """The running world as the policy's process sees it: `object_pose()` (the object's
    true pose in the world) and `time` (the world's clock, s), both at most
    PUBLISH_PERIOD_S old, and `stats()` (the world's loop statistics, as HilWorld.stats, at
    most STATS_PERIOD_S old)."""

    def __init__(self, block) -> None:
        self._block = block

    def _values(self) -> np.ndarray:
        with self._block.get_lock():
            return np.array(self._block.get_obj(), float)

    def object_pose(self) -> RigidTransform:
        from dexdrake.systems.station import pose_from_vector

        return pose_from_vector(self._values()[:7])

    @property
    def time(self) -> float:
        return float(self._values()[7])

    def stats(self) -> dict[str, float]:
        return dict(zip(STATS, self._values()[8:].tolist()))


class _Publisher:
    """The world process's side of the block: `write()` publishes the object's pose, and
    the world's step statistics when they are STATS_PERIOD_S old; `run` calls it every
    PUBLISH_PERIOD_S until `stop` is set (the publisher thread)."""

    def __init__(self, world, block) -> None:
        self.world, self.block = world, block
        self._stats, self._stats_due = np.zeros(len(STATS)), 0.0

    def write(self) -> None:
        from dexdrake.systems.station import pose_vector

        if self.world.time >= self._stats_due:
            s = self.world.stats()
            self._stats = np.nan_to_num(np.array([s[name] for name in STATS], float))
            self._stats_due = self.world.time + STATS_PERIOD_S
        values = np.concatenate([pose_vector(self.world.object_pose()), [self.world.time], self._stats])
        with self.block.get_lock():
            self.block[:] = values.tolist()

    def run(self, stop: threading.Event) -> None:
        while not stop.wait(PUBLISH_PERIOD_S):
            self.write()


def world_process(scenario: Scenario, block, stack: contextlib.ExitStack) -> tuple[int, Callable[[], dict]]:
    """The world process's factory (hardware/emulator_process.Factory): builds and starts
    the world and its publisher (module docstring); reports the Z1 emulator's port; at the
    end: {"hand": servo and PWM, "arm": FSM state}, as the separate emulators report."""
    from dexdrake.hands.description import load_hand
    from dexdrake.hardware.z1_udp import ArmFSMState
    from dexdrake.systems.station import start_world

    world = start_world(scenario, stack, load_hand(scenario.hand))
    hand, arm = world.hand_emulator, world.arm_emulator
    world.hold_until(lambda: hand.servo_on and arm.fsm != ArmFSMState.PASSIVE)
    publisher, stop = _Publisher(world, block), threading.Event()
    publisher.write()  # a pose in the block before the parent reads it
    thread = threading.Thread(target=publisher.run, args=(stop,), name="world-publisher", daemon=True)
    thread.start()
    stack.callback(thread.join, 1.0)
    stack.callback(stop.set)

    return arm.port, lambda: {"hand": allegro_final(hand), "arm": z1_final(arm)}


@contextlib.contextmanager
def running_world(scenario: Scenario, emulators: Emulators) -> Iterator[Scenario]:
    """Start the world process of an `emulated_world` scenario (module docstring); yields
    the scenario with the ports it serves. `emulators` receives the process ("world") and
    the `WorldView` (`.world`)."""
    scenario = resolve_ports(scenario)
    block = multiprocessing.get_context("spawn").Array("d", _SIZE)
    with EmulatorProcess(functools.partial(world_process, scenario, block),
                         scenario.drivers.hand.realtime_priority or 0, name="emulated-world") as process:
        emulators.processes["world"] = process
        emulators.world = WorldView(block)
        arm = scenario.drivers.arm
        yield dc.replace(scenario, drivers=dc.replace(
            scenario.drivers, arm=dc.replace(arm, controller_port=process.report)))


def running_devices(scenario: Scenario, emulators: Emulators) -> contextlib.AbstractContextManager[Scenario]:
    """The emulated devices of an `emulated_process` (emulated_devices.running_emulators) or
    `emulated_world` scenario (running_world), as a context that yields the scenario with
    the ports they use."""
    if scenario.drivers.hand.kind == "emulated_world":
        return running_world(scenario, emulators)
    return running_emulators(scenario, emulators)
