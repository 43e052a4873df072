"""CPU per GraspEnv step with the drivers' target limits in the sim station (TargetLimiter,
updated every plant step: what training, sim and hil run) against the peer: the same env
whose station feeds the set-points straight to the plant's PD (no limiter).

Both envs run the scripted grasp on the same seeds in the same process, alternating
episodes; the ratio is per CPU-second (time.process_time), the best of `--repeats` rounds.
Run: python scripts/bench_target_limits.py [--hand adroit] [--object sphere_medium]
     [--feature-set DexRep] [--episodes 3] [--repeats 2]
"""

from __future__ import annotations

import argparse
import os
import time


def unlimited_station(scenario):
    """The sim station of `scenario` without the drivers' target limits (the peer)."""
    from pydrake.systems.framework import DiagramBuilder

    from dexdrake.systems.scene import build_grasp_scene
    from dexdrake.systems.station import Station

    scene = build_grasp_scene(scenario)
    builder = DiagramBuilder()
    sub = builder.AddNamedSystem("scene", scene.diagram)
    builder.ExportInput(sub.GetInputPort("command"), "command")
    for name in ("hand_state", "object_pose", "query_object"):
        builder.ExportOutput(sub.GetOutputPort(name), name)
    return Station(scenario, builder.Build(), scene.hand, scene=scene)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hand", default="adroit")
    parser.add_argument("--object", default="sphere_medium")
    parser.add_argument("--feature-set", default="DexRep", help="'none': hand state only")
    parser.add_argument("--episodes", type=int, default=3, help="episodes of the one object (seeds 0..N-1)")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()

    from dexdrake.systems import grasp_env
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.scripted_grasp import ScriptedGrasp

    scenario = training_scenario(args.hand, args.object)
    features = None if args.feature_set == "none" else args.feature_set
    limited = grasp_env.GraspEnv(scenario, features, horizon=100)
    grasp_env.sim_station = unlimited_station  # the peer's station, for its construction only
    peer = grasp_env.GraspEnv(scenario, features, horizon=100)
    assert not peer.built.station.diagram.HasSubsystemNamed("driver_target_limits")

    def ms_per_step(env) -> float:
        start, steps = time.process_time(), 0
        for seed in range(args.episodes):
            steps += env.rollout(ScriptedGrasp, seed).steps
        return (time.process_time() - start) / steps * 1e3

    print(f"hand={args.hand} object={args.object} features={args.feature_set} episodes={args.episodes} x 100 "
          f"steps, plant step {scenario.time_step * 1e3:g} ms; load average {os.getloadavg()[0]:.1f}")
    ms_per_step(limited), ms_per_step(peer)  # warm-up
    rounds = [(ms_per_step(limited), ms_per_step(peer)) for _ in range(args.repeats)]
    best_limited, best_peer = min(r[0] for r in rounds), min(r[1] for r in rounds)
    print(f"CPU ms per env step: with target limits {best_limited:.2f}, without (peer) {best_peer:.2f}, "
          f"ratio {best_limited / best_peer:.3f}")


if __name__ == "__main__":
    main()
