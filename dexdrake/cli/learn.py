"""CLI: `dexdrake train bc|dagger|dapg` and `dexdrake eval`.

Heavy imports (torch, pydrake) happen inside the commands so `--help` stays quick.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shlex
from functools import partial
from pathlib import Path
from typing import Any

from dexdrake import argtypes
from dexdrake.errors import DexdrakeError
from dexdrake.eval.seeds import FIRST_TEST_SEED, FIRST_VALIDATION_SEED, SEED_RANGES, check_evaluation_seeds, describe
from dexdrake.outputs import WriterLock, check_run_kind
from dexdrake.task import TARGET_THRESHOLDS, TaskSpec


def command_line(words: list[str], args: argparse.Namespace, options: list[str]) -> str:
    """The command with every option's effective value (for result tables and manifests)."""
    parts = ["dexdrake", *words]
    for opt in options:
        value = getattr(args, opt.replace("-", "_"))
        if isinstance(value, bool):
            parts += [f"--{opt}"] if value else []
        elif isinstance(value, list):
            parts += [f"--{opt}", *map(str, value)] if value else []
        elif value is not None:
            parts += [f"--{opt}", str(value)]
    return shlex.join(parts)


def _add_backend_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--backend", choices=("process", "ray", "sequential"), default="process",
                        help="where rollout workers run: local processes, Ray actors, or in this process")
    parser.add_argument("--address", help="Ray cluster to join (e.g. auto or HEAD_IP:6379; needs --backend ray; "
                        "default: a local Ray instance); see configs/ray_cluster.md")


def _add_envs_per_worker(parser: argparse.ArgumentParser, what: str, note: str = "") -> None:
    parser.add_argument("--envs-per-worker", type=argtypes.count, default=None,
                        help=f"{what} whose episodes a worker steps in lockstep, one policy call for all of them "
                             f"(default: dexdrake.learn.samplers.ENVS_PER_WORKER{note})")


def _envs_per_worker(args: argparse.Namespace) -> int:
    from dexdrake.learn.samplers import ENVS_PER_WORKER

    return args.envs_per_worker or ENVS_PER_WORKER


TRAINING_OBJECTS_HELP = ("'train', 'train+augmented' (with the scaled copies and shapes of `dexdrake objects augment`) or "
                         "comma-separated object names")


def _add_regularisation_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--weight-decay", type=argtypes.non_negative, default=0.0,
                        help="decoupled weight decay of the BC fits (AdamW; 0: Adam)")
    parser.add_argument("--obs-noise", type=argtypes.non_negative, default=0.0,
                        help="Gaussian noise on the BC fits' training inputs, in observation stds (0: none)")


def add_parser(subparsers) -> None:
    train = subparsers.add_parser("train", help="train a DexRepNet policy (behaviour cloning, DAPG)")
    train_sub = train.add_subparsers(dest="train_command", required=True)

    bc = train_sub.add_parser("bc", help="behaviour cloning from a demo dataset (.npz)")
    bc.add_argument("--data", required=True, type=Path, help="demo dataset .npz (metadata: hand, feature_set, observation_blocks)")
    bc.add_argument("--out", required=True, type=argtypes.output_folder, help="output folder (checkpoints, bc_log.csv/png)")
    bc.add_argument("--epochs", type=argtypes.count, default=150)
    bc.add_argument("--batch", type=argtypes.count, default=64)
    bc.add_argument("--lr", type=argtypes.positive, default=1e-5)
    _add_regularisation_options(bc)
    bc.add_argument("--seed", type=argtypes.seed, default=0)
    bc.add_argument("--threads", type=argtypes.count, default=1, help="torch CPU threads")
    bc.set_defaults(func=cmd_train_bc)

    dapg = train_sub.add_parser("dapg", help="DAPG fine-tuning of a BC or DAgger policy in the Drake grasp env")
    dapg.add_argument("--init", required=True, type=Path, help="policy checkpoint to start from (e.g. dagger_policy.pt)")
    dapg.add_argument("--demos", required=True, type=Path,
                      help="demonstration term: a demo dataset .npz or a DAgger output folder (its data_XX.npz)")
    dapg.add_argument("--demo-samples", type=argtypes.count, default=50000,
                      help="demonstration pairs kept (uniform, seeded), all used every iteration")
    dapg.add_argument("--demo-std-fraction", type=argtypes.positive,
                      help="fresh start: exploration std = this x the demo actions' std, per dimension "
                           "(default: dexdrake.learn.policy.DEMO_STD_FRACTION)")
    dapg.add_argument("--demo-weight", type=argtypes.positive,
                      help="the demonstration term's weight lambda0 at iteration 0, decaying by lambda1 per iteration "
                           "(default: dexdrake.learn.dapg.DAPGConfig.lam0, the paper's); a run started from a DAPG "
                           "policy may go on from its run's decayed weight")
    dapg.add_argument("--reward", choices=sorted(TARGET_THRESHOLDS), default=TaskSpec.reward,
                      help="paper: r_t as the paper writes it (full pay up to 0.22 m from the target); aligned: "
                           "Adroit relocate's 0.05/0.10 m radii, paying r_t only inside the success radius "
                           "(see dexdrake.task)")
    dapg.add_argument("--out", required=True, type=argtypes.output_folder, help="output folder (dapg_state.pt, checkpoints, curves)")
    dapg.add_argument("--iterations", type=argtypes.count, default=500)
    dapg.add_argument("--per-object", type=argtypes.episodes, default=10,
                      help=f"trajectories per object per iteration (at most {argtypes.MAX_EPISODES})")
    dapg.add_argument("--objects", default="train", help=TRAINING_OBJECTS_HELP)
    dapg.add_argument("--horizon", type=argtypes.steps, default=200,
                      help=f"control steps per trajectory (at most {argtypes.MAX_STEPS})")
    dapg.add_argument("--workers", type=argtypes.count, default=2)
    _add_envs_per_worker(dapg, "environments")
    _add_backend_options(dapg)
    dapg.add_argument("--resume", action="store_true", help="continue the run in OUT (dapg_state.pt) where it stopped")
    dapg.add_argument("--seed", type=argtypes.seed, default=0)
    dapg.set_defaults(func=cmd_train_dapg)

    dagger = train_sub.add_parser("dagger", help="DAgger with the state-driven grasp expert (no demo file needed)")
    dagger.add_argument("--out", required=True, type=argtypes.output_folder, help="output folder (per-iteration data and policies, dagger_log.csv)")
    dagger.add_argument("--hand", default="adroit")
    dagger.add_argument("--feature-set", default="DexRep")
    dagger.add_argument("--objects", default="train", help=TRAINING_OBJECTS_HELP)
    dagger.add_argument("--iterations", type=argtypes.count, default=6)
    dagger.add_argument("--per-object", type=argtypes.episodes, default=2,
                        help=f"episodes per object per iteration (at most {argtypes.MAX_EPISODES})")
    dagger.add_argument("--horizon", type=argtypes.steps, default=100,
                        help=f"control steps per episode (at most {argtypes.MAX_STEPS})")
    dagger.add_argument("--expert-noise", type=argtypes.float_in(0.0, 1.0, low_open=False), default=0.0,
                        help="DART-style correlated (OU) action-noise std on the expert's iteration 0 "
                             "(normalised action units; the labels stay clean)")
    dagger.add_argument("--epochs", type=argtypes.count, default=20, help="BC epochs after each iteration")
    dagger.add_argument("--lr", type=argtypes.positive, default=1e-4)
    _add_regularisation_options(dagger)
    dagger.add_argument("--arm-weight", type=argtypes.positive, default=1.0,
                        help="loss weight of the arm's action dimensions (the fingers' is 1)")
    dagger.add_argument("--probe-per-object", type=argtypes.int_at_least(0), default=0,
                        help="episodes per validation object per iteration, labelled but never trained on: the "
                             "log's unseen_success and unseen_loss (default 0: no probe)")
    dagger.add_argument("--init", type=Path, default=None,
                        help="policy checkpoint that drives iteration 0 and is fine-tuned (default: the expert drives)")
    dagger.add_argument("--prior", type=Path, nargs="+", default=[], metavar="DIR",
                        help="earlier DAgger runs' folders: their states, labelled anew by this expert, are trained on too")
    dagger.add_argument("--residual-arm", action="store_true",
                        help="a new network's arm actions are added to the arm's current position (it learns the lead)")
    dagger.add_argument("--resume-changed", action="store_true",
                        help="go on with a run in OUT whose settings (iterations, per-object, epochs, lr, ...) differ: "
                             "later iterations use the new ones; fewer --iterations choose dagger_policy.pt again "
                             "among the first ones (default: refused)")
    dagger.add_argument("--workers", type=argtypes.count, default=2)
    _add_envs_per_worker(dagger, "policy-driven environments")
    _add_backend_options(dagger)
    dagger.add_argument("--threads", type=argtypes.count, default=2, help="torch CPU threads for the BC fits")
    dagger.add_argument("--seed", type=argtypes.seed, default=0)
    dagger.set_defaults(func=cmd_train_dagger)

    recipe = train_sub.add_parser("recipe", help="every stage of a training recipe (expert table, DAgger, DAPG, choice "
                                  "on validation seeds, test evaluation), resumable; see configs/recipes/")
    recipe.add_argument("recipe", type=Path, help="recipe YAML (dexdrake.learn.recipe.Recipe)")
    recipe.add_argument("--out", required=True, type=Path, help="run folder (one subfolder per stage; re-run to resume)")
    recipe.add_argument("--ship", action="store_true", help="copy the policy, manifest, tables and curves to --weights")
    recipe.add_argument("--weights", type=Path, help="where --ship writes (default: the installed models/weights)")
    recipe.add_argument("--workers", type=argtypes.count, default=2)
    _add_backend_options(recipe)
    recipe.add_argument("--threads", type=argtypes.count, default=2, help="torch CPU threads for the BC fits")
    recipe.set_defaults(func=cmd_train_recipe)

    ev = subparsers.add_parser("eval", help="per-object success of a policy (the paper's Table I layout)")
    ev.add_argument("--policy", required=True, type=Path, help="policy checkpoint (.pt)")
    ev.add_argument("--objects", default="unseen",
                    help="'seen', 'unseen' (test), 'validation' (choices), 'near' (the earlier unseen set) or object names")
    ev.add_argument("--episodes", type=argtypes.episodes, default=10,
                    help=f"episodes per object (seeds S..S+N-1; at most {argtypes.MAX_EPISODES})")
    ev.add_argument("--seed", type=argtypes.seed, default=FIRST_VALIDATION_SEED,
                    help="first episode seed S (default: the first validation seed); the seeds must lie in one of "
                         + ", ".join(f"{n} {describe(r)}" for n, r in SEED_RANGES.items())
                         + f": validation for every choice, test (from {FIRST_TEST_SEED}) once per shipped policy")
    ev.add_argument("--workers", type=argtypes.count, default=1, help="worker processes")
    _add_envs_per_worker(ev, "objects (one environment each)", "; 1 with --rrd")
    ev.add_argument("--horizon", type=argtypes.steps, default=100,
                    help=f"control steps per episode (paper: 100; at most {argtypes.MAX_STEPS})")
    ev.add_argument("--out", type=argtypes.output_folder, help="folder for eval_<label>.md/.csv/.json")
    ev.add_argument("--label", type=argtypes.label, help="table label (default: seen, unseen or selected, from --objects)")
    ev.add_argument("--rrd", type=argtypes.output_file(".rrd"),
                    help="write a rerun recording of every episode to this .rrd file (one worker)")
    ev.set_defaults(func=cmd_eval)


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

    from dexdrake.learn.bc import BCConfig, train_bc
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
    bc_config = BCConfig(epochs=args.epochs, batch_size=args.batch, lr=args.lr, weight_decay=args.weight_decay,
                         obs_noise=args.obs_noise, seed=args.seed)
    command = command_line(["train", "bc"], args, ["data", "out", "epochs", "batch", "lr", "weight-decay", "obs-noise",
                                                    "seed", "threads"])
    meta = {"command": command, "dataset": str(args.data), "dataset_metadata": dataset_summary(data.metadata),
            "scenario": _scenario_record(config.hand)}
    print(f"BC: {len(data)} samples, {config.obs_dim}-d observations {dict(config.blocks)}, {config.action_dim} actions")
    with WriterLock(args.out, f"the run folder {args.out}"):
        result = train_bc(policy, data, args.out, bc_config, meta)
    print(f"best epoch {result.best_epoch} (val loss {result.best_val_loss:.4g}); "
          f"checkpoints {result.best_checkpoint} and {result.last_checkpoint}; curves {result.log_csv.with_suffix('.png')}")
    return 0


def cmd_train_dapg(args: argparse.Namespace) -> int:
    from dexdrake.learn.dapg import DAPGConfig, load_demo_term, train_dapg
    from dexdrake.learn.policy import DEMO_STD_FRACTION, load_policy
    from dexdrake.learn.samplers import make_sampler
    from dexdrake.objects.library import training_objects
    from dexdrake.systems.env_factory import env_factory_for_policy

    check_run_kind(args.out, "DAPG")
    args.envs_per_worker = _envs_per_worker(args)
    if args.demo_std_fraction is None:
        args.demo_std_fraction = DEMO_STD_FRACTION
    if args.demo_weight is None:
        args.demo_weight = DAPGConfig.lam0
    policy, init_meta = load_policy(args.init)
    policy.train()
    objects = training_objects(args.objects)
    demos = load_demo_term(args.demos, policy.config.obs_dim, policy.config.action_dim, args.demo_samples, args.seed)
    config = DAPGConfig(iterations=args.iterations, rollouts_per_iteration=args.per_object * len(objects),
                        seed_groups=len(objects), time_scale=args.horizon, seed=args.seed,
                        demo_std_fraction=args.demo_std_fraction, lam0=args.demo_weight, reward=args.reward)
    factory = env_factory_for_policy(policy.config, objects, args.horizon, object_from_seed=True,
                                     task=TaskSpec(reward=config.reward))
    command = command_line(["train", "dapg"], args, ["init", "demos", "demo-samples", "demo-std-fraction", "demo-weight",
                                                      "reward", "out",
                                                      "iterations", "per-object", "objects", "horizon", "workers",
                                                      "envs-per-worker", "backend", "address", "resume", "seed"])
    meta = {"command": command, "init": str(args.init), "demos": str(args.demos),
            "init_sha256": hashlib.sha256(args.init.read_bytes()).hexdigest(),
            "dataset_metadata": dataset_summary(demos.metadata), "demo_pairs": len(demos), "objects": objects,
            "init_metadata": {k: v for k, v in init_meta.items() if k in ("command", "dataset", "epoch", "iteration")},
            "scenario": _scenario_record(policy.config.hand)}
    print(f"DAPG: {len(objects)} objects x {args.per_object} trajectories of {args.horizon} steps per iteration, "
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
    from dexdrake.learn.dagger import DaggerConfig, train_dagger
    from dexdrake.objects.library import training_objects
    from dexdrake.systems.env_factory import GraspEnvFactory
    from dexdrake.systems.reactive_grasp import ReactiveGrasp

    check_run_kind(args.out, "DAgger")
    objects = training_objects(args.objects)

    observation_blocks(load_hand(args.hand), args.feature_set)  # unknown names: refused before workers start
    torch.set_num_threads(args.threads)
    config = DaggerConfig(hand=args.hand, feature_set=args.feature_set, iterations=args.iterations,
                          episodes_per_object=args.per_object, horizon=args.horizon, expert_noise=args.expert_noise,
                          epochs=args.epochs, lr=args.lr, weight_decay=args.weight_decay, obs_noise=args.obs_noise,
                          arm_weight=args.arm_weight,
                          workers=args.workers, envs_per_worker=_envs_per_worker(args), backend=args.backend,
                          seed=args.seed,
                          probe_per_object=args.probe_per_object, init=str(args.init or ""), prior=tuple(map(str, args.prior)),
                          residual_arm=args.residual_arm)
    command = command_line(["train", "dagger"], args, ["out", "hand", "feature-set", "objects", "iterations", "per-object",
                                                        "horizon", "expert-noise", "epochs", "lr", "weight-decay", "obs-noise",
                                                        "arm-weight", "probe-per-object",
                                                        "init", "prior", "residual-arm", "resume-changed", "workers", "envs-per-worker",
                                                        "backend", "address", "threads", "seed"])
    from dexdrake.objects.library import resolve_objects

    probes = resolve_objects("validation")[1] if args.probe_per_object else []
    meta = {"command": command, "scenario": _scenario_record(args.hand)}
    with WriterLock(args.out, f"the run folder {args.out}"):
        final = train_dagger(objects, args.out, GraspEnvFactory, ReactiveGrasp, config, meta,
                             args.address, probes, args.resume_changed)
    print(f"DAgger done: {final}; log {args.out / 'dagger_log.csv'}")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from dexdrake.eval.evaluate import evaluate_policy
    from dexdrake.eval.tables import markdown_table, write_report
    from dexdrake.objects.library import resolve_objects
    from dexdrake.systems.env_factory import env_factory_for_policy

    label, objects = resolve_objects(args.objects)
    label = args.label or label
    part = check_evaluation_seeds(args.seed, args.episodes)
    print(f"seeds {args.seed}..{args.seed + args.episodes - 1}: {part} range {describe(SEED_RANGES[part])}", flush=True)
    logger = None
    if args.rrd:
        if args.workers > 1:
            raise DexdrakeError("--rrd records in one process: use --workers 1")
        from dexdrake.systems.rerun_logger import RerunLogger

        logger = RerunLogger(args.rrd, "eval")
    try:
        report = evaluate_policy(args.policy, env_factory_for_policy, objects, args.episodes, args.seed, args.workers,
                                 args.horizon, label=label, record=None if logger is None else logger.hooks,
                                 envs_per_worker=_envs_per_worker(args),
                                 command=command_line(["eval"], args, ["policy", "objects", "episodes", "seed",
                                                                       "workers", "envs-per-worker", "horizon", "out",
                                                                       "label", "rrd"]))
    finally:
        if logger is not None:
            logger.close()
    print(markdown_table(report))
    if args.out:
        paths = write_report(report, args.out)
        print("wrote " + ", ".join(str(p) for p in paths.values()))
    low, high = report.average_ci95_pct()
    print(json.dumps({"average_pct": round(report.average_pct(), 2), "ci95_pct": [round(low, 2), round(high, 2)],
                      "episodes": len(report.episodes)}))
    return 0


def cmd_train_recipe(args: argparse.Namespace) -> int:
    import torch

    from dexdrake.learn.pipeline import Runtime, run_recipe, ship_run
    from dexdrake.learn.recipe import load_recipe
    from dexdrake.paths import models_dir
    from dexdrake.systems.env_factory import GraspEnvFactory, env_factory_for_policy
    from dexdrake.systems.reactive_grasp import ReactiveGrasp

    recipe = load_recipe(args.recipe)
    torch.set_num_threads(args.threads)
    command = command_line(["train", "recipe", str(args.recipe)], args,
                           ["out", "ship", "weights", "workers", "backend", "address", "threads"])
    runtime = Runtime(partial(GraspEnvFactory, perception=recipe.perception),
                      partial(env_factory_for_policy, perception=recipe.perception), ReactiveGrasp, args.workers,
                      args.backend, args.address, command, scenario=_scenario_record(recipe.hand, recipe.perception, "recipe field"))
    chosen = run_recipe(recipe, args.recipe, args.out, runtime)
    print(f"recipe done: {chosen}; tables in {args.out / 'test'}")
    if args.ship:
        manifest = ship_run(recipe, args.out, args.weights or models_dir() / "weights", command)
        print(f"shipped {manifest.with_suffix('.pt')} and its manifest {manifest}")
    return 0
