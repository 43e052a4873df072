"""Sim-to-HIL parity of the shipped Allegro-on-Z1 policy: the same controller, episode loop
and success rule (dexdrake.systems.diagram.run_station_episode, dexdrake.task) on the same objects
and seeds, once in simulation and once hardware-in-the-loop at each PWM -> N*m scale
(`--scales`, multiples of allegro_units.NM_PER_PWM, the one place that assumption lives).

Both sides see the same set-point path: in HIL the drivers clamp and rate-limit the
set-points (Allegro `max_target_rate`, Z1 `max_velocity` of `--config`); the simulated
station models the same limits (systems/target_limits.py). HIL uses rendered perception
(`--camera rendered`, the default: a pose one camera period after its frame, on the
simulated clock) or the world's pose (`sim`); simulation uses the true pose.

Episodes run in simulation first, then in HIL at the first scale, then at the other scales
(the sensitivity to the PWM assumption) interleaved episode by episode; the table is
rewritten after every episode, so a run stopped early leaves a consistent table whose
"sim, same episodes" column compares each row with simulation on exactly its episodes.

    .venv/bin/python scripts/parity_hil.py --objects can_soda lightbulb --seeds 0 1 \
        --horizon 150 --scales 1 0.5 2 [--out models/weights/parity_hil.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from dexdrake import argtypes


class PoseError:
    """An episode logger (the interface of systems/rerun_logger.RerunLogger that the episode
    loop calls) that keeps, per control step, the distance (m) between the object position
    the controller saw and the world's at the instant it was sampled (the world's pose
    logged at the end of the previous step)."""

    def __init__(self) -> None:
        self.errors: list[float] = []
        self._world: np.ndarray | None = None

    def log_station_step(self, t, hand_state, command, object_pose, stats, world_pose) -> None:
        if self._world is not None:
            self.errors.append(float(np.linalg.norm(object_pose[:3] - self._world)))
        self._world = world_pose.translation()

    def log_fault(self, text: str) -> None:
        pass


def run(config: str, obj: str, seed: int, steps: int, mode: str, scale: float, camera: str) -> dict:
    from dexdrake.systems.controllers import make_controller
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.scenario import load_scenario, simulated
    from dexdrake.systems.station import make_station

    scenario = load_scenario(config)
    scenario.object, scenario.seed = obj, seed
    if mode == "sim":
        scenario = simulated(scenario)
    else:
        scenario.hil.pwm_torque_scale = scale
        scenario.drivers.camera.kind = camera
    controller, _ = make_controller(scenario)
    t0, cpu0 = time.perf_counter(), time.process_time()
    pose_error = PoseError() if mode == "hil" else None
    with make_station(scenario) as station:
        result = run_station_episode(station, controller, steps, logger=pose_error)
        log = station.perception.log if station.perception is not None else None
    row = {"object": obj, "seed": seed, "mode": mode, "scale": scale, "success": result.success,
           "lift": result.max_lift, "fault": result.fault, "wall_s": time.perf_counter() - t0,
           "cpu_s": time.process_time() - cpu0}
    if log is not None:
        row.update(pose_error=pose_error.errors, track_cpu=log.cpu_s.get("track", []),
                   global_cpu=log.cpu_s.get("global", []), losses=log.tracking_losses)
    return row


def perception_table(rows: list[dict], modes: list[tuple[str, float]]) -> str:
    """Perception in the loop, per HIL scale (episodes with a perception log): its cost and
    the pose error the controller saw, over every control step."""
    lines = ["| PWM -> N*m scale | frames tracked | CPU per tracked frame: median / p95 (ms) | "
             "global registrations (CPU, median s) | tracking lost | pose error the policy saw "
             "(position, every control step): median / p95 / max (mm) |", "|---|---|---|---|---|---|"]
    for mode, scale in modes:
        sel = [r for r in rows if r["mode"] == mode and r["scale"] == scale and "pose_error" in r]
        if not sel:
            continue
        track = 1e3 * np.array([c for r in sel for c in r["track_cpu"]] or [np.nan])
        glob = [c for r in sel for c in r["global_cpu"]]
        err = 1e3 * np.array([e for r in sel for e in r["pose_error"]] or [np.nan])
        lines.append(f"| {scale:g} x | {sum(len(r['track_cpu']) for r in sel)} | {np.median(track):.1f} / "
                     f"{np.percentile(track, 95):.1f} | {len(glob)} ({np.median(glob or [np.nan]):.2f}) | "
                     f"{sum(r['losses'] for r in sel)} | {np.median(err):.1f} / {np.percentile(err, 95):.1f} / "
                     f"{err.max():.1f} |")
    return "\n".join(lines) if len(lines) > 2 else ""


def table(rows: list[dict], modes: list[tuple[str, float]], command: str, config: str) -> str:
    """The parity table (markdown) of the episodes in `rows`."""
    from dexdrake.hands.allegro_units import NM_PER_PWM
    from dexdrake.systems.scenario import load_scenario

    hand = load_scenario(config).drivers
    lines = [f"Command: `{command}`", "",
             "| mode | PWM -> N*m scale | episodes | success | mean max lift (m) | faults | "
             "sim, same episodes: success / lift (m) | successes (object/seed) |",
             "|---|---|---|---|---|---|---|---|"]
    sim = {(r["object"], r["seed"]): r for r in rows if r["mode"] == "sim"}
    for mode, scale in modes:
        sel = [r for r in rows if r["mode"] == mode and r["scale"] == scale]
        if not sel:
            continue
        same = [sim[r["object"], r["seed"]] for r in sel if (r["object"], r["seed"]) in sim]
        wins = " ".join(f"{r['object']}/{r['seed']}" for r in sel if r["success"]) or "-"
        lines.append(f"| {mode} | {'-' if mode == 'sim' else f'{scale:g} x'} | {len(sel)} | "
                     f"{np.mean([r['success'] for r in sel]):.0%} | "
                     f"{np.nanmean([r['lift'] for r in sel]):.3f} | {sum(bool(r['fault']) for r in sel)} | "
                     f"{np.mean([r['success'] for r in same]):.0%} / {np.nanmean([r['lift'] for r in same]):.3f} | "
                     f"{wins} |")
    rate = hand.hand.max_target_rate
    lines += ["", f"NM_PER_PWM = 1/{1 / NM_PER_PWM:g} N*m per PWM count (dexdrake/hands/allegro_units.py). "
              f"Set-points in both modes: joint limits, Allegro target rate "
              f"{'driver default' if rate is None else f'{rate:g} rad/s'}, Z1 "
              f"{'model velocity limit' if hand.arm.max_velocity is None else f'{hand.arm.max_velocity:g} rad/s'} "
              f"({config}); load average {os.getloadavg()[0]:.1f}; CPU per episode (this process, not the "
              "perception worker): "
              + ", ".join(f"{m}{'' if m == 'sim' else f' {s:g}x'} "
                          f"{np.mean([r['cpu_s'] for r in rows if r['mode'] == m and r['scale'] == s]):.0f} s"
                          for m, s in modes if any(r["mode"] == m and r["scale"] == s for r in rows)) + "."]
    perception = perception_table(rows, modes)
    if perception:
        lines += ["", "Perception in the loop (the perception worker's CPU per frame: segmentation, "
                  "back-projection, registration; not the rendering):", "", perception]
    return "\n".join(lines)


def write_atomic(path: str, text: str) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        f.write(text + "\n")
    os.replace(tmp, path)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="hil")
    parser.add_argument("--objects", nargs="+", default=["box_cube", "sphere_small", "can_soda"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--horizon", type=argtypes.steps, default=150, help=argtypes.horizon_help())
    parser.add_argument("--scales", nargs="+", type=float, default=[1.0, 0.5, 2.0])
    parser.add_argument("--camera", choices=["rendered", "sim"], default="rendered")
    parser.add_argument("--out", help="write the table (markdown) here as well, after every episode")
    args = parser.parse_args()
    command = ("python scripts/parity_hil.py --config " + args.config + " --objects " + " ".join(args.objects)
               + " --seeds " + " ".join(map(str, args.seeds)) + f" --horizon {args.horizon} --scales "
               + " ".join(f"{s:g}" for s in args.scales) + f" --camera {args.camera}")
    modes = [("sim", 1.0)] + [("hil", s) for s in args.scales]
    episodes = [(obj, seed) for seed in args.seeds for obj in args.objects]
    order = [(mode, scale, obj, seed) for mode, scale in modes[:2] for obj, seed in episodes]
    order += [(mode, scale, obj, seed) for obj, seed in episodes for mode, scale in modes[2:]]
    rows: list[dict] = []
    for mode, scale, obj, seed in order:
        row = run(args.config, obj, seed, args.horizon, mode, scale, args.camera)
        rows.append(row)
        print(f"  {mode} x{scale:g} {obj:14s} seed {seed}: success {row['success']} lift "
              f"{row['lift']:.3f} m {row['fault'] or ''} ({row['wall_s']:.0f} s wall, "
              f"{row['cpu_s']:.0f} s CPU)"
              + (f"; pose error max {1e3 * max(row['pose_error'], default=np.nan):.0f} mm, tracking lost "
                 f"{row['losses']}" if "pose_error" in row else ""), flush=True)
        if args.out:
            write_atomic(args.out, table(rows, modes, command, args.config))
    print(table(rows, modes, command, args.config))
    return 0


if __name__ == "__main__":
    sys.exit(main())
