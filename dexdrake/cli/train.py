"""CLI: `dexdrake train bc|dagger|dapg|recipe|retest`.

The flags of `bc`, `dagger` and `dapg` are made from the training code's settings
dataclasses (BCConfig, DaggerConfig, DAPGConfig and the recipe stages' fields the command
line adds: objects, episodes per object, demonstration pairs), so each setting's name, type,
default and help are written once.
"""

from __future__ import annotations

import argparse
import hashlib
from functools import partial
from pathlib import Path
from typing import Any

from dexdrake import argtypes
from dexdrake.cli.flags import (add_backend_options, add_envs_per_worker, add_settings, command_line, envs_per_worker,
                                option_names, setting_names, settings_from_args)
from dexdrake.errors import DexdrakeError
from dexdrake.learn.bc import BCConfig
from dexdrake.learn.dagger import DaggerConfig
from dexdrake.learn.dapg import DAPGConfig
from dexdrake.learn.recipe import DaggerStage, DapgStage
from dexdrake.outputs import WriterLock, check_run_kind
from dexdrake.task import TaskSpec


def add_parser(subparsers) -> None:
    train = subparsers.add_parser("train", help="train a DexRepNet policy (BC, DAgger, DAPG or a recipe of them)",
                                  description="Train a DexRepNet policy.")
    train_sub = train.add_subparsers(dest="train_command", required=True)

    bc = train_sub.add_parser("bc", help="behaviour cloning from a demo dataset (.npz)")
    bc.add_argument("--data", required=True, type=Path, help="demo dataset .npz (metadata: hand, feature_set, observation_blocks)")
    bc.add_argument("--out", required=True, type=argtypes.output_folder, help="output folder (checkpoints, bc_log.csv/png)")
    add_settings(bc, BCConfig)
    bc.add_argument("--threads", type=argtypes.count, default=1, help="torch CPU threads")
    bc.set_defaults(func=cmd_train_bc, recorded_options=option_names(bc))

    dagger = train_sub.add_parser(
        "dagger", help="DAgger with the grasp expert (ReactiveGrasp)",
        description="DAgger: the grasp expert (ReactiveGrasp) drives iteration 0 and labels every state the "
                    "policy visits after it (no demo file needed); the policy is re-fit by behaviour cloning after "
                    "each iteration.")
    dagger.add_argument("--out", required=True, type=argtypes.output_folder, help="output folder (per-iteration data and policies, dagger_log.csv)")
    add_settings(dagger, DaggerStage)
    add_settings(dagger, DaggerConfig)
    dagger.add_argument("--resume-changed", action="store_true",
                        help="go on with a run in OUT whose settings (iterations, episodes-per-object, epochs, lr, ...) differ: "
                             "later iterations use the new ones; fewer --iterations choose dagger_policy.pt again "
                             "among the first ones (default: refused)")
    add_envs_per_worker(dagger, "policy-driven environments")
    add_backend_options(dagger)
    dagger.add_argument("--threads", type=argtypes.count, default=2, help="torch CPU threads for the BC fits")
    dagger.set_defaults(func=cmd_train_dagger, recorded_options=option_names(dagger))

    dapg = train_sub.add_parser("dapg", help="DAPG fine-tuning of a BC or DAgger policy",
                                description="DAPG fine-tuning of a BC or DAgger policy in the Drake grasp env.")
    dapg.add_argument("--init", required=True, type=Path, help="policy checkpoint to start from (e.g. dagger_policy.pt)")
    dapg.add_argument("--demos", required=True, type=Path,
                      help="demonstration term: a demo dataset .npz or a DAgger output folder (its data_XX.npz)")
    add_settings(dapg, DapgStage)
    dapg.add_argument("--out", required=True, type=argtypes.output_folder, help="output folder (dapg_state.pt, checkpoints, curves)")
    add_settings(dapg, DAPGConfig, *(name for name in setting_names(DAPGConfig) if name != "seed"))
    dapg.add_argument("--workers", type=argtypes.count, default=2, help="rollout worker processes")
    add_envs_per_worker(dapg, "environments")
    add_backend_options(dapg)
    dapg.add_argument("--resume", action="store_true", help="continue the run in OUT (dapg_state.pt) where it stopped")
    add_settings(dapg, DAPGConfig, "seed")
    dapg.set_defaults(func=cmd_train_dapg, recorded_options=option_names(dapg))

    recipe = train_sub.add_parser("recipe", help="every stage of a training recipe, resumable",
                                  description="Every stage of a training recipe: expert table, DAgger, DAPG, choice "
                                              "on validation seeds, test evaluation (see configs/recipes/); re-run to resume.")
    recipe.add_argument("recipe", type=Path, help="recipe YAML (dexdrake.learn.recipe.Recipe)")
    recipe.add_argument("--out", required=True, type=Path, help="run folder (one subfolder per stage; re-run to resume)")
    recipe.add_argument("--until", metavar="STAGE",
                        help="stop after this stage (e.g. choose: a candidate run that may not ship leaves the test "
                             "seeds unused; re-run without it to go on)")
    recipe.add_argument("--ship", action="store_true", help="copy the policy, manifest, tables and curves to --weights")
    recipe.add_argument("--weights", type=Path, help="where --ship writes (default: the installed models/weights)")
    recipe.add_argument("--workers", type=argtypes.count, default=2, help="rollout worker processes")
    add_backend_options(recipe)
    recipe.add_argument("--threads", type=argtypes.count, default=2, help="torch CPU threads for the BC fits")
    recipe.set_defaults(func=cmd_train_recipe, recorded_options=option_names(recipe))

    retest = train_sub.add_parser(
        "retest", help="re-evaluate a shipped policy with the current code (its test tables and manifest metrics)",
        description="Re-evaluate a shipped policy on the test seeds as its tables were made (objects, horizon, "
                    "episodes), seeing the object pose as it was trained to; rewrite its seen/unseen tables and its "
                    "manifest's metrics and record the command in the manifest.")
    retest.add_argument("policy", type=Path, help="a shipped policy (.pt) with its manifest (.json) beside it")
    retest.add_argument("--episodes-per-object", type=argtypes.episodes, metavar="N",
                        help=argtypes.episodes_per_object_help("seeds from the first test seed")
                        + " (default: as the shipped tables were made)")
    retest.add_argument("--workers", type=argtypes.count, default=2, help="evaluation worker processes (default: 2)")
    add_envs_per_worker(retest, "objects (one environment each)")
    retest.set_defaults(func=cmd_train_retest, recorded_options=option_names(retest))


def policy_config_from_metadata(metadata: dict[str, Any], action_dim: int, obs_dim: int):
    """A PolicyConfig from a dataset's metadata (observation_blocks, hand, feature_set)."""
    from dexdrake.learn.policy import PolicyConfig

    missing = [k for k in ("observation_blocks", "hand", "feature_set") if not metadata.get(k)]
    if missing:
        raise DexdrakeError(f"dataset metadata lacks {missing} (a replay dataset needs `--feature-set`, "
                            f"e.g. DexRep); it has {sorted(metadata)}")
    blocks = metadata["observation_blocks"]
    blocks = dict(blocks) if not isinstance(blocks, dict) else blocks
    config = PolicyConfig.from_blocks(blocks, action_dim, feature_set=str(metadata["feature_set"]), hand=str(metadata["hand"]))
    if config.obs_dim != obs_dim:
        raise DexdrakeError(f"dataset observation_blocks {blocks} sum to {config.obs_dim}, observations have {obs_dim} columns")
    return config


def _scenario_record(hand: str, perception=None, source: str = "the training scenario") -> dict[str, Any]:
    """The record of the sim scenario training runs `hand` under, seeing the object through
    `perception` (a PerceptionModel; None: the true pose), stored in checkpoints; a
    perception model the scenario refuses is refused here, before any work."""
    from dexdrake.perceived_pose import PerceptionModel
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.scenario import validate_scenario
    from dexdrake.systems.scenario_record import scenario_record

    scenario = training_scenario(hand, perception=perception or PerceptionModel())
    validate_scenario(scenario, source)
    return scenario_record(scenario)


def dataset_summary(metadata: dict[str, Any]) -> dict[str, Any]:
    """The small, JSON-friendly part of a dataset's metadata (drops per-demo records)."""
    keep = ("format", "source", "hand", "feature_set", "observation_blocks", "objects", "counts", "seed",
            "command", "success_rates", "script", "folder", "pairs_total", "pairs_used")
    out = {k: metadata[k] for k in keep if k in metadata}
    if isinstance(out.get("success_rates"), dict) and "overall" in out["success_rates"]:
        out["success_rates"] = {"overall": out["success_rates"]["overall"]}
    return out


def cmd_train_bc(args: argparse.Namespace) -> int:
    import torch

    from dexdrake.learn.bc import train_bc
    from dexdrake.learn.demo_dataset import load_demo_dataset
    from dexdrake.learn.policy import DexRepNetPolicy

    check_run_kind(args.out, "BC")
    if (args.out / "bc_best.pt").is_file():
        raise DexdrakeError(f"{args.out} already holds a BC run (bc_best.pt); choose another --out or delete it")
    torch.set_num_threads(args.threads)
    data = load_demo_dataset(args.data)
    config = policy_config_from_metadata(data.metadata, data.actions.shape[1], data.observations.shape[1])
    policy = DexRepNetPolicy(config)
    policy.set_log_std_from_actions(data.actions)  # BC fits the mean only; RL explores at the demos' spread
    bc_config = settings_from_args(BCConfig, args)
    command = command_line(["train", "bc"], args, args.recorded_options)
    meta = {"command": command, "dataset": str(args.data), "dataset_metadata": dataset_summary(data.metadata),
            "scenario": _scenario_record(config.hand)}
    print(f"BC: {len(data)} samples, {config.obs_dim}-d observations {dict(config.blocks)}, {config.action_dim} actions")
    with WriterLock(args.out, f"the run folder {args.out}"):
        result = train_bc(policy, data, args.out, bc_config, meta)
    print(f"best epoch {result.best_epoch} (val loss {result.best_val_loss:.4g}); "
          f"checkpoints {result.best_checkpoint} and {result.last_checkpoint}; curves {result.log_csv.with_suffix('.png')}")
    return 0


def cmd_train_dapg(args: argparse.Namespace) -> int:
    from dexdrake.learn.dapg import load_demo_term, train_dapg
    from dexdrake.learn.policy import load_policy
    from dexdrake.learn.samplers import make_sampler
    from dexdrake.objects.library import training_objects
    from dexdrake.systems.env_factory import env_factory_for_policy

    check_run_kind(args.out, "DAPG")
    args.envs_per_worker = envs_per_worker(args)
    policy, init_meta = load_policy(args.init)
    policy.train()
    objects = training_objects(args.objects)
    demos = load_demo_term(args.demos, policy.config.obs_dim, policy.config.action_dim, args.demo_samples, args.seed)
    config = settings_from_args(DAPGConfig, args, rollouts_per_iteration=args.episodes_per_object * len(objects),
                                seed_groups=len(objects))
    factory = env_factory_for_policy(policy.config, objects, args.horizon, object_from_seed=True,
                                     task=TaskSpec(reward=config.reward))
    command = command_line(["train", "dapg"], args, args.recorded_options)
    meta = {"command": command, "init": str(args.init), "demos": str(args.demos),
            "init_sha256": hashlib.sha256(args.init.read_bytes()).hexdigest(),
            "dataset_metadata": dataset_summary(demos.metadata), "demo_pairs": len(demos), "objects": objects,
            "init_metadata": {k: v for k, v in init_meta.items() if k in ("command", "dataset", "epoch", "iteration")},
            "scenario": _scenario_record(policy.config.hand)}
    print(f"DAPG: {len(objects)} objects x {args.episodes_per_object} trajectories of {args.horizon} steps per iteration, "
          f"{len(demos)} demonstration pairs, {args.iterations} iterations, backend {args.backend} with "
          f"{args.workers} worker(s) x {args.envs_per_worker} env(s) in lockstep")
    with WriterLock(args.out, f"the run folder {args.out}"):
        sampler = make_sampler(factory, args.backend, args.workers, args.address, args.envs_per_worker)
        try:
            result = train_dapg(policy, sampler, args.out, config, demos, resume=args.resume, metadata=meta)
        finally:
            sampler.close()
    last = result.rows[-1] if result.rows else None
    summary = (f"; last iteration: return {last['mean_return']:.2f}, success {last['success_rate']:.2f}, "
               f"{last['env_steps']} env steps, {last['cpu_s'] / 3600:.3f} CPU-hours in all") if last else ""
    print(f"DAPG done at iteration {result.iterations_done}{summary}; curves {result.plot_png}, "
          f"manifest {args.out / 'dapg_manifest.json'}")
    return 0


def cmd_train_dagger(args: argparse.Namespace) -> int:
    import torch

    from dexdrake.dexrep.feature_sets import observation_blocks
    from dexdrake.hands.description import load_hand
    from dexdrake.learn.dagger import train_dagger
    from dexdrake.objects.library import resolve_objects, training_objects
    from dexdrake.systems.env_factory import GraspEnvFactory
    from dexdrake.systems.reactive_grasp import ReactiveGrasp

    check_run_kind(args.out, "DAgger")
    objects = training_objects(args.objects)

    observation_blocks(load_hand(args.hand), args.feature_set)  # unknown names: refused before workers start
    torch.set_num_threads(args.threads)
    config = settings_from_args(DaggerConfig, args, envs_per_worker=envs_per_worker(args), backend=args.backend)
    command = command_line(["train", "dagger"], args, args.recorded_options)
    probes = resolve_objects("validation")[1] if args.probe_per_object else []
    meta = {"command": command, "scenario": _scenario_record(args.hand)}
    with WriterLock(args.out, f"the run folder {args.out}"):
        final = train_dagger(objects, args.out, GraspEnvFactory, ReactiveGrasp, config, meta,
                             args.address, probes, args.resume_changed)
    print(f"DAgger done: {final}; log {args.out / 'dagger_log.csv'}")
    return 0


def cmd_train_recipe(args: argparse.Namespace) -> int:
    import torch

    from dexdrake.learn.pipeline import Runtime, run_recipe, ship_run
    from dexdrake.learn.recipe import load_recipe
    from dexdrake.paths import models_dir
    from dexdrake.systems.env_factory import GraspEnvFactory, env_factory_for_policy
    from dexdrake.systems.reactive_grasp import ReactiveGrasp

    recipe = load_recipe(args.recipe)
    if args.ship and args.until is not None:
        raise DexdrakeError("--ship needs every stage (its test tables): leave out --until")
    torch.set_num_threads(args.threads)
    command = command_line(["train", "recipe", str(args.recipe)], args, args.recorded_options)
    runtime = Runtime(partial(GraspEnvFactory, perception=recipe.perception),
                      partial(env_factory_for_policy, perception=recipe.perception), ReactiveGrasp, args.workers,
                      args.backend, args.address, command, scenario=_scenario_record(recipe.hand, recipe.perception, "recipe field"))
    chosen = run_recipe(recipe, args.recipe, args.out, runtime, args.until)
    if args.until is not None:
        print(f"stopped after {args.until} (--until); re-run without it to go on")
        return 0
    print(f"recipe done: {chosen}; tables in {args.out / 'test'}")
    if args.ship:
        manifest = ship_run(recipe, args.out, args.weights or models_dir() / "weights", command)
        print(f"shipped {manifest.with_suffix('.pt')} and its manifest {manifest}")
    return 0


def cmd_train_retest(args: argparse.Namespace) -> int:
    from dexdrake.learn.retest import read_shipped, retest
    from dexdrake.perceived_pose import PerceptionModel
    from dexdrake.systems.env_factory import env_factory_for_policy

    shipped = read_shipped(args.policy)
    perception = PerceptionModel(**shipped.scenario.get("perception", {}))
    command = command_line(["train", "retest", str(args.policy)], args, args.recorded_options)
    metrics = retest(shipped, partial(env_factory_for_policy, perception=perception), args.workers, command,
                     args.episodes_per_object, envs_per_worker(args))
    print(f"re-tested {args.policy}: seen {metrics['seen']['average_pct']:.1f} %, unseen "
          f"{metrics['unseen']['average_pct']:.1f} %; rewrote {shipped.tables}_seen.md/_unseen.md (.csv) and "
          f"{shipped.manifest_path}")
    return 0
