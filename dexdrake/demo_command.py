"""CLI `dexdrake demo`: the shipped policy tries to grasp an unseen object in simulation, recorded to rerun.

Needs nothing but the repository: the policy file `models/weights/adroit_dexrep_policy.pt`
and its manifest (`.json`, whose unseen evaluation picks the default object).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from dexdrake import argtypes
from dexdrake.errors import DexdrakeError

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


def add_parser(subparsers) -> None:
    demo = subparsers.add_parser("demo", help="the shipped policy tries to grasp an unseen object (writes a rerun recording)")
    demo.add_argument("--object", help="object name (default: the unseen object the shipped policy grasps best)")
    demo.add_argument("--seed", type=argtypes.seed, default=0, help="placement seed")
    demo.add_argument("--rrd", type=argtypes.output_file(".rrd"), default=Path("demo.rrd"), help="rerun recording to write")
    demo.add_argument("--policy", type=Path, help="policy checkpoint (default: the shipped one)")
    demo.add_argument("--steps", type=argtypes.count, default=100, help="control steps (50 Hz; paper evaluation: 100)")
    demo.set_defaults(func=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    if args.steps < 1:
        raise DexdrakeError(f"--steps must be >= 1, got {args.steps}")
    policy_path = args.policy or default_policy_path()
    if not Path(policy_path).is_file():
        hint = ("the shipped default policy is missing from this install; train one with "
                "`python scripts/build_default_policy.py` (or `dexdrake train bc`) or pass --policy")
        raise DexdrakeError(f"policy file {policy_path} not found: {hint}")
    import torch

    from dexdrake.eval.envs import env_factory_for_policy
    from dexdrake.eval.evaluate import run_episode
    from dexdrake.learn.policy import load_policy
    from dexdrake.learn.samplers import check_env_matches
    from dexdrake.objects.library import get_object
    from dexdrake.systems.rerun_logger import RerunEpisodeLogger

    torch.set_num_threads(1)
    name = args.object or best_unseen_object(Path(policy_path).with_suffix(".json"))
    info = get_object(name)
    policy, _ = load_policy(policy_path)
    env = env_factory_for_policy(policy.config, [name], args.steps)()
    check_env_matches(env, policy)
    logger = RerunEpisodeLogger(args.rrd)
    start = time.perf_counter()
    try:
        success, lift, steps, reward = run_episode(_LoggedEnv(env, logger), policy, args.seed, args.steps)
    finally:
        logger.close()
    wall = time.perf_counter() - start
    print(f"object={name} ({info.split}) seed={args.seed} success={success} max_lift={lift:.3f}m "
          f"steps={steps} reward={reward:.1f} wall={wall:.1f}s rrd={args.rrd}")
    return 0


class _LoggedEnv:
    """Wraps a GraspEnv so every reset and step is logged to rerun."""

    def __init__(self, env, logger):
        self.env, self.logger = env, logger

    def reset(self, seed: int):
        obs = self.env.reset(seed)
        self.logger.log_step(self.env, None)
        return obs

    def step(self, action):
        out = self.env.step(action)
        self.logger.log_step(self.env, out[3])
        return out
