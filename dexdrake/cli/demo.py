"""CLI `dexdrake demo`: the shipped policy tries to grasp an object in simulation, recorded to rerun.

Needs nothing but the repository: the policy file `models/weights/adroit_dexrep_policy.pt`
and its manifest (`.json`, whose unseen evaluation picks the default object). Any object
(training, unseen or user-imported) can be chosen with --object and any placement with
--seed. Next to the episode's result it prints the policy's measured seen/unseen success
rates from the manifest, so one episode is never mistaken for the policy's rate.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from dexdrake import argtypes
from dexdrake.cli.flags import add_horizon
from dexdrake.errors import DexdrakeError
from dexdrake.eval.evaluate import EVAL_HORIZON

POLICY_NAME = "adroit_dexrep_policy"
FALLBACK_OBJECT = "apple"


def default_policy_path() -> Path:
    """The shipped default policy: models/weights/adroit_dexrep_policy.pt."""
    from dexdrake.paths import models_dir

    return models_dir() / "weights" / f"{POLICY_NAME}.pt"


def best_unseen_object(manifest_path: Path) -> str:
    """The unseen object with the highest success in the manifest's evaluation (ties: by name)."""
    if not manifest_path.is_file():
        return FALLBACK_OBJECT
    try:
        per_object = json.loads(manifest_path.read_text())["metrics"]["unseen"]["per_object"]
    except (KeyError, TypeError, json.JSONDecodeError):
        return FALLBACK_OBJECT
    if not per_object:
        return FALLBACK_OBJECT
    return min(per_object, key=lambda n: (-per_object[n]["success_pct"], -per_object[n]["mean_max_lift"], n))


def recorded_success_seed(manifest_path: Path, name: str) -> int | None:
    """The first evaluation seed on which the manifest records a success on `name` (the demo
    then replays that evaluation episode), or None."""
    try:
        metrics = json.loads(manifest_path.read_text())["metrics"]
        seeds = [s for label in ("unseen", "seen") for s in metrics.get(label, {}).get("successful_seeds", {}).get(name, [])]
    except (OSError, KeyError, TypeError, AttributeError, json.JSONDecodeError):
        return None
    return min(seeds) if seeds else None


def measured_rates(manifest_path: Path) -> str:
    """One line with the seen/unseen success rates the policy's manifest records."""
    try:
        metrics = json.loads(manifest_path.read_text())["metrics"]
    except (OSError, KeyError, TypeError, json.JSONDecodeError):
        return f"measured rates: none (no readable metrics in {manifest_path})"
    parts = []
    for label in ("seen", "unseen"):
        m = metrics.get(label) if isinstance(metrics, dict) else None
        if not isinstance(m, dict) or "average_pct" not in m:
            parts.append(f"{label} not measured")
            continue
        text = f"{label} {m['average_pct']:.1f} %"
        if "average_ci95_pct" in m:
            text += f" (95 % CI {m['average_ci95_pct'][0]:.1f}-{m['average_ci95_pct'][1]:.1f})"
        if "per_object" in m and "episodes_per_object" in m:
            text += f" over {len(m['per_object'])} objects x {m['episodes_per_object']} episodes"
        if "seed" in m:
            text += f" from seed {m['seed']}"
        parts.append(text)
    return f"measured rates of this policy ({manifest_path.name}): " + "; ".join(parts)


def add_parser(subparsers) -> None:
    demo = subparsers.add_parser("demo", help="the shipped policy tries to grasp an object (writes a rerun recording)")
    demo.add_argument("--object", help="any object name: training, unseen or user-imported "
                                       "(default: the unseen object the shipped policy grasps best)")
    demo.add_argument("--seed", type=argtypes.seed, help="placement seed (default: the first evaluation seed on which "
                                                         "the manifest records a success on the object, else 0)")
    demo.add_argument("--rrd", type=argtypes.output_file(".rrd"), default=Path("demo.rrd"), help="rerun recording to write")
    demo.add_argument("--policy", type=Path, help="policy checkpoint (default: the shipped one)")
    add_horizon(demo, EVAL_HORIZON)
    demo.set_defaults(func=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    policy_path = args.policy or default_policy_path()
    if not Path(policy_path).is_file():
        hint = ("the shipped default policy is missing from this install; train one with "
                "`dexdrake train recipe configs/recipes/adroit.yaml --ship` or pass --policy")
        raise DexdrakeError(f"policy file {policy_path} not found: {hint}")
    import torch

    from dexdrake.episode import run_episode
    from dexdrake.eval.evaluate import mean_actor
    from dexdrake.learn.policy import load_policy
    from dexdrake.learn.samplers import check_env_matches
    from dexdrake.objects.library import get_object
    from dexdrake.systems.env_factory import env_factory_for_policy
    from dexdrake.systems.rerun_logger import RerunLogger

    torch.set_num_threads(1)
    manifest = Path(policy_path).with_suffix(".json")
    name = args.object or best_unseen_object(manifest)
    info = get_object(name)
    recorded = recorded_success_seed(manifest, name) if args.seed is None else None
    seed = args.seed if args.seed is not None else recorded if recorded is not None else 0
    policy, _ = load_policy(policy_path)
    env = env_factory_for_policy(policy.config, [name], args.horizon)()
    check_env_matches(env, policy)
    logger = RerunLogger(args.rrd, "demo")
    start = time.perf_counter()
    try:
        result = run_episode(env, mean_actor(policy), seed, args.horizon, **logger.hooks(env))
    finally:
        logger.close()
    wall = time.perf_counter() - start
    print(f"object={name} ({info.split}) seed={seed} success={result.success} max_lift={result.max_lift:.3f}m "
          f"steps={result.steps} reward={result.total_reward:.1f} wall={wall:.1f}s rrd={args.rrd}")
    if recorded is not None:
        print(f"seed {seed} replays an evaluation episode the manifest records as a success; --seed N tries any other")
    print(measured_rates(manifest))
    return 0
