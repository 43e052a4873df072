"""Sim-to-HIL parity (`dexdrake parity`): one episode of the scenario's controller in
simulation or hardware-in-the-loop (`run_parity_episode`, the same episode loop and success
rule: systems/diagram.run_station_episode, dexdrake.task) and the markdown table of such
episodes (`parity_table`), HIL at each PWM -> N*m scale (multiples of
allegro_units.NM_PER_PWM, the one place that assumption lives) beside simulation on the same
objects and seeds.

Both sides see the same set-point path: in HIL the drivers clamp and rate-limit the
set-points (Allegro `max_target_rate`, Z1 `max_velocity` of the scenario); the simulated
station models the same limits (systems/target_limits.py). HIL uses rendered perception
(camera `rendered`: a pose one camera period after its frame, on the simulated clock) or the
world's pose (`sim`); simulation, the scenario's perception model (the one its policy was
trained under: pose noise, frame period, latency; dexdrake/perceived_pose.py), so that sim is
the policy's protocol evaluation and HIL the camera pipeline in its place.
"""

from __future__ import annotations

import os
import time

import numpy as np


class PoseError:
    """An episode logger (the interface of systems/rerun_logger.RerunLogger that the episode
    loop calls) that keeps, per control step, the distance (m) between the object position
    the controller saw and the world's at the instant it was sampled (the world's pose
    logged at the end of the previous step), while the object is on the table (its centre
    above the table top, z = 0): one that fell off it, out of view, is not a pose error."""

    def __init__(self) -> None:
        self.errors: list[float] = []
        self._world: np.ndarray | None = None

    def log_station_step(self, t, hand_state, command, object_pose, stats, world_pose) -> None:
        if self._world is not None and self._world[2] > 0.0:
            self.errors.append(float(np.linalg.norm(object_pose[:3] - self._world)))
        self._world = world_pose.translation()

    def log_fault(self, text: str) -> None:
        pass


def run_parity_episode(config: str, obj: str, seed: int, steps: int, mode: str, scale: float, camera: str) -> dict:
    """One episode of `config`'s controller on `obj` at `seed` for `steps` control steps, in
    simulation (`mode` "sim") or HIL at PWM scale `scale` with camera `camera`: its row of the
    table (success, max lift, fault, wall and CPU time, the pose error the controller saw; with
    rendered perception its cost)."""
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
    pose_error = PoseError()
    with make_station(scenario) as station:
        result = run_station_episode(station, controller, steps, logger=pose_error)
        log = station.perception.log if station.perception is not None else None
    row = {"object": obj, "seed": seed, "mode": mode, "scale": scale, "success": result.success,
           "lift": result.max_lift, "fault": result.fault, "wall_s": time.perf_counter() - t0,
           "cpu_s": time.process_time() - cpu0, "pose_error": pose_error.errors}
    if log is not None:
        row.update(track_cpu=log.cpu_s.get("track", []),
                   global_cpu=log.cpu_s.get("global", []), losses=log.tracking_losses)
    return row


def perception_table(rows: list[dict], modes: list[tuple[str, float]]) -> str:
    """Perception in the loop, per HIL scale (episodes with a perception log): its cost."""
    lines = ["| PWM -> N*m scale | frames tracked | CPU per tracked frame: median / p95 (ms) | "
             "global registrations (CPU, median s) | tracking lost |", "|---|---|---|---|---|"]
    for mode, scale in modes:
        sel = [r for r in rows if r["mode"] == mode and r["scale"] == scale and "track_cpu" in r]
        if not sel:
            continue
        track = 1e3 * np.array([c for r in sel for c in r["track_cpu"]] or [np.nan])
        glob = [c for r in sel for c in r["global_cpu"]]
        lines.append(f"| {scale:g} x | {sum(len(r['track_cpu']) for r in sel)} | {np.median(track):.1f} / "
                     f"{np.percentile(track, 95):.1f} | {len(glob)} ({np.median(glob or [np.nan]):.2f}) | "
                     f"{sum(r['losses'] for r in sel)} |")
    return "\n".join(lines) if len(lines) > 2 else ""


def pose_error_text(rows: list[dict]) -> str:
    """median / p95 / max (mm) of the pose error the controller saw in `rows` (`PoseError`)."""
    err = 1e3 * np.array([e for r in rows for e in r["pose_error"]] or [np.nan])
    return f"{np.median(err):.1f} / {np.percentile(err, 95):.1f} / {err.max():.1f}"


def controller_text(config: str) -> str:
    """Which controller `config` runs: its policy checkpoint with the file's sha256, or the
    scripted grasp."""
    from dexdrake.objects.meshfile import file_hash
    from dexdrake.paths import resolve_model_path
    from dexdrake.systems.scenario import load_scenario

    policy = load_scenario(config).policy
    if policy is None:
        return f"Controller: the scripted grasp ({config} has no policy)."
    path = resolve_model_path(policy.checkpoint)
    return f"Controller: policy `{policy.checkpoint}` (sha256 {file_hash(path)[:12]}, {policy.feature_set})."


def parity_table(rows: list[dict], modes: list[tuple[str, float]], command: str, config: str) -> str:
    """The parity table (markdown) of the episodes in `rows`."""
    from dexdrake.hands.allegro_units import NM_PER_PWM
    from dexdrake.systems.scenario import load_scenario

    hand = load_scenario(config).drivers
    lines = [f"Command: `{command}`", "", controller_text(config), "",
             "| mode | PWM -> N*m scale | episodes | success | mean max lift (m) | faults | "
             "pose error the controller saw (position, every control step with the object on the table): median / p95 / max (mm) | "
             "sim, same episodes: success / lift (m) | successes (object/seed) |",
             "|---|---|---|---|---|---|---|---|---|"]
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
                     f"{pose_error_text(sel)} | "
                     f"{np.mean([r['success'] for r in same]):.0%} / {np.nanmean([r['lift'] for r in same]):.3f} | "
                     f"{wins} |")
    rate = hand.hand.max_target_rate
    lines += ["", f"NM_PER_PWM = 1/{1 / NM_PER_PWM:g} N*m per PWM count (dexdrake/hands/allegro_units.py). "
              f"Set-points in both modes: joint limits, Allegro target rate "
              f"{'driver default' if rate is None else f'{rate:g} rad/s'}, Z1 "
              f"{'driver default' if hand.arm.max_velocity is None else f'{hand.arm.max_velocity:g} rad/s'} "
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
