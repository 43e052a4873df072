"""Choose the grasp expert's (ReactiveGrasp's) grasp variant per training object by simulated trials.

    python scripts/choose_expert_grasps.py [--hand adroit] [--seeds 100,...,111] [--workers 2] [--horizon 100]
        [--objects a,b,...]

Each variant (overrides of the hand's GraspScript: the open and closed poses, how far the
fingers close, the grasp centre's depth, reach and floor) runs the expert (ReactiveGrasp) on every training
object for the given seeds (the variants whose named grasp poses the hand has); the variant
with the most successes wins (ties: the earlier
variant, the hand's default first). A variant stops trying seeds once it can no longer beat
the best so far (`best_variant`), which chooses exactly as trying every seed would.
Writes models/weights/<hand>_expert_grasps.json (variants, per-object successes, the choice
and the command), which `ReactiveGrasp` reads; with --objects it re-chooses those objects only,
keeping the other entries of the existing table (their trials ran on its seeds, which must be
the same; variants added since show as untried there) and noting the command per re-chosen
object. Choose on seeds other than those of the reported expert table
(scripts/scripted_grasp_table.py uses 0..9), so the table is not measured on the seeds the
choice was fitted to. The default is twelve seeds, as fewer cannot tell most variants apart
(the comparison: models/weights/expert_grasp_table.md).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
from collections.abc import Callable
from dataclasses import replace

from tqdm import tqdm

VARIANTS: dict[str, dict] = {  # name -> GraspScript overrides; the first is the hand's default
    "power": {},
    "power_80": {"closure": 0.8},
    "oppose_80": {"closed_pose": "oppose", "closure": 0.8},
    "oppose_70": {"closed_pose": "oppose", "closure": 0.7},
    "power_floor_10": {"min_height": 0.01},  # flat objects: the grasp centre 1 cm above the table, ...
    "power_floor_25": {"min_height": 0.025},  # ... or 2.5 cm (the default plans it below the table)
    "oppose_80_floor_10": {"closed_pose": "oppose", "closure": 0.8, "min_height": 0.01},
    "oppose_80_floor_25": {"closed_pose": "oppose", "closure": 0.8, "min_height": 0.025},
    # flat and hollow objects: the thumb pre-shaped to oppose before the descent, the grasp centre
    # 1.5 cm below the top (a fingertip pinch; a rim pinch on a deep bowl) or 7 cm (a stem)
    "pinch_15": {"closed_pose": "oppose", "open_pose": "oppose", "palm_depth": 0.015, "tall_palm_depth": 0.015},
    "pinch_15_reach_40_80": {"closed_pose": "oppose", "open_pose": "oppose", "closure": 0.8, "palm_depth": 0.015,
                             "tall_palm_depth": 0.015, "reach": -0.04},
    "stem_70": {"closed_pose": "oppose", "open_pose": "oppose", "closure": 0.8, "palm_depth": 0.07,
                "tall_palm_depth": 0.07, "reach": -0.04},
    # wide and tall objects: the palm down on the top (the grasp centre 5 cm below it), or a
    # deeper grasp around the body with the fingers closing 80 %
    "palm_50": {"palm_depth": 0.05, "tall_palm_depth": 0.05},
    "palm_65_80": {"palm_depth": 0.065, "tall_palm_depth": 0.065, "closure": 0.8},
    # wide dishes: the same pinch on the rim, 6 cm out along the fingers, 1.5 or 0.8 cm below the top
    "rim_60": {"closed_pose": "oppose", "open_pose": "oppose", "palm_depth": 0.015, "tall_palm_depth": 0.015,
               "reach": 0.06},
    "rim_60_low": {"closed_pose": "oppose", "open_pose": "oppose", "palm_depth": 0.008, "tall_palm_depth": 0.008,
                   "reach": 0.06},
    # flat, thin and hollow objects (hands with 'pinch' poses): fingertips pointed down close toward the
    # thumb at table level (the grasp centre 7 cm above the table, or 4 cm above a taller top, 3.5 cm toward
    # the little-finger side to centre the tips), holding only once the thumb and a finger touch; across the
    # footprint's centre, or on the rim 2 cm inside its far edge (plates, bowls, rings)
    "pinch": {"closed_pose": "pinch", "open_pose": "pinch_open", "min_height": 0.07, "palm_depth": -0.04,
              "tall_palm_depth": -0.04, "reach": -0.033, "side": -0.035, "hover": 0.12, "closed_hold": 1.1},
    "pinch_rim": {"closed_pose": "pinch", "open_pose": "pinch_open", "min_height": 0.07, "palm_depth": -0.04,
                  "tall_palm_depth": -0.04, "reach": -0.02, "reach_edge": 1.0, "side": -0.035, "hover": 0.12,
                  "closed_hold": 1.1},
}


def best_variant(variants: list[str], seeds: list[int], succeeds: Callable[[str, int], bool]) -> tuple[str, dict[str, list[bool]]]:
    """The variant with the most successes over `seeds` (ties: the earlier one), and each
    variant's outcomes on the seeds it tried: a variant stops once even success on all its
    remaining seeds could not beat the best so far, so it could not have been chosen."""
    best, best_count, tried = variants[0], -1, {}
    for variant in variants:
        outcomes: list[bool] = []
        for seed in seeds:
            if sum(outcomes) + len(seeds) - len(outcomes) <= best_count:
                break
            outcomes.append(succeeds(variant, seed))
        tried[variant] = outcomes
        if len(outcomes) == len(seeds) and sum(outcomes) > best_count:
            best, best_count = variant, sum(outcomes)
    return best, tried


def _trial_object(args: tuple[str, str, list[int], int]) -> tuple[str, str, dict[str, list[bool]]]:
    hand, name, seeds, horizon = args
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.reactive_grasp import ReactiveGrasp
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.scripted_grasp import script_for

    env = GraspEnv(training_scenario(hand, name), horizon=horizon)
    default = script_for(env.scene.hand)

    def succeeds(variant: str, seed: int) -> bool:
        script = replace(default, **VARIANTS[variant])
        return env.rollout(lambda e: ReactiveGrasp(e, script), seed).success

    return name, *best_variant(hand_variants(env.scene.hand), seeds, succeeds)


def hand_variants(hand) -> list[str]:
    """The variants `hand` can take: those whose named grasp poses its description has."""
    return [name for name, v in VARIANTS.items()
            if all(v.get(key, "") in ("", *hand.grasp_poses) for key in ("closed_pose", "open_pose"))]


def main() -> None:
    from dexdrake import argtypes
    from dexdrake.eval.evaluate import EVAL_HORIZON

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hand", default="adroit")
    parser.add_argument("--seeds", type=argtypes.seed_list, default=list(range(100, 112)),
                        help="comma-separated placement seeds of the trials")
    parser.add_argument("--horizon", type=int, default=EVAL_HORIZON, help="control steps (default: the evaluation's)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--objects", help="comma-separated training objects to re-choose (default: all)")
    args = parser.parse_args()

    from dexdrake.hands.description import load_hand
    from dexdrake.objects.library import list_objects
    from dexdrake.systems.reactive_grasp import expert_grasps_path

    seeds = args.seeds
    names = [o.name for o in list_objects("train")]
    out = expert_grasps_path(args.hand)
    command = f"python {' '.join(sys.argv)}"
    old = json.loads(out.read_text()) if args.objects and out.is_file() else None
    if args.objects:
        chosen_names = args.objects.split(",")
        unknown = sorted(set(chosen_names) - set(names))
        if unknown:
            raise SystemExit(f"error: not training objects: {unknown}")
        if old is not None and old["seeds"] != seeds:
            raise SystemExit(f"error: {out} was chosen on seeds {old['seeds']}; re-choose with --seeds "
                             f"{','.join(map(str, old['seeds']))} (or every object)")
        names = chosen_names
    jobs = [(args.hand, n, seeds, args.horizon) for n in names]
    objects = {}
    with mp.get_context("spawn").Pool(args.workers) as pool:
        for name, best, tried in tqdm(pool.imap_unordered(_trial_object, jobs), total=len(jobs), desc="objects"):
            objects[name] = {"variant": best, "successes": {v: sum(ok) for v, ok in tried.items()},
                             "tries": {v: len(ok) for v, ok in tried.items()}}
    variants = {v: VARIANTS[v] for v in hand_variants(load_hand(args.hand))}
    if old is not None:
        for o in objects.values():
            o["command"] = command
        objects = {**old["objects"], **objects}
        names = list(objects)
        for o in objects.values():  # kept objects: the variants added since are untried
            for v in variants:
                o["successes"].setdefault(v, 0)
                o["tries"].setdefault(v, 0)
    else:
        objects = {name: objects[name] for name in names}
    for name, o in objects.items():
        print(f"{name:18s} {o['variant']:10s} " + " ".join(f"{v}={o['successes'][v]}/{o['tries'][v]}"
                                                          for v in o["successes"]))
    chosen = sum(o["successes"][o["variant"]] for o in objects.values())
    tries = sum(sum(o["tries"].values()) for o in objects.values())
    print(f"chosen per object: {chosen}/{len(names) * len(seeds)}; {tries} of {len(names) * len(seeds) * len(variants)} "
          "trials run (the rest could not change a choice)")
    table = {"hand": args.hand, "command": old["command"] if old else command, "seeds": seeds,
             "horizon": args.horizon, "variants": variants, "objects": objects}
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(table, indent=1) + "\n")
    tmp.replace(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
