"""Soak the hardware-in-the-loop station: a long run reporting missed deadlines, loop-period
percentiles and memory at start and end.

The HIL station of `--config` (default: the packaged hil scenario, camera "sim" unless --perception)
runs for `--minutes` of simulated time with a gentle sine controller around the pre-grasp
pose (every finger joint +-0.15 rad at 0.2 Hz, every arm joint +-0.05 rad at 0.05 Hz) or,
with --policy, the scenario's own controller. Sampled every `--sample-s` of simulated time:
  CAN: the Allegro PD loop's cycle times (simulated clock; deadline 2 x the 3 ms period);
  Z1: the UDP client's tick times (the world's clock; deadline 2 x 2 ms);
  control: the wall time of each control step (deadline: the control period, i.e. real
           time) and its period on the simulated clock;
  world: the wall time of each plant step and the late hand replies it counted;
  memory: resident set size (VmRSS) of this process.
Faults end the run early and are reported. `--wall-minutes` bounds the run's wall time as
well (a loaded host runs the world slower than real time): the run then ends at the
control step where it is reached, and says how much simulated time it covered.

    .venv/bin/python scripts/soak_hil.py --minutes 10 [--wall-minutes 40] [--config hil] [--policy]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def rss_mb() -> float:
    """Resident set size of this process (MiB), from /proc/self/status."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


class _Periods:
    """Periods between timestamps read from a driver's bounded deque, kept incrementally."""

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
    `log_station_step`, `log_fault`): samples the loops every `sample_s` and ends the run
    (WallTimeUp) once `wall_limit_s` of wall time have passed."""

    def __init__(self, station, sample_s: float, wall_limit_s: float = np.inf):
        self.station = station
        self.wall_end = time.perf_counter() + wall_limit_s
        self.every = max(1, round(sample_s / station.scenario.control_period))
        self.can = _Periods(2 * 0.003)
        self.z1 = _Periods(2 * 0.002)
        self.world = _Periods(np.inf)
        self.step_walls: list[float] = []
        self._wall = time.perf_counter()
        self.rss: list[tuple[float, float]] = [(0.0, rss_mb())]

    def sample(self) -> None:
        d = self.station.devices
        self.can.take(d["allegro"]._stats.cycle_times)
        self.z1.take(d["z1"]._tick_times)
        self.world.take(self.station.world._step_walls)

    def log_station_step(self, t, hand_state, command, object_pose, stats, world_pose) -> None:
        now = time.perf_counter()
        self.step_walls.append(now - self._wall)
        self._wall = now
        if len(self.step_walls) % self.every == 0:
            self.sample()
            self.rss.append((t, rss_mb()))
        if now > self.wall_end:
            raise WallTimeUp(f"wall-time limit reached at t = {t:.1f} s simulated")

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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="hil")
    parser.add_argument("--minutes", type=float, default=10.0, help="simulated minutes")
    parser.add_argument("--policy", action="store_true", help="the scenario's controller, not the sine")
    parser.add_argument("--perception", action="store_true", help="keep the scenario's camera")
    parser.add_argument("--wall-minutes", type=float, default=np.inf,
                        help="end the run after this much wall time even if --minutes is not reached")
    parser.add_argument("--sample-s", type=float, default=5.0)
    args = parser.parse_args()

    from dexdrake.systems.controllers import make_controller
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.scenario import load_scenario
    from dexdrake.systems.station import make_station

    scenario = load_scenario(args.config)
    if not args.perception:
        scenario.drivers.camera.kind = "sim"
    steps = int(round(args.minutes * 60 / scenario.control_period))
    controller = make_controller(scenario)[0] if args.policy else None
    rss0 = rss_mb()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    with make_station(scenario) as station:
        if controller is None:
            controller = sine_controller(station.hand, station.hand.pregrasp_vector())
        monitor = SoakMonitor(station, args.sample_s, args.wall_minutes * 60)
        monitor.rss[0] = (0.0, rss0)
        try:
            result = run_station_episode(station, controller, steps, logger=monitor)
            done, fault, policy, note = result.steps, result.fault, result.stats["policy"], ""
        except WallTimeUp as err:  # the station's exit stops the devices as after any episode
            done, fault, policy, note = len(monitor.step_walls), None, None, f" ({err})"
        monitor.close()
        world = station.world.stats()
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    walls = np.asarray(monitor.step_walls[1:]) * 1e3
    print(f"soak: {scenario.name} {args.minutes:g} simulated min ({done}/{steps} control steps), "
          f"controller {'scenario' if args.policy else 'sine'}; wall {wall:.0f} s, CPU {cpu:.0f} s, "
          f"real-time factor {world['real_time_factor']:.2f}")
    print(f"  fault: {fault or 'none'}{note}")
    for name, per in (("CAN PD loop (sim clock, deadline 6 ms)", monitor.can),
                      ("Z1 UDP loop (sim clock, deadline 4 ms)", monitor.z1)):
        r = per.report()
        print(f"  {name}: {r['n']} periods, p50 {r['p50_ms']:.2f} p90 {r['p90_ms']:.2f} p99 "
              f"{r['p99_ms']:.2f} max {r['max_ms']:.2f} ms, missed {r['missed']}")
    period_ms = scenario.control_period * 1e3
    print(f"  control step (wall, deadline {period_ms:.0f} ms): p50 {np.percentile(walls, 50):.1f} "
          f"p90 {np.percentile(walls, 90):.1f} p99 {np.percentile(walls, 99):.1f} max {walls.max():.1f} ms, "
          f"missed {int(np.sum(walls > period_ms))} of {walls.size}"
          + ("" if policy is None else f"; sim-clock period p99 {policy['p99_ms']:.2f} ms, non-finite held "
             f"{policy['non_finite']}, clipped {policy['clipped']}"))
    r = monitor.world.report()
    print(f"  world step (wall): p50 {r['p50_ms']:.2f} p99 {r['p99_ms']:.2f} max {r['max_ms']:.2f} ms; "
          f"late hand replies {world['late_replies']:.0f}, late arm commands {world['late_arm_commands']:.0f}")
    rss = [m for _, m in monitor.rss]
    print(f"  memory (RSS): start {rss[0]:.0f} MiB, after set-up {rss[1]:.0f} MiB, end {rss[-1]:.0f} MiB "
          f"(growth after set-up {rss[-1] - rss[1]:+.1f} MiB over {len(rss) - 2} samples)")
    print(f"  load average {__import__('os').getloadavg()[0]:.1f}")
    print(f"command: .venv/bin/python scripts/soak_hil.py --config {args.config} --minutes {args.minutes:g}"
          + (f" --wall-minutes {args.wall_minutes:g}" if np.isfinite(args.wall_minutes) else "")
          + (" --policy" if args.policy else "") + (" --perception" if args.perception else ""))
    return 1 if fault else 0


if __name__ == "__main__":
    sys.exit(main())
