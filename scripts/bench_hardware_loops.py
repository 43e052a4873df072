"""Loop timing of the hardware drivers in the policy's process vs in their own processes.

The devices are emulators in processes of their own (the Allegro firmware emulator on
python-can's `udp_multicast` interface, kept on loopback by hardware/can_bus.py; the Z1
controller emulator over UDP on loopback; free ports). The bench process plays the policy's process: it commands a slow sine to both
drivers every 20 ms (the control period) while a CPU-bound Python thread runs in it. Each
mode runs both drivers together for `--seconds`:

  in   in-process      AllegroHand and Z1Arm threads in the bench process (one GIL with the load)
  out  out-of-process  each driver in its own process (hardware/driver_process.DriverProcess)
  rt   own process, RT the same, its threads SCHED_FIFO (`--priority`; ProcessConfig.realtime_priority)
  stream               no driver: a listener process (at `--priority`) times the emulator's
                       3 ms position stream, the floor any CAN loop period sits on

and prints per mode: the CAN PD loop's period p50/p99/max (ms) and its trips (faults latched;
each is counted, then reset), the Z1 loop's rate (Hz), period p99/max and trips, and each
mode's ratio to the first. A trip here is false: the emulators never fault. The emulators
run SCHED_FIFO (`--emulator-priority`): a device has CPUs of its own, so the host's load
must not slow the device side of the measurement.
`--load-procs N` adds N busy background processes; the machine's 1-minute load average is
sampled during each run and printed with the figures. Period statistics come from the
drivers' windows (the last 20000 cycles: 60 s of CAN, 40 s of Z1), read every 20 s; the
worst window's p99 and max are printed.

    .venv/bin/python scripts/bench_hardware_loops.py [--seconds 60] [--load-procs 2] [--modes in,out,rt,stream]
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import multiprocessing
import os
import signal
import socket
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from dexdrake.hardware.allegro_can import AllegroConfig, AllegroHand
from dexdrake.hardware.allegro_emulator import EmulatorConfig
from dexdrake.hardware.allegro_can import default_joint_limits as hand_limits
from dexdrake.hardware.can_bus import open_can_bus
from dexdrake.hardware.driver_process import (
    DriverProcess, ProcessConfig, allegro_on_bus, run_realtime, z1_client,
)
from dexdrake.hardware.emulator_process import EmulatorProcess, allegro_emulator, z1_emulator
from dexdrake.hardware.z1_emulator import Z1EmulatorConfig
from dexdrake.hardware.z1_udp import Z1Arm, Z1Config, free_udp_port
from dexdrake.hardware.z1_udp import default_joint_limits as arm_limits

CONTROL_PERIOD_S = 0.02
STATS_EVERY_S = 20.0


# ----------------------------------------------------------------------------- load
def _burn(stop: threading.Event) -> None:
    """CPU-bound pure Python (holds the GIL but for the interpreter's switch interval)."""
    x = 0
    while not stop.is_set():
        for i in range(10_000):
            x += i * i


def _busy() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    while True:
        pass


# ----------------------------------------------------------------------------- one run
@dataclass
class Run:
    key: str
    mode: str
    can_windows: list[dict] = field(default_factory=list)
    z1_windows: list[dict] = field(default_factory=list)
    trips: dict[str, list[str]] = field(default_factory=lambda: {"can": [], "z1": []})
    loads: list[float] = field(default_factory=list)


MODES = {"in": "in-process", "out": "out-of-process", "rt": "own process, RT", "stream": "stream alone"}


def _listen_main(bus_args: dict, priority: int, seconds: float, conn) -> None:
    """Ask the emulator for its 3 ms position stream and time the last finger's frames
    (SCHED_FIFO at `priority` with its memory locked, no driver): the device side's own jitter."""
    from dexdrake.hardware.allegro_can import Msg, SetPeriod, can_id, encode
    from dexdrake.hardware.safety import period_stats

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if priority:
        run_realtime(priority)
    bus = open_can_bus(bus_args)
    try:
        bus.send(encode(SetPeriod(3, 0, 0)))
        times, end = [], time.monotonic() + seconds
        while time.monotonic() < end:
            msg = bus.recv(0.1)
            if msg is not None and msg.arbitration_id == can_id(Msg.POSITION + 3):
                times.append(time.monotonic())
        bus.send(encode(SetPeriod(0, 0, 0)))
    finally:
        bus.shutdown()
    conn.send(period_stats(times))


def stream_alone(priority: int, seconds: float, bus_args: dict) -> Run:
    """The emulator's position stream as a bare listener process hears it (no driver)."""
    run = Run("stream", MODES["stream"])
    ctx = multiprocessing.get_context("spawn")
    conn, child = ctx.Pipe()
    proc = ctx.Process(target=_listen_main, args=(bus_args, priority, seconds, child), daemon=True)
    proc.start()
    run.can_windows.append(conn.recv())
    run.loads.append(os.getloadavg()[0])
    proc.join()
    return run


def _drivers(mode: str, priority: int, bus_args: dict, z1_ports: tuple[int, int], stack: contextlib.ExitStack):
    z1_cfg = Z1Config(local_port=z1_ports[1], controller_port=z1_ports[0])
    if mode != "in":
        cfg = ProcessConfig(realtime_priority=priority if mode == "rt" else 0)
        hand = DriverProcess(functools.partial(allegro_on_bus, bus_args, 0, AllegroConfig()), cfg, "Allegro hand")
        arm = DriverProcess(functools.partial(z1_client, z1_cfg), cfg, "Z1 arm")
    else:
        bus = open_can_bus(bus_args)
        stack.callback(bus.shutdown)
        hand, arm = AllegroHand(bus, 0, AllegroConfig()), Z1Arm(z1_cfg)
    stack.enter_context(hand)
    stack.enter_context(arm)
    return hand, arm


def run_mode(mode: str, priority: int, seconds: float, bus_args: dict, z1_ports: tuple[int, int],
             cpu_thread: bool) -> Run:
    """Both drivers for `seconds` under the bench's load, commanded every control period."""
    run = Run(mode, MODES[mode])
    (hlo, hhi), (alo, ahi) = hand_limits(), arm_limits()
    stop = threading.Event()
    with contextlib.ExitStack() as stack:
        hand, arm = _drivers(mode, priority, bus_args, z1_ports, stack)
        if cpu_thread:
            burner = threading.Thread(target=_burn, args=(stop,), daemon=True)
            burner.start()
            stack.callback(burner.join)
            stack.callback(stop.set)
        last_fault: dict[str, str | None] = {"can": None, "z1": None}
        t0 = next_stats = time.monotonic()
        while (t := time.monotonic() - t0) < seconds:
            s = 0.3 * np.sin(2 * np.pi * 0.25 * t)
            hand.command_positions((hlo + hhi) / 2 + s * (hhi - hlo) / 2)
            arm.command_positions((alo + ahi) / 2 + s * (ahi - alo) / 2)
            for name, dev in (("can", hand), ("z1", arm)):
                fault = dev.state().fault
                if fault is not None and fault != last_fault[name]:  # a reset is asynchronous
                    run.trips[name].append(f"{t:.1f} s: {fault}")
                    dev.reset_fault()
                last_fault[name] = fault
            if time.monotonic() >= next_stats + STATS_EVERY_S:
                next_stats = time.monotonic()
                _window(run, hand, arm)
            time.sleep(CONTROL_PERIOD_S)
        _window(run, hand, arm)
    return run


def _window(run: Run, hand, arm) -> None:
    run.can_windows.append(hand.stats())
    run.z1_windows.append(arm.stats())
    run.loads.append(os.getloadavg()[0])


# ----------------------------------------------------------------------------- report
def _figures(run: Run) -> dict[str, float]:
    worst = lambda windows, key: max((w[key] for w in windows), default=float("nan"))  # noqa: E731
    return {"can_p50": float(np.median([w["p50_ms"] for w in run.can_windows])),
            "can_p99": worst(run.can_windows, "p99_ms"), "can_max": worst(run.can_windows, "max_ms"),
            "can_trips": len(run.trips["can"]),
            "z1_rate": min((w["rate_hz"] for w in run.z1_windows), default=float("nan")),
            "z1_p99": worst(run.z1_windows, "p99_ms"), "z1_max": worst(run.z1_windows, "max_ms"),
            "z1_trips": len(run.trips["z1"])}


def report(runs: list[Run], seconds: float) -> None:
    print(f"\n{'mode':<16}{'load':>11}{'CAN p50':>9}{'p99':>8}{'max':>8}{'trips':>7}"
          f"{'Z1 rate':>10}{'p99':>8}{'max':>8}{'trips':>7}   ({seconds:.0f} s each; ms, Hz)")
    figs = [_figures(r) for r in runs]
    for run, f in zip(runs, figs):
        load = f"{min(run.loads):.1f}-{max(run.loads):.1f}"
        print(f"{run.mode:<16}{load:>11}{f['can_p50']:9.2f}{f['can_p99']:8.2f}{f['can_max']:8.1f}"
              f"{f['can_trips']:7d}{f['z1_rate']:10.1f}{f['z1_p99']:8.2f}{f['z1_max']:8.1f}{f['z1_trips']:7d}")
    a = figs[0]
    for run, b in zip(runs[1:], figs[1:]):  # against the first mode, measured in the same run
        ratio = lambda key: b[key] / a[key] if a[key] else float("nan")  # noqa: E731
        name = f"{run.key} / {runs[0].key}"
        print(f"{name:<16}{'':>11}{ratio('can_p50'):9.2f}{ratio('can_p99'):8.2f}{ratio('can_max'):8.2f}"
              f"{'':>7}{ratio('z1_rate'):10.3f}{ratio('z1_p99'):8.2f}{ratio('z1_max'):8.2f}")
    for run in runs:
        for name, trips in run.trips.items():
            for trip in trips[:5]:
                print(f"  {run.mode} {name} trip at {trip}")
    print("targets (issue): CAN p99 <= 5 ms, no false trip; Z1 holds 500 Hz")


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", 0))
        return s.getsockname()[1]


def main() -> None:
    from can.interfaces.udp_multicast import UdpMulticastBus

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="run time per mode")
    parser.add_argument("--load-procs", type=int, default=0, help="busy background processes to add")
    parser.add_argument("--no-cpu-thread", action="store_true", help="no CPU-bound thread in the bench process")
    parser.add_argument("--modes", default="in,out,rt,stream",
                        help="comma-separated: in (in-process), out (own process), rt (own process, "
                             "SCHED_FIFO), stream (the emulator's stream alone, at --priority)")
    parser.add_argument("--priority", type=int, default=50, help="SCHED_FIFO priority of mode rt's drivers")
    parser.add_argument("--emulator-priority", type=int, default=60,
                        help="SCHED_FIFO priority of the emulators (devices have CPUs of their own); 0: normal")
    args = parser.parse_args()
    modes = args.modes.split(",")
    if not modes or any(m not in MODES for m in modes):
        parser.error(f"--modes: comma-separated {', '.join(MODES)}, got {args.modes!r}")
    print(f"command: bench_hardware_loops.py --seconds {args.seconds:g} --load-procs {args.load_procs}"
          f"{' --no-cpu-thread' if args.no_cpu_thread else ''} --modes {args.modes} "
          f"--priority {args.priority} --emulator-priority {args.emulator_priority}")
    print(f"machine: {os.cpu_count()} CPUs, 1-min load average {os.getloadavg()[0]:.2f} before the run; "
          f"CPU-bound thread in the policy's process: {'no' if args.no_cpu_thread else 'yes'}")
    bus_args = dict(interface="udp_multicast", channel=UdpMulticastBus.DEFAULT_GROUP_IPv4,
                    port=_free_udp_port(), receive_own_messages=False)
    ctx = multiprocessing.get_context("spawn")
    busy = [ctx.Process(target=_busy, daemon=True) for _ in range(args.load_procs)]
    for proc in busy:
        proc.start()
    runs = []
    try:
        (hlo, hhi), (alo, ahi) = hand_limits(), arm_limits()
        hand_emulator = functools.partial(allegro_emulator, bus_args, EmulatorConfig(lower=hlo, upper=hhi))
        client = free_udp_port()  # the controller sends every state to the client's fixed port
        arm_emulator = functools.partial(z1_emulator, Z1EmulatorConfig(port=0, client_port=client, lower=alo, upper=ahi))
        with EmulatorProcess(hand_emulator, args.emulator_priority), \
                EmulatorProcess(arm_emulator, args.emulator_priority) as arm_process:
            z1_ports = (arm_process.report, client)
            for mode in modes:
                runs.append(stream_alone(args.priority, args.seconds, bus_args) if mode == "stream" else
                            run_mode(mode, args.priority, args.seconds, bus_args, z1_ports, not args.no_cpu_thread))
    finally:
        for proc in busy:
            proc.kill()
            proc.join()
    report(runs, args.seconds)


if __name__ == "__main__":
    main()
