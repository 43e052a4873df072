"""Device emulators in processes of their own, in real time on real transports.

`EmulatorProcess(factory)` spawns a child that builds an emulator with `factory(stack)`
(starting it in its own thread, registering its stop and its transport's closing on
`stack`), reports what a client needs to reach it (the Z1 emulator's port) and serves
until `stop()` or until the parent is gone (its pipe closes). On `stop()` the child sends
the emulated device's last state (`final`: the hand's servo and PWM, the arm's FSM state),
read before the emulator stops: what the device was left in. The child ignores SIGINT (a
terminal's Ctrl-C is the parent's to handle) and stops on SIGTERM. With `realtime_priority`
its threads run SCHED_FIFO and its memory is locked (`driver_process.run_realtime`): a device
has CPUs and memory of its own, so the host's load must not slow the device side of a measurement. Once built, the child freezes its heap (as a driver's
process does: `driver_process.freeze_heap`), so that the garbage collector does not stop
the emulator longer than a device would ever pause.

Factories: `allegro_emulator` (the firmware emulator on a python-can bus that crosses
processes, e.g. `udp_multicast`), `z1_emulator` (the controller emulator on a UDP port).
"""

from __future__ import annotations

import contextlib
import functools
import multiprocessing
import signal
import threading
from collections.abc import Callable
from typing import Any

from dexdrake.hardware.driver_process import freeze_heap, run_realtime
from dexdrake.hardware.safety import HardwareError

# builds and starts an emulator; returns (what to report, a function of the device's state at the end)
Factory = Callable[[contextlib.ExitStack], tuple[Any, Callable[[], dict]]]


def _child_main(factory: Factory, conn, realtime_priority: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    terminated = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: terminated.set())
    with contextlib.ExitStack() as stack:
        try:
            if realtime_priority:
                run_realtime(realtime_priority)
            report, final = factory(stack)
            freeze_heap()
        except Exception as err:  # the parent raises it as a HardwareError
            conn.send(("error", f"{type(err).__name__}: {err}"))
            return
        conn.send(("ready", report))
        while not terminated.is_set():
            try:
                if conn.poll(0.1):
                    conn.recv()  # anything: stop
                    conn.send(("final", final()))
                    return
            except (EOFError, OSError):  # the parent is gone
                return


class EmulatorProcess:
    """An emulator in its own process (module docstring); a context manager. `report` is
    what the factory reported (e.g. the Z1 emulator's port); `final`, after `stop()`, the
    device's state at the end (None if the child could not tell)."""

    def __init__(self, factory: Factory, realtime_priority: int = 0, start_timeout_s: float = 30.0,
                 name: str = "emulator"):
        self.factory, self.realtime_priority, self.start_timeout_s = factory, realtime_priority, start_timeout_s
        self.name = name
        self.report: Any = None
        self.final: dict | None = None
        self._process: multiprocessing.process.BaseProcess | None = None
        self._conn = None

    @property
    def pid(self) -> int | None:
        """The emulator process's id (None before start)."""
        return None if self._process is None else self._process.pid

    @property
    def exitcode(self) -> int | None:
        """The emulator process's exit code (None before start and while it runs)."""
        return None if self._process is None else self._process.exitcode

    def start(self) -> Any:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(target=_child_main, args=(self.factory, child, self.realtime_priority),
                                    name=f"dexdrake-{self.name}", daemon=True)
        self._process.start()
        child.close()
        reply = self._conn.recv() if self._conn.poll(self.start_timeout_s) else None
        if reply is None or reply[0] != "ready":
            self.stop()
            raise HardwareError(f"emulator process did not start: {reply[1] if reply else 'no answer'}")
        self.report = reply[1]
        return self.report

    def stop(self) -> None:
        """Ask the child to stop its emulator and exit (SIGKILL after 5 s)."""
        if self._conn is not None:
            with contextlib.suppress(OSError, EOFError):  # a child that is gone reports nothing
                self._conn.send("stop")
                if self._conn.poll(5.0):
                    kind, value = self._conn.recv()
                    self.final = value if kind == "final" else None
        if self._process is not None:
            self._process.join(5.0)
            if self._process.is_alive():
                self._process.kill()
                self._process.join()
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def __enter__(self) -> EmulatorProcess:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def allegro_emulator(bus: dict, config, stack: contextlib.ExitStack) -> tuple[None, Callable[[], dict]]:
    """The Allegro firmware emulator (EmulatorConfig `config`) on the python-can bus of
    `bus` (can.Bus keyword arguments, opened by `can_bus.open_can_bus`), started; reports
    nothing; at the end: "servo_on", "max_abs_pwm" (the PWM it applies), "frame_errors" (the
    frames it dropped, by kind), "running" (its thread had not died)."""
    from dexdrake.hardware.allegro_emulator import AllegroEmulator
    from dexdrake.hardware.can_bus import open_can_bus

    opened = open_can_bus(bus)
    stack.callback(opened.shutdown)
    emulator = stack.enter_context(AllegroEmulator(opened, config=config))
    return None, functools.partial(allegro_final, emulator)


def allegro_final(emulator) -> dict:
    """What an Allegro emulator's device was left in: "servo_on", "max_abs_pwm" (the PWM it
    applies), "frame_errors" (bad frames by kind), "running" (its thread still alive)."""
    return {"servo_on": emulator.servo_on, "max_abs_pwm": float(abs(emulator.pwm).max()),
            "frame_errors": dict(emulator.frame_errors), "running": emulator.running}


def z1_emulator(config, stack: contextlib.ExitStack) -> tuple[int, Callable[[], dict]]:
    """The Z1 controller emulator (Z1EmulatorConfig `config`), started; reports its port; at
    the end: "fsm" (the controller's state name), "packet_errors" (the commands it dropped,
    by kind), "running" (its thread had not died)."""
    from dexdrake.hardware.z1_emulator import Z1Emulator

    emulator = stack.enter_context(Z1Emulator(config))
    return emulator.port, functools.partial(z1_final, emulator)


def z1_final(emulator) -> dict:
    """What a Z1 emulator's controller was left in: "fsm" (its state's name), "packet_errors"
    (bad datagrams by kind), "running" (its thread still alive)."""
    return {"fsm": emulator.fsm.name, "packet_errors": dict(emulator.packet_errors), "running": emulator.running}
