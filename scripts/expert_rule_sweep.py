"""Paired sweep of the state-driven expert's rules: its success on the training objects under
`ReactiveRules` overrides, on the same seeds.

    python scripts/expert_rule_sweep.py [--hand adroit] [--seeds 100,101,102,103] [--workers 2]
        [--horizon 100] SPEC [SPEC ...]

Each SPEC is "" (the rules as they are) or comma-separated overrides such as
"keep_xy=0.05,max_lead=0.5". Prints, per SPEC, the successes over all objects and seeds, and
the objects whose count differs between SPECs. Sweep on the choice's seeds (100..), never on
the expert table's 0..9.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
from dataclasses import fields, replace

from tqdm import tqdm


def parse_spec(spec: str) -> dict[str, float]:
    """'a=1,b=2.5' -> {'a': 1.0, 'b': 2.5} ('' -> {}); ValueError names an unknown rule or a bad value."""
    from dexdrake.systems.reactive_grasp import ReactiveRules

    types = {f.name: f.type for f in fields(ReactiveRules)}
    overrides = {}
    for item in filter(None, spec.split(",")):
        key, _, value = item.partition("=")
        if key not in types:
            raise ValueError(f"unknown rule {key!r} in {spec!r}; known: {', '.join(sorted(types))}")
        try:
            overrides[key] = int(value) if types[key] == "int" else float(value)
        except ValueError:
            raise ValueError(f"{item!r}: {key} takes {'an integer' if types[key] == 'int' else 'a number'}") from None
    return overrides


def _trial_object(args: tuple[str, str, list[int], int, dict]) -> tuple[str, int]:
    hand_name, name, seeds, horizon, overrides = args
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.reactive_grasp import ReactiveGrasp, ReactiveRules
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.scripted_grasp import with_overrides

    env = GraspEnv(training_scenario(hand_name, name), horizon=horizon)
    hand = env.scene.hand
    rules = replace(with_overrides(ReactiveRules, hand.grasp_expert, hand, "grasp_expert"), **overrides)
    return name, sum(env.rollout(lambda e: ReactiveGrasp(e, rules=rules), s).success for s in seeds)


def main() -> None:
    from dexdrake import argtypes
    from dexdrake.eval.evaluate import EVAL_HORIZON

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("specs", nargs="+", metavar="SPEC")
    parser.add_argument("--hand", default="adroit")
    parser.add_argument("--seeds", type=argtypes.seed_list, default=[100, 101, 102, 103],
                        help="comma-separated placement seeds")
    parser.add_argument("--horizon", type=argtypes.count, default=EVAL_HORIZON,
                        help="control steps (default: the evaluation's)")
    parser.add_argument("--workers", type=argtypes.count, default=2)
    args = parser.parse_args()
    try:
        specs = {spec: parse_spec(spec) for spec in args.specs}
    except ValueError as e:
        parser.error(str(e))
    seeds = args.seeds

    from dexdrake.objects.library import list_objects

    names = [o.name for o in list_objects("train")]
    counts: dict[str, dict[str, int]] = {}
    with mp.get_context("spawn").Pool(args.workers) as pool:
        for spec, overrides in specs.items():
            jobs = [(args.hand, n, seeds, args.horizon, overrides) for n in names]
            counts[spec] = dict(tqdm(pool.imap_unordered(_trial_object, jobs), total=len(jobs), desc=spec or "as is"))
            total = sum(counts[spec].values())
            print(f"{spec or 'as is':40s} {total}/{len(names) * len(seeds)} = {100 * total / (len(names) * len(seeds)):.1f} %",
                  flush=True)
    for name in names:
        row = [counts[spec][name] for spec in specs]
        if len(set(row)) > 1:
            print(f"{name:18s} " + " ".join(f"{c:3d}" for c in row))


if __name__ == "__main__":
    main()
