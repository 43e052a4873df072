"""Sim-to-HIL parity of the shipped Allegro-on-Z1 policy: the same controller, episode loop
and success rule (dexdrake.systems.diagram.run_station_episode, dexdrake.task) on the same objects
and seeds, once in simulation and once hardware-in-the-loop at each PWM -> N*m scale
(`--scales`, multiples of allegro_units.NM_PER_PWM, the one place that assumption lives).
HIL uses rendered perception (`--camera rendered`, the default) or the world's pose (`sim`).

    .venv/bin/python scripts/parity_hil.py --objects box_cube sphere_small --seeds 0 1 \
        --steps 150 --scales 0.5 1 2 [--out models/weights/parity_hil.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def run(config: str, obj: str, seed: int, steps: int, mode: str, scale: float, camera: str) -> dict:
    from dexdrake.systems.controllers import make_controller
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.scenario import load_scenario
    from dexdrake.systems.station import make_station

    scenario = load_scenario(config)
    scenario.object, scenario.seed = obj, seed
    if mode == "sim":
        scenario.drivers.hand.kind = scenario.drivers.arm.kind = scenario.drivers.camera.kind = "sim"
    else:
        scenario.hil.pwm_torque_scale = scale
        scenario.drivers.camera.kind = camera
    controller, _ = make_controller(scenario)
    t0 = time.perf_counter()
    with make_station(scenario) as station:
        result = run_station_episode(station, controller, steps)
    return {"object": obj, "seed": seed, "mode": mode, "scale": scale, "success": result.success,
            "lift": result.max_lift, "fault": result.fault, "wall_s": time.perf_counter() - t0}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="configs/hil.yaml")
    parser.add_argument("--objects", nargs="+", default=["box_cube", "sphere_small", "can_soda"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--scales", nargs="+", type=float, default=[0.5, 1.0, 2.0])
    parser.add_argument("--camera", choices=["rendered", "sim"], default="rendered")
    parser.add_argument("--out", help="write the table (markdown) here as well")
    args = parser.parse_args()
    rows = []
    for obj in args.objects:
        for seed in args.seeds:
            for mode, scale in [("sim", 1.0)] + [("hil", s) for s in args.scales]:
                row = run(args.config, obj, seed, args.steps, mode, scale, args.camera)
                rows.append(row)
                print(f"  {obj:14s} seed {seed} {mode} x{scale:g}: success {row['success']} lift "
                      f"{row['lift']:.3f} m {row['fault'] or ''} ({row['wall_s']:.0f} s)", flush=True)
    command = ("python scripts/parity_hil.py --objects " + " ".join(args.objects) + " --seeds "
               + " ".join(map(str, args.seeds)) + f" --steps {args.steps} --scales "
               + " ".join(f"{s:g}" for s in args.scales) + f" --camera {args.camera}")
    lines = [f"Command: `{command}`", "",
             "| mode | PWM -> N*m scale | episodes | success | mean max lift (m) | faults |",
             "|---|---|---|---|---|---|"]
    for mode, scale in [("sim", 1.0)] + [("hil", s) for s in args.scales]:
        sel = [r for r in rows if r["mode"] == mode and r["scale"] == scale]
        lines.append(f"| {mode} | {'-' if mode == 'sim' else f'{scale:g} x'} | {len(sel)} | "
                     f"{np.mean([r['success'] for r in sel]):.0%} | "
                     f"{np.nanmean([r['lift'] for r in sel]):.3f} | {sum(bool(r['fault']) for r in sel)} |")
    lines += ["", f"NM_PER_PWM = 1/200 N*m per PWM count (dexdrake/hands/allegro_units.py); "
                  f"load average {os.getloadavg()[0]:.1f}."]
    table = "\n".join(lines)
    print(table)
    if args.out:
        tmp = args.out + ".tmp"
        with open(tmp, "w") as f:
            f.write(table + "\n")
        os.replace(tmp, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
