"""A hardware driver run in its own process, behind a proxy with the driver's public API.

The Allegro PD loop and the Z1 client loop are Python threads; in the process that runs the
diagram, the policy and perception they share one GIL with that work and are starved by
it. `DriverProcess(factory)` starts a child with the multiprocessing "spawn" context; the
child calls `factory(stack)` to build the driver (opening its bus or socket there, and
registering their closing on `stack`), starts it and supervises it every `poll_period_s`:

  parent -> child  shared memory: the joint target (seqlock: sequence number, values) and
                   the parent's heartbeat (CLOCK_MONOTONIC, shared by all processes),
                   written every `heartbeat_period_s` by a thread of the proxy; a stop flag.
                   Pipe: requests (stats, loop_times, stop; reset_fault with the sequence number of the
                   last target written before it: that target is never applied after the
                   reset, whose driver holds the measured position until the next one).
  child -> parent  shared memory: the driver's latest state (seqlock, written by the child);
                   pipe: the fault reason as soon as the driver latches one, replies.

The child runs the driver's safe stop (`driver.stop()`: Allegro zero torque then servo off;
Z1 PASSIVE) and exits when: the parent asks (stop flag or message), the parent's heartbeat
is older than `heartbeat_timeout_s` (a hung or starved parent), the pipe closes (a dead
parent), SIGTERM comes, the driver's loop thread ends or the supervision itself fails. It ignores SIGINT: a Ctrl-C in the terminal reaches the whole
process group, and only the parent decides when the device stops. `stop()` in the parent
cannot be cut short by Ctrl-C: each step is idempotent and an interrupted stop resumes
where it was, then re-raises the interrupt; a child that does not exit in
`stop_timeout_s` gets SIGTERM (its safe stop), then SIGKILL.

With `realtime_priority` the child's threads run SCHED_FIFO: its loops then wait for no
normal process on the machine (the host's load), only for the devices, and its memory is
locked (`run_realtime`), so no page the loops touch is reclaimed and faulted back in. Before the driver
starts, the child freezes its heap (`freeze_heap`): the garbage collector's full passes,
which stop every thread of the process, then walk only what the loops create, not the
imports.

Seqlock: the writer makes the sequence odd, writes, makes it even; a reader copies the
values between two equal even sequence reads. Each side has one writer; CPython stores
each float64 with one aligned 8-byte store, and x86-64 keeps stores in order (TSO).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import dataclasses
import enum
import gc
import math
import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.shared_memory import SharedMemory
from typing import Any

import numpy as np

from dexdrake.hardware.safety import HardwareError, SafeStopContext

MCL_CURRENT, MCL_FUTURE = 1, 2  # mlockall flags (<sys/mman.h>, Linux)

Factory = Callable[[contextlib.ExitStack], Any]  # builds a driver with start/stop/state/...

_CAPACITY = 512  # float64 slots per block (the largest state, Allegro's, takes 82)
_HEARTBEAT, _STOP = 0, 1  # control slots
_CONTROL, _COMMAND, _STATE = 0, 8, 8 + _CAPACITY  # block offsets in the shared array


@dataclass(frozen=True)
class ProcessConfig:
    """How the driver's process runs: the timing of the exchange (s) and its scheduling."""

    poll_period_s: float = 0.002  # child: takes the target and publishes the state this often
    heartbeat_period_s: float = 0.01  # parent: writes its heartbeat this often
    heartbeat_timeout_s: float = 0.5  # child: a heartbeat this old stops the device
    start_timeout_s: float = 30.0  # spawn, imports and the driver's start sequence
    stop_timeout_s: float = 3.0  # then SIGTERM, then SIGKILL
    # child: after a reset request the fault it had is not reported again unless still
    # latched this long after (the driver's loop thread clears it on its next pass)
    reset_grace_s: float = 0.2
    # 1..99: the child's threads run SCHED_FIFO at this priority (needs CAP_SYS_NICE or an
    # rtprio limit, `ulimit -r`; refused otherwise), so that no normal process delays them;
    # 0: normal scheduling
    realtime_priority: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.realtime_priority <= 99:
            raise HardwareError(f"realtime_priority must be 0..99, got {self.realtime_priority}")
        if not (math.isfinite(self.heartbeat_timeout_s) and self.heartbeat_timeout_s > self.heartbeat_period_s > 0):
            raise HardwareError(f"heartbeat_timeout_s must be a finite time longer than the heartbeat's "
                                f"period ({self.heartbeat_period_s} s), got {self.heartbeat_timeout_s}")


def run_realtime(priority: int) -> None:
    """Run the calling thread, and the threads it starts later, SCHED_FIFO at `priority`
    (1..99), with every page of the process locked in RAM now and later (mlockall MCL_CURRENT |
    MCL_FUTURE: the kernel's reclaim never drops a page the loops touch, which a fault would
    bring back from disk while a loop waits); HardwareError saying what is missing when the
    system refuses either."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as err:
        raise HardwareError(f"cannot run at SCHED_FIFO priority {priority}: {err.strerror} (needs "
                            f"CAP_SYS_NICE or `ulimit -r` >= {priority})") from None
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
        raise HardwareError(f"cannot lock the process's memory: {os.strerror(ctypes.get_errno())} (needs "
                            "CAP_IPC_LOCK or `ulimit -l unlimited`)")


def freeze_heap() -> None:
    """Collect, then move every object alive now to the garbage collector's permanent
    generation: a full collection stops all threads of the process while it walks the
    tracked objects (the ~60k of numpy, python-can and the project's modules take ~20 ms, more
    on a loaded machine), and after this it walks only those created later."""
    gc.collect()
    gc.freeze()


# ----------------------------------------------------------------------------- seqlock
def _write(block: np.ndarray, values: np.ndarray) -> None:
    """Publish `values` in `block` ([sequence, values...]); one writer per block."""
    block[0] += 1.0
    block[1: 1 + values.size] = values
    block[0] += 1.0


def _read(block: np.ndarray, size: int, tries: int = 1000) -> tuple[float, np.ndarray] | None:
    """(sequence, values) of a consistent snapshot of `block`, retried while it is being
    written; None after `tries` (a writer that died in the middle of a write)."""
    for _ in range(tries):
        seq = block[0]
        if seq % 2 == 0:
            values = block[1: 1 + size].copy()
            if block[0] == seq:
                return seq, values
        time.sleep(0)
    return None


# ----------------------------------------------------------------------------- state codec
class StateCodec:
    """Flattens a driver's frozen state dataclass into float64s and back, shaped after a
    template state: arrays keep their size, enums and ints their type (NaN is None), and
    the `fault` field travels by pipe, not here."""

    def __init__(self, template: Any):
        self.template = template
        self.fields = [f.name for f in dataclasses.fields(template) if f.name != "fault"]
        self.sizes = [np.size(getattr(template, name)) for name in self.fields]
        self.size = int(sum(self.sizes))
        if self.size > _CAPACITY - 1:
            raise HardwareError(f"driver state of {self.size} values exceeds {_CAPACITY - 1}")

    def encode(self, state: Any) -> np.ndarray:
        return np.concatenate([np.ravel(np.asarray(math.nan if v is None else v, dtype=float))
                               for v in (getattr(state, name) for name in self.fields)])

    def decode(self, flat: np.ndarray, fault: str | None) -> Any:
        values, i = {}, 0
        for name, size in zip(self.fields, self.sizes):
            kind = getattr(self.template, name)
            chunk = flat[i: i + size]
            i += size
            if isinstance(kind, np.ndarray):
                values[name] = chunk.copy()
            elif isinstance(kind, enum.Enum):
                values[name] = type(kind)(int(chunk[0]))
            elif kind is None or isinstance(kind, int):
                values[name] = None if math.isnan(chunk[0]) else int(chunk[0])
            else:
                values[name] = float(chunk[0])
        return dataclasses.replace(self.template, fault=fault, **values)


# ----------------------------------------------------------------------------- child
def _child_main(factory: Factory, conn: multiprocessing.connection.Connection, shm_name: str,
                config: ProcessConfig) -> None:
    """The driver's process: build, start, supervise, safe stop (see the module docstring)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    terminated = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: terminated.set())
    shm = SharedMemory(shm_name)
    try:
        buf = np.ndarray((_STATE + _CAPACITY,), dtype=np.float64, buffer=shm.buf)
        fault, stats = _run_driver(factory, conn, buf, config, terminated)
        with contextlib.suppress(OSError):
            conn.send(("stopped", fault, stats))
    finally:
        del buf
        shm.close()


def _run_driver(factory: Factory, conn, buf: np.ndarray, config: ProcessConfig,
                terminated: threading.Event) -> tuple[str | None, dict]:
    """Build and start the driver, supervise it, and leave it in its safe stop (the stack
    closes the driver first, then its bus); (the last fault, the driver's stats)."""
    with contextlib.ExitStack() as stack:
        try:
            if config.realtime_priority:
                run_realtime(config.realtime_priority)
            driver = factory(stack)
            stack.callback(driver.stop)
            freeze_heap()
            driver.start()
            codec = StateCodec(driver.state())
        except Exception as err:  # the parent raises it as a HardwareError
            conn.send(("error", f"{type(err).__name__}: {err}"))
            return None, {}
        _write(buf[_STATE:], codec.encode(codec.template))
        conn.send(("ready", codec.template))
        try:
            reason = _supervise(driver, codec, conn, buf, config, terminated)
        except Exception as err:  # a failing supervisor ends in the safe stop too, reported
            reason = f"driver process failed: {err!r}"
        fault = driver.state().fault
    with contextlib.suppress(OSError):
        if reason is not None and fault is None:
            conn.send(("fault", reason))
    return fault or reason, driver.stats()


def _supervise(driver, codec: StateCodec, conn, buf: np.ndarray, config: ProcessConfig,
               terminated: threading.Event) -> str | None:
    """Exchange targets and states until asked to stop (None) or the parent is lost (why)."""
    n = codec.sizes[codec.fields.index("q")]
    seq_done, fault_sent = 0.0, None
    resetting, reset_until = None, 0.0  # the fault a reset is to clear, and until when it may
    while not terminated.is_set() and buf[_CONTROL + _STOP] == 0:
        try:
            if conn.poll(config.poll_period_s):
                match conn.recv():
                    case "stop":
                        return None
                    case ("reset_fault", seq_written):
                        resetting, reset_until = driver.state().fault, time.monotonic() + config.reset_grace_s
                        driver.reset_fault()
                        fault_sent, seq_done = None, max(seq_done, seq_written)
                    case "stats":
                        conn.send(("stats", driver.stats()))
                    case ("loop_times", since):
                        conn.send(("loop_times", driver.loop_times(since)))
        except (EOFError, OSError):
            return "parent process gone"
        command = _read(buf[_COMMAND:], n)  # None: the parent died writing (its heartbeat tells)
        if command is not None and command[0] != seq_done:
            seq_done = command[0]
            driver.command_positions(command[1])
        state = driver.state()
        _write(buf[_STATE:], codec.encode(state))
        if resetting is not None and (state.fault != resetting or time.monotonic() > reset_until):
            resetting = None  # cleared (or another fault), or still latched after the grace
        if state.fault is not None and state.fault not in (fault_sent, resetting):
            fault_sent = state.fault
            with contextlib.suppress(OSError):
                conn.send(("fault", state.fault))
        if not driver.running:  # its loop thread ended (the driver latched why)
            return state.fault or "driver loop ended"
        age = time.monotonic() - buf[_CONTROL + _HEARTBEAT]
        if age > config.heartbeat_timeout_s:
            return f"parent heartbeat lost for {age * 1e3:.0f} ms"
    return None


# ----------------------------------------------------------------------------- parent
class DriverProcess(SafeStopContext):
    """Proxy of a driver running in its own process (module docstring): `start()`,
    `command_positions(q)`, `state()` (with the fault the child reported), `running`,
    `stats()`, `loop_times(since)`, `reset_fault()`, `stop()`; a context manager like the
    drivers."""

    def __init__(self, factory: Factory, config: ProcessConfig | None = None, name: str = "driver"):
        self.factory, self.config, self.name = factory, config or ProcessConfig(), name
        self._process: multiprocessing.process.BaseProcess | None = None
        self._conn: multiprocessing.connection.Connection | None = None
        self._shm: SharedMemory | None = None
        self._buf: np.ndarray | None = None
        self._codec: StateCodec | None = None
        self._lock = threading.Lock()  # one parent thread at a time on the pipe / command block
        self._beating = threading.Event()
        self._beat: threading.Thread | None = None
        self._fault: str | None = None
        self._final_stats: dict | None = None

    @property
    def pid(self) -> int | None:
        """The driver process's id (None before start)."""
        return None if self._process is None else self._process.pid

    @property
    def exitcode(self) -> int | None:
        """The driver process's exit code (None before start and while it runs)."""
        return None if self._process is None else self._process.exitcode

    # --------------------------------------------------------------- session
    def start(self) -> None:
        """Spawn the driver's process and wait until its driver has started."""
        if self._process is not None:
            raise HardwareError(f"{self.name}: already started")
        self._shm = SharedMemory(create=True, size=8 * (_STATE + _CAPACITY))
        self._buf = np.ndarray((_STATE + _CAPACITY,), dtype=np.float64, buffer=self._shm.buf)
        self._buf[:] = 0.0
        self._buf[_CONTROL + _HEARTBEAT] = time.monotonic()
        self._conn, child_conn = multiprocessing.Pipe()
        ctx = multiprocessing.get_context("spawn")
        self._process = ctx.Process(target=_child_main, name=f"dexdrake-{self.name}", daemon=True,
                                    args=(self.factory, child_conn, self._shm.name, self.config))
        self._beating.set()
        self._beat = threading.Thread(target=self._heartbeat, name=f"{self.name}-heartbeat", daemon=True)
        self._beat.start()
        self._process.start()
        child_conn.close()
        reply = self._await("ready", self.config.start_timeout_s)
        if reply is None or reply[0] != "ready":
            exited = not self._process.is_alive()
            self.stop()
            why = reply[1] if reply is not None else (
                f"it exited with code {self._process.exitcode}" if exited
                else f"no answer within {self.config.start_timeout_s} s")
            raise HardwareError(f"{self.name}: the driver process did not start: {why}")
        self._codec = StateCodec(reply[1])

    def _heartbeat(self) -> None:
        while self._beating.is_set():
            self._buf[_CONTROL + _HEARTBEAT] = time.monotonic()
            time.sleep(self.config.heartbeat_period_s)

    def stop(self) -> None:
        """The child's safe stop, then its exit; repeated Ctrl-C resumes it (re-raised after)."""
        interrupt = None
        while True:
            try:
                self._stop_steps()
                break
            except KeyboardInterrupt as err:
                interrupt = err
        if interrupt is not None:
            raise interrupt

    def _stop_steps(self) -> None:
        """Idempotent: stop flag, heartbeat off, stop request, join (SIGTERM, SIGKILL), free."""
        if self._buf is not None:
            self._buf[_CONTROL + _STOP] = 1.0
        self._beating.clear()
        if self._beat is not None:
            self._beat.join()
        proc = self._process
        if proc is not None:
            if self._conn is not None:
                with contextlib.suppress(OSError, ValueError):
                    self._conn.send("stop")
            deadline = time.monotonic() + self.config.stop_timeout_s
            while proc.is_alive() and time.monotonic() < deadline:
                self._pump(0.05)
            for end in (proc.terminate, proc.kill):
                if proc.is_alive():
                    end()
                    proc.join(self.config.stop_timeout_s)
            self._pump(0.0)
            proc.join()
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._shm is not None:
            self._buf = None
            self._shm.close()
            self._shm.unlink()
            self._shm = None

    @property
    def running(self) -> bool:
        """True while the child process supervises a started driver."""
        return (self._codec is not None and self._final_stats is None and self._buf is not None
                and self._process is not None and self._process.is_alive())

    # --------------------------------------------------------------- pipe
    def _pump(self, timeout: float, want: str | None = None) -> tuple | None:
        """Handle the child's messages for up to `timeout` s; the first message of kind
        `want` is returned (faults and the final report are kept as they come)."""
        deadline = time.monotonic() + timeout
        while self._conn is not None:
            try:
                if not self._conn.poll(max(deadline - time.monotonic(), 0.0)):
                    return None
                msg = self._conn.recv()
            except (EOFError, OSError):
                return None
            if msg[0] == "fault":
                self._fault = self._fault or msg[1]
            elif msg[0] == "stopped":
                self._fault = self._fault or msg[1]
                self._final_stats = msg[2]
            if want is not None and msg[0] in (want, "error"):
                return msg
        return None

    def _await(self, kind: str, timeout: float) -> tuple | None:
        with self._lock:
            return self._pump(timeout, kind)

    # --------------------------------------------------------------- driver API
    def command_positions(self, q: np.ndarray) -> None:
        """Set the joint targets (the driver's order and units); the child's driver clamps,
        rate-limits and may reject them as in-process (its target shows in state())."""
        if not self.running:
            raise HardwareError(f"{self.name}: the driver process is not running")
        q = np.asarray(q, dtype=float).ravel()
        n = self._codec.template.q.size
        if q.size != n:
            raise HardwareError(f"{self.name}: need {n} joint targets, got {q.size}")
        with self._lock:
            _write(self._buf[_COMMAND:], q)

    def state(self) -> Any:
        """The driver's latest state as the child published it, with the fault it reported."""
        if self._codec is None:
            raise HardwareError(f"{self.name}: the driver process was never started")
        with self._lock:
            self._pump(0.0)
        proc = self._process
        if self._fault is None and self._final_stats is None and not proc.is_alive():
            self._fault = f"the driver process exited with code {proc.exitcode} without its report"
        if self._buf is None:  # stopped: the last state is gone with the shared memory
            return dataclasses.replace(self._codec.template, fault=self._fault)
        snapshot = _read(self._buf[_STATE:], self._codec.size)
        if snapshot is None:
            raise HardwareError(f"{self.name}: the driver process stopped in the middle of a state write")
        return self._codec.decode(snapshot[1], self._fault)

    def stats(self) -> dict:
        """The driver's loop statistics (after stop: those of its last run)."""
        if self._final_stats is not None or not self.running:
            return dict(self._final_stats or {})
        with self._lock:
            try:
                self._conn.send("stats")
            except OSError:  # the child ended since `running` was read: its report says why
                self._pump(0.0)
                return dict(self._final_stats or {})
            reply = self._pump(self.config.stop_timeout_s, "stats")
        return {} if reply is None or reply[0] != "stats" else reply[1]

    def loop_times(self, since: float = -math.inf) -> np.ndarray:
        """The child's driver's loop times after `since` (CLOCK_MONOTONIC s, as in every
        process); none once it has stopped."""
        with self._lock:
            if not self.running:
                return np.zeros(0)
            try:
                self._conn.send(("loop_times", since))
            except OSError:  # the child ended since `running` was read
                return np.zeros(0)
            reply = self._pump(self.config.stop_timeout_s, "loop_times")
        return np.zeros(0) if reply is None or reply[0] != "loop_times" else reply[1]

    def reset_fault(self) -> None:
        """Ask the child's driver to clear its latched fault (its own rules apply: the
        drivers re-arm holding the measured position); a target written before this call
        and not yet taken by the child is dropped. The child reports that fault again only
        if it is still latched `reset_grace_s` later."""
        with self._lock:
            self._pump(0.0)  # fault reports already on their way belong to before the reset
            if not self.running:
                raise HardwareError(f"{self.name}: the driver process is not running")
            self._fault = None
            self._conn.send(("reset_fault", float(self._buf[_COMMAND])))


# ----------------------------------------------------------------------------- factories
def allegro_on_bus(bus: dict, device_id: int, config, stack: contextlib.ExitStack):
    """An AllegroHand on the python-can bus of `bus` (can.Bus keyword arguments, opened by
    `can_bus.open_can_bus`) in the calling process (a `DriverProcess` factory through
    functools.partial)."""
    from dexdrake.hardware.allegro_can import AllegroHand
    from dexdrake.hardware.can_bus import open_can_bus

    opened = open_can_bus(bus)
    stack.callback(opened.shutdown)
    return AllegroHand(opened, device_id, config)


def z1_client(config, stack: contextlib.ExitStack):
    """A Z1Arm of `config` (a `DriverProcess` factory through functools.partial; the arm
    opens its socket when started)."""
    from dexdrake.hardware.z1_udp import Z1Arm

    return Z1Arm(config)
