"""Soak a hardware-in-the-loop station: a long run reporting missed deadlines, loop-period
percentiles, faults and memory at start and end.

The station of `--config` (camera "sim", the world's true object pose, unless --perception)
runs a gentle sine controller around the pre-grasp pose (every finger joint +-0.15 rad at
0.2 Hz, every arm joint +-0.05 rad at 0.05 Hz) or, with --policy, the scenario's own
controller, for one episode of `--minutes` of control. The scenario's mode picks the world:
  hil (default: the packaged hil scenario): every device on the world's simulated clock, in
      this process; the episode loop on that clock.
  real with `emulated_world` drivers (configs/real_emulated_world.yaml): the wall-clock
      world in its own process (systems/emulated_world.py), each driver in its own, and the
      episode supervised as `dexdrake real` runs it (systems/real_episode.py: the move to
      the start pose, the episode in real time, the retreat, the safe stop).
      `--realtime-priority` replaces the scenario's SCHED_FIFO priority of the driver and
      world processes (0: normal scheduling).
`--wall-minutes` bounds the run's wall time as well (a loaded host runs the hil world slower
than real time, and starves the control loop of either): the run then ends at the control
step where it is reached (safe stop, no retreat), and says how much it covered.
Sampled every `--sample-s` of control or wall time:
  CAN: the Allegro PD loop's cycle times (the devices' clock; deadline 2 x the 3 ms period);
  Z1: the UDP client's tick times (the devices' clock; deadline 2 x 2 ms);
  control: hil: the wall time of each control step (deadline: the control period, i.e.
           real time) and its period on the simulated clock; real: the wall period of each
           control step (deadline 2 x the control period);
  world: hil: the wall time of each plant step; real: the world process's step statistics
         (the worst sampled); the late hand replies and arm commands it counted;
  memory: resident set size (VmRSS) of this process.
A fault ends the run and is reported.

    .venv/bin/python scripts/soak_hil.py --minutes 10 [--wall-minutes 40] [--config hil] [--policy]
    .venv/bin/python scripts/soak_hil.py --config real_emulated_world --minutes 10 [--realtime-priority 0]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from dataclasses import dataclass

import numpy as np

from dexdrake.errors import DexdrakeError


def rss_mb() -> float:
    """Resident set size of this process (MiB), from /proc/self/status."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


class _Periods:
    """Periods between loop times (a driver's `loop_times`, a world's step times), kept
    incrementally: `take` adds the times after the last one taken."""

    def __init__(self, deadline_s: float):
        self.deadline_s = deadline_s
        self.last = -np.inf
        self.periods: list[np.ndarray] = []  # float64 chunks: the monitor adds little to RSS

    def take(self, stamps) -> None:
        new = [t for t in list(stamps) if t > self.last]
        if not new:
            return
        times = ([self.last] if np.isfinite(self.last) else []) + new
        self.periods.append(np.diff(times))
        self.last = new[-1]

    def report(self) -> dict:
        p = np.concatenate(self.periods) * 1e3 if self.periods else np.zeros(0)
        if p.size == 0:
            return {"n": 0}
        return {"n": int(p.size), "p50_ms": float(np.percentile(p, 50)),
                "p90_ms": float(np.percentile(p, 90)), "p99_ms": float(np.percentile(p, 99)),
                "max_ms": float(p.max()), "missed": int(np.sum(p > self.deadline_s * 1e3))}


class WallTimeUp(Exception):
    """The soak's wall-time bound was reached (ends the run; not a fault)."""


class SoakMonitor:
    """An episode logger (the calls the episode loop makes on systems/rerun_logger.RerunLogger:
    `log_station_step`, `log_fault`): samples the loops every `sample_s` of control or of
    wall time, whichever comes first (the drivers keep their last 20000 loop times: 40 s of
    Z1 ticks), and ends the run (WallTimeUp) once `wall_limit_s` of wall time have passed.
    The drivers' loop times come from the drivers (`loop_times`, in this process or through
    their process's proxy); the world's, from a simulated-clock HilWorld's step times or, for
    the wall-clock world in its process, from its statistics."""

    def __init__(self, station, sample_s: float, wall_limit_s: float = np.inf):
        self.station = station
        self.wall_end = time.perf_counter() + wall_limit_s
        self.sample_s = sample_s
        self.every = max(1, round(sample_s / station.scenario.control_period))
        self.next_sample = time.perf_counter() + sample_s  # wall time
        self.can = _Periods(2 * 0.003)
        self.z1 = _Periods(2 * 0.002)
        self.world = _Periods(np.inf)
        self.world_stats: list[dict] = []  # the wall-clock world's, as sampled
        self.step_walls: list[float] = []  # each control step's wall time (hil) or period (real)
        self.steps = 0
        self._wall = None  # the wall time of the episode's last step (None: no step yet)
        self.rss: list[tuple[float, float]] = [(0.0, rss_mb())]

    def sample(self) -> None:
        self.next_sample = time.perf_counter() + self.sample_s
        d, world = self.station.devices, self.station.world
        self.can.take(d["allegro"].loop_times(self.can.last))
        self.z1.take(d["z1"].loop_times(self.z1.last))
        if self.station.mode == "hil":
            self.world.take(world._step_walls)
        else:
            self.world_stats.append(world.stats())

    def log_station_step(self, t, hand_state, command, object_pose, stats, world_pose) -> None:
        now = time.perf_counter()
        if self._wall is not None:
            self.step_walls.append(now - self._wall)
        self._wall = now
        self.steps += 1
        if self.steps % self.every == 0 or now >= self.next_sample:
            self.sample()
            self.rss.append((t, rss_mb()))
        if now > self.wall_end:
            raise WallTimeUp(f"wall-time limit reached at t = {t:.1f} s of control")

    def log_fault(self, text: str) -> None:
        pass

    def close(self) -> None:
        self.sample()
        self.rss.append((float("nan"), rss_mb()))


def sine_controller(hand, q0: np.ndarray):
    n_arm = len(hand.arm_joints)
    lo, hi = hand.joint_limits()
    amp = np.where(np.arange(len(q0)) < n_arm, 0.05, 0.15)
    freq = np.where(np.arange(len(q0)) < n_arm, 0.05, 0.2)

    def controller(t, hand_state, object_pose):
        return np.clip(q0 + amp * np.sin(2 * np.pi * freq * t), lo, hi)

    return controller


@dataclass
class Soaked:
    """What a soak ran: control steps done, the fault that ended it (hil: the episode's;
    real: with the supervised sequence's phase), why it ended early, and the controller's
    statistics (None when it ended early)."""

    steps: int
    fault: str | None
    note: str
    policy: dict | None


def soak(station, controller, steps: int, monitor: SoakMonitor) -> Soaked:
    """One episode of `steps` control periods: hil, the episode loop on the simulated clock;
    real (the wall-clock world), `dexdrake real`'s supervised sequence around it."""
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.real_episode import run_supervised

    try:
        if station.mode == "hil":
            result = run_station_episode(station, controller, steps, logger=monitor)
            return Soaked(result.steps, result.fault, "", result.stats["policy"])
        out = run_supervised(station, controller, steps, monitor, say=lambda line: None)
    except WallTimeUp as err:  # the station's exit stops the devices as after any episode
        return Soaked(monitor.steps, None, f" ({err})", None)
    return Soaked(monitor.steps, None if out.fault is None else f"{out.phase}: {out.fault}", "",
                  None if out.episode is None else out.episode.stats["policy"])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="hil", help="a hil scenario, or a real one with emulated_world drivers")
    parser.add_argument("--minutes", type=float, default=10.0,
                        help="minutes of control (hil: simulated; real: on the wall clock)")
    parser.add_argument("--policy", action="store_true", help="the scenario's controller, not the sine")
    parser.add_argument("--perception", action="store_true", help="keep the scenario's camera")
    parser.add_argument("--wall-minutes", type=float, default=np.inf,
                        help="end the run after this much wall time even if --minutes is not reached")
    parser.add_argument("--sample-s", type=float, default=5.0)
    parser.add_argument("--realtime-priority", type=int,
                        help="real: SCHED_FIFO priority of the driver and world processes, 0: normal "
                             "scheduling (default: the scenario's)")
    args = parser.parse_args()

    from dexdrake.systems.controllers import make_controller
    from dexdrake.systems.emulated_devices import Emulators
    from dexdrake.systems.emulated_world import running_world
    from dexdrake.systems.scenario import load_scenario
    from dexdrake.systems.station import make_station

    try:
        scenario = load_scenario(args.config)
    except DexdrakeError as err:
        parser.error(str(err))
    wall_clock = scenario.mode == "real"
    if not (scenario.mode == "hil" or (wall_clock and scenario.drivers.hand.kind == "emulated_world")):
        parser.error(f"{args.config}: a {scenario.mode} scenario with {scenario.drivers.hand.kind} drivers; "
                     "soak a hil scenario or a real one with emulated_world drivers (configs/real_emulated_world.yaml)")
    if not args.perception:
        scenario.drivers.camera.kind = "sim"
    if args.realtime_priority is not None:
        if not 0 <= args.realtime_priority <= 99:
            parser.error(f"--realtime-priority must be 0..99, got {args.realtime_priority}")
        for entry in (scenario.drivers.hand, scenario.drivers.arm):
            entry.realtime_priority = args.realtime_priority or None
    steps = int(round(args.minutes * 60 / scenario.control_period))
    controller = make_controller(scenario)[0] if args.policy else None
    rss0 = rss_mb()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    with contextlib.ExitStack() as stack:
        world = None
        if wall_clock:
            emulators = Emulators()
            scenario = stack.enter_context(running_world(scenario, emulators))
            world = emulators.world
        station = stack.enter_context(make_station(scenario, world=world))
        if controller is None:
            controller = sine_controller(station.hand, station.hand.pregrasp_vector())
        monitor = SoakMonitor(station, args.sample_s, args.wall_minutes * 60)
        monitor.rss[0] = (0.0, rss0)
        run = soak(station, controller, steps, monitor)
        monitor.close()
        world = station.world.stats()
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    walls = np.asarray(monitor.step_walls) * 1e3
    where = "in a supervised episode on the wall-clock emulated world" if wall_clock else "on the simulated clock"
    print(f"soak: {scenario.name} {args.minutes:g} min of control ({run.steps}/{steps} control steps) {where}, "
          f"controller {'scenario' if args.policy else 'sine'}; wall {wall:.0f} s, CPU "
          f"{'of this process ' if wall_clock else ''}{cpu:.0f} s, real-time factor {world['real_time_factor']:.2f}")
    print(f"  fault: {run.fault or 'none'}{run.note}")
    clock = "wall clock" if wall_clock else "sim clock"
    for name, per in ((f"CAN PD loop ({clock}, deadline 6 ms)", monitor.can),
                      (f"Z1 UDP loop ({clock}, deadline 4 ms)", monitor.z1)):
        r = per.report()
        print(f"  {name}: no periods" if r["n"] == 0 else
              f"  {name}: {r['n']} periods, p50 {r['p50_ms']:.2f} p90 {r['p90_ms']:.2f} p99 "
              f"{r['p99_ms']:.2f} max {r['max_ms']:.2f} ms, missed {r['missed']}")
    period_ms = scenario.control_period * 1e3
    deadline_ms = 2 * period_ms if wall_clock else period_ms
    policy = run.policy
    times = ("none timed" if walls.size == 0 else
             f"p50 {np.percentile(walls, 50):.1f} p90 {np.percentile(walls, 90):.1f} p99 "
             f"{np.percentile(walls, 99):.1f} max {walls.max():.1f} ms")
    print(f"  control step ({'wall period' if wall_clock else 'wall'}, deadline {deadline_ms:.0f} ms): {times}, "
          f"missed {int(np.sum(walls > deadline_ms))} of {walls.size}"
          + ("" if policy is None else ("" if wall_clock else f"; sim-clock period p99 {policy['p99_ms']:.2f} ms")
             + f", non-finite held {policy['non_finite']}, clipped {policy['clipped']}"))
    if wall_clock:
        worst = {k: max(s[k] for s in monitor.world_stats) for k in ("step_p99_ms", "step_max_ms", "lag_s")}
        print(f"  world step (wall, its process; worst of {len(monitor.world_stats)} samples of its window): "
              f"p99 {worst['step_p99_ms']:.2f} max {worst['step_max_ms']:.2f} ms, lag behind the wall clock "
              f"up to {worst['lag_s'] * 1e3:.0f} ms; ", end="")
    else:
        r = monitor.world.report()
        print(f"  world step (wall): p50 {r['p50_ms']:.2f} p99 {r['p99_ms']:.2f} max {r['max_ms']:.2f} ms; ", end="")
    print(f"late hand replies {world['late_replies']:.0f}, late arm commands {world['late_arm_commands']:.0f}")
    rss = [m for _, m in monitor.rss]
    print(f"  memory (RSS): start {rss[0]:.0f} MiB, after set-up {rss[1]:.0f} MiB, end {rss[-1]:.0f} MiB "
          f"(growth after set-up {rss[-1] - rss[1]:+.1f} MiB over {len(rss) - 2} samples)")
    print(f"  load average {os.getloadavg()[0]:.1f}")
    print(f"command: .venv/bin/python scripts/soak_hil.py --config {args.config} --minutes {args.minutes:g}"
          + (f" --wall-minutes {args.wall_minutes:g}" if np.isfinite(args.wall_minutes) else "")
          + ("" if args.realtime_priority is None else f" --realtime-priority {args.realtime_priority}")
          + (" --policy" if args.policy else "") + (" --perception" if args.perception else ""))
    return 1 if run.fault else 0


if __name__ == "__main__":
    sys.exit(main())
