"""A supervised episode on a real station (`dexdrake real`), on the wall clock:

  1. move to the start pose (the hand's pre-grasp pose: arm over the object, hand open),
  2. the episode: the scenario's controller in the one diagram of every mode
     (systems/diagram.run_station_episode: perception's first pose, then `steps` control
     periods; a rerun logger records it, faults included),
  3. retreat: the hand opens (fingers to the start pose's, the arm held; a finger the object or
     the table blocks stops where it is), then the arm goes back to the start pose, lifting the
     open hand off the object (the blocked fingers reach their goal on the way),
and the caller's `with make_station(...)` ends all of it in the drivers' safe stop.

Moves (1, 3) send set-points on the straight line in joint space from the measured pose to
the goal, advancing `real.move_speed` (rad/s) on the fastest joint, one every control period,
straight to the drivers (which keep their own clamps and target-rate limits); every
set-point passes the workspace box first (systems/workspace.py). A move ends when every
joint is within `real.move_tolerance` of its goal (the hand's opening also once every joint
has stood still for OPEN_SETTLE_S after the last set-point); not there `real.move_timeout_s`
after its last set-point is a fault. Any fault (a driver's, a set-point outside the box, perception's,
a stale pose) ends the sequence where it happened: nothing more is sent and the caller's
safe stop follows.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dexdrake.errors import StationFault
from dexdrake.episode import EpisodeResult
from dexdrake.hardware.safety import HardwareError
from dexdrake.systems.diagram import run_station_episode
from dexdrake.systems.station import Station

PHASES = ("move to the start pose", "episode", "retreat")
OPEN_SETTLE_S = 0.5  # s: the opening hand has stopped where no joint moved a fifth of move_tolerance


@dataclass
class SupervisedResult:
    """How far the sequence got: `phase` (one of PHASES) it ended in, the `fault` that
    ended it (None: it finished), and the episode's result once the episode ran."""

    phase: str
    fault: str | None
    episode: EpisodeResult | None = None


def move_to(station: Station, goal: np.ndarray, label: str, settle_s: float | None = None) -> float:
    """Drive the station from its measured pose to `goal` (policy order) as the module
    docstring says; returns the move's wall time (s). StationFault on a fault. With
    `settle_s` the move also ends once its last set-point is sent and no joint has moved a
    fifth of `real.move_tolerance` for `settle_s`."""
    real, period = station.scenario.real, station.scenario.control_period
    goal = np.asarray(goal, float)
    start = station.positions()
    duration = float(np.max(np.abs(goal - start))) / real.move_speed
    t0 = time.monotonic()
    still_at, still_since = None, 0.0  # where the joints have stood since when (after the last set-point)
    while True:
        t = time.monotonic() - t0
        s = 1.0 if duration <= 0 else min(t / duration, 1.0)
        station.send(start + s * (goal - start))
        q = station.positions()
        error = float(np.max(np.abs(q - goal)))
        if s >= 1.0 and error <= real.move_tolerance:
            return t
        if settle_s is not None and s >= 1.0:
            if still_at is None or np.max(np.abs(q - still_at)) > real.move_tolerance / 5:
                still_at, still_since = q, t
            elif t - still_since >= settle_s:
                return t
        if t > duration + real.move_timeout_s:
            raise StationFault(f"{label}: still {error:.3f} rad from the goal {real.move_timeout_s:.0f} s "
                               "after its last set-point")
        time.sleep(period)


def start_pose(station: Station) -> np.ndarray:
    """The episode's start pose: the hand's pre-grasp pose (policy order)."""
    return station.hand.pregrasp_vector()


def run_supervised(station: Station, controller, steps: int, logger=None,
                   say: Callable[[str], None] = print) -> SupervisedResult:
    """Steps 1-3 of the module docstring on a started real station; `say` reports each
    phase. Ctrl-C propagates (the caller's station context stops the devices safely)."""
    n_arm = len(station.hand.arm_joints)
    start = start_pose(station)

    def fault(phase: str, err: Exception) -> SupervisedResult:
        if logger is not None:
            logger.log_fault(f"{phase}: {err}")
        return SupervisedResult(phase, str(err))

    phase = PHASES[0]
    try:
        say(f"{phase} at {station.scenario.real.move_speed} rad/s ...")
        say(f"  arrived in {move_to(station, start, phase):.1f} s")
    except (StationFault, HardwareError) as err:
        return fault(phase, err)
    phase = PHASES[1]
    say(f"{phase}: {steps} control steps of {station.scenario.control_period * 1e3:.0f} ms ...")
    result = run_station_episode(station, controller, steps, logger)
    if result.fault:
        return SupervisedResult(phase, result.fault, result)
    say(f"  {result.steps} steps; {result.wall_s:.1f} s with the wait for the first pose")
    phase = PHASES[2]
    try:
        say(f"{phase}: the hand opens, then the arm goes back to the start pose ...")
        here = station.positions()
        opened = np.concatenate([here[:n_arm], start[n_arm:]])
        t = move_to(station, opened, f"{phase} (open the hand)", OPEN_SETTLE_S)
        short = float(np.max(np.abs(station.positions()[n_arm:] - start[n_arm:])))
        if short > station.scenario.real.move_tolerance:
            say(f"  the hand stopped {short:.3f} rad short of open (blocked): the arm lifts it clear")
        t += move_to(station, start, f"{phase} (arm to the start pose)")
        say(f"  done in {t:.1f} s")
    except (StationFault, HardwareError) as err:
        out = fault(phase, err)
        out.episode = result
        return out
    return SupervisedResult(phase, None, result)
