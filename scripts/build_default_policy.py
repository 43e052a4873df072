"""Build the shipped default policy: DAgger with the expert (ReactiveGrasp) -> eval -> models/weights.

The whole pipeline from a recipe (expert, DAgger, DAPG stages, choice on validation seeds,
test tables, shipping) is `dexdrake train recipe`; this script ships runs made by hand.

    python scripts/build_default_policy.py [--work runs/default_policy] [--iterations 6] [--episodes-per-object 2]
        [--epochs 20] [--lr 1e-4] [--seen-episodes 2] [--unseen-episodes 5] [--workers 2]
        [--hand adroit] [--objects train] [--dagger DIR | --dapg DIR | --shipped] [--seeds validation|test]

Each stage is a real command (printed and recorded in the manifest) and is skipped when its
output already exists in --work (DAgger itself resumes per iteration; evaluations are kept per
policy file content, so another policy is evaluated afresh). The result:
models/weights/<hand>_dexrep_policy.pt (DAgger's chosen iterate), <hand>_dexrep_policy.json
(commands, seeds, data, feature set, compute, metrics) and the evaluation tables
eval_seen.md / eval_unseen.md with their .csv (eval_<hand>_seen.md ... for other hands than the Adroit);
"seen" means the training objects used.
Choices and shipping are measured apart: by default (`--seeds validation`) the policy is
evaluated on the validation seeds with the validation objects standing for the unseen ones,
into --work only, to choose between candidates; `--seeds test` evaluates the chosen one once
on the test seeds and the unseen objects and ships it with those tables. DAgger picks its
iterate by the best success on its own training rollouts. `--dagger DIR` evaluates and ships an existing DAgger output
folder (e.g. a long run resumed over several sessions) instead of running DAgger; the
manifest then records the commands that run's policy and log name. `--dapg DIR` evaluates and
ships a DAPG run's best policy (the highest mean return on its own rollouts), which must have
started from the shipped policy (by the sha256 it records) or be the run an earlier iterate of
which is shipped: the manifest keeps the training record, adds (or, for the same run, replaces)
the DAPG stage (config, sessions, env steps, CPU-hours) and copies its learning curves beside
the policy (<hand>_dexrep_policy_dapg.csv/.png; _dapg2... for a later DAPG run started from a
shipped DAPG policy). `--shipped` re-evaluates
the shipped policy with the current code (e.g. after a fix that changes the evaluation's
episodes) and rewrites its tables and metrics, keeping the manifest's training record.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

from dexdrake.eval.seeds import FIRST_TEST_SEED, FIRST_VALIDATION_SEED
from dexdrake.learn.ship import sha256, ship_eval_table
from dexdrake.objects.meshfile import write_atomic

ROOT = Path(__file__).resolve().parents[1]
DISPLAY = {sys.executable: "python", str(Path(sys.executable).with_name("dexdrake")): "dexdrake"}
EVAL_SEED = {"validation": FIRST_VALIDATION_SEED, "test": FIRST_TEST_SEED}  # first seed per --seeds
HELD_OUT = {"validation": "validation", "test": "unseen"}  # the held-out objects per --seeds
DATA_SOURCE = ("DAgger on the training objects: states visited by the expert (ReactiveGrasp) (iteration 0) and by "
               "the policy (later iterations), labelled by the expert (systems/reactive_grasp.py ReactiveGrasp); "
               "not the human-demo replay")


def run(cmd: list[str], done: Path, log: list[dict]) -> None:
    """Run `cmd` unless `done` exists; record the command and its wall time."""
    text = shlex.join([DISPLAY.get(w, w) for w in cmd])
    if done.exists():
        print(f"[skip, {done} exists] {text}")
        log.append({"command": text, "skipped": True})
        return
    print(f"[run] {text}", flush=True)
    start = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT)
    log.append({"command": text, "wall_s": round(time.perf_counter() - start, 1)})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("runs/default_policy"))
    parser.add_argument("--iterations", type=int, default=6)
    parser.add_argument("--episodes-per-object", type=int, default=2,
                        help="episodes per training object per DAgger iteration")
    parser.add_argument("--epochs", type=int, default=20, help="BC epochs after each DAgger iteration")
    parser.add_argument("--lr", type=float, default=1e-4)
    parser.add_argument("--seen-episodes", type=int, default=2, help="evaluation episodes per seen object")
    parser.add_argument("--unseen-episodes", type=int, default=5, help="evaluation episodes per held-out object")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--hand", default="adroit")
    parser.add_argument("--objects", default="train", help="'train' or comma-separated training object names")
    parser.add_argument("--seeds", choices=tuple(EVAL_SEED), default="validation",
                        help="validation: measure a candidate (nothing shipped); test: measure once and ship")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--dagger", type=Path, help="an existing DAgger output folder to evaluate and ship")
    mode.add_argument("--dapg", type=Path, help="a DAPG output folder (started from the shipped policy) to evaluate and ship")
    mode.add_argument("--shipped", action="store_true",
                      help="re-evaluate the shipped policy, keeping its manifest's training record")
    args = parser.parse_args()

    dexdrake = str(Path(sys.executable).with_name("dexdrake"))
    for option in ("work", "dagger", "dapg"):  # absolute: the eval commands run in the repository root
        if getattr(args, option) is not None:
            setattr(args, option, getattr(args, option).resolve())
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    dagger = args.dagger or work / "dagger"
    weights = ROOT / "models" / "weights"
    name = f"{args.hand}_dexrep_policy"
    target = weights / f"{name}.pt"
    log: list[dict] = []
    start = time.perf_counter()
    if args.dagger and not (dagger / "dagger_policy.pt").is_file():
        sys.exit(f"build_default_policy: error: {dagger} has no dagger_policy.pt")
    if (args.shipped or args.dapg) and not (target.is_file() and target.with_suffix(".json").is_file()):
        sys.exit(f"build_default_policy: error: no shipped {target} with its manifest")
    if args.dapg:  # a snapshot: a running DAPG may write a new best file while this evaluates and ships
        candidate = work / "dapg_policy_best.pt"
        if not (args.dapg / "dapg_policy_best.pt").is_file():
            sys.exit(f"build_default_policy: error: {args.dapg} has no dapg_policy_best.pt")
        write_atomic(candidate, (args.dapg / "dapg_policy_best.pt").read_bytes())
        check_dapg_started_from(args.dapg, candidate, target)
    if not (args.dagger or args.dapg or args.shipped):
        run([dexdrake, "train", "dagger", "--out", str(dagger), "--hand", args.hand, "--objects", args.objects,
             "--iterations", str(args.iterations), "--episodes-per-object",
             str(args.episodes_per_object), "--epochs", str(args.epochs), "--lr", str(args.lr), "--workers", str(args.workers),
             "--seed", "0"], dagger / "dagger_policy.pt", log)
    policy = target.relative_to(ROOT) if args.shipped else candidate if args.dapg else dagger / "dagger_policy.pt"
    seen = "seen" if args.objects == "train" else args.objects
    evals = work / "eval" / sha256(ROOT / policy)[:12]  # per policy content: a stale evaluation is never reused for another
    evals = evals / args.seeds
    for label, objects, episodes in (("unseen", HELD_OUT[args.seeds], args.unseen_episodes), ("seen", seen, args.seen_episodes)):
        run([dexdrake, "eval", "--policy", str(policy), "--objects", objects, "--label", label, "--episodes-per-object", str(episodes),
             "--seed", str(EVAL_SEED[args.seeds]), "--workers", str(args.workers), "--out", str(evals)],
            evals / f"eval_{label}.json", log)
    if args.seeds == "validation":
        averages = {label: json.loads((evals / f"eval_{label}.json").read_text())["average_pct"] for label in ("seen", "unseen")}
        print(f"validation (nothing shipped): seen {averages['seen']:.1f} %, validation objects {averages['unseen']:.1f} %; "
              f"tables in {evals}")
        return

    tables = "eval" if args.hand == "adroit" else f"eval_{args.hand}"
    if not args.shipped:
        write_atomic(target, policy.read_bytes())
    source = f"{policy} (a copy of {args.dapg / 'dapg_policy_best.pt'})" if args.dapg else policy
    note = "" if args.shipped else f"The evaluated file was {source}, copied byte for byte to models/weights/{name}.pt."
    metrics = {label: ship_eval_table(evals, label, policy, weights / f"{tables}_{label}.md",
                                      f"models/weights/{name}.pt", note) for label in ("seen", "unseen")}

    if args.shipped or args.dapg:
        manifest = json.loads(target.with_suffix(".json").read_text())
        kept = [c for c in manifest["commands"] if not c["command"].startswith(("dexdrake eval", "python scripts/build_default_policy.py"))]
        if args.dapg:
            sessions = add_dapg_stage(manifest, args.dapg, target, weights / name)
            kept = [c for c in kept if c not in sessions] + sessions
        manifest.update(commands=kept + log + [{"command": shlex.join(["python", *sys.argv])}], metrics=metrics)
    else:
        manifest = new_manifest(args, dagger, target, log, metrics, start)
    write_atomic(weights / f"{name}.json", (json.dumps(manifest, indent=1) + "\n").encode())
    print(f"wrote {target} ({target.stat().st_size / 1e6:.2f} MB), its manifest and eval tables; "
          f"seen {metrics['seen']['average_pct']:.1f} %, unseen {metrics['unseen']['average_pct']:.1f} %")


def shipped_dapg_entry(manifest: dict, dapg: Path) -> dict | None:
    """The manifest's record of the DAPG run in `dapg`, if the shipped policy came from it (its last stage)."""
    stages = manifest["training"].get("dapg", [])
    return stages[-1] if stages and stages[-1]["folder"] == str(dapg) else None


def check_dapg_started_from(dapg: Path, candidate: Path, target: Path) -> None:
    """Exit with one line unless `candidate` (a policy of the DAPG run in `dapg`) comes from a run
    that started from the shipped `target` (or from the run an earlier iterate of which is
    shipped), whose manifest's training record the shipped DAPG policy then inherits."""
    from dexdrake.errors import DexdrakeError
    from dexdrake.learn.policy import load_policy

    try:
        _, meta = load_policy(candidate)
    except DexdrakeError as exc:
        sys.exit(f"build_default_policy: error: {exc}")
    manifest = json.loads(target.with_suffix(".json").read_text())
    started = meta.get("init_sha256")  # None for a run made before it was recorded
    entry = shipped_dapg_entry(manifest, dapg)
    same = started in (None, entry["init_sha256"]) if entry else started == manifest["sha256"]
    if sha256(target) != manifest["sha256"] or not same:
        sys.exit(f"build_default_policy: error: {dapg} did not start from the shipped {target.name} "
                 f"(its init: {meta.get('init')}), whose training record the manifest would keep")


def add_dapg_stage(manifest: dict, dapg: Path, target: Path, stem: Path) -> list[dict]:
    """Record the DAPG run in `dapg` as a training stage of `manifest` (replacing its record of an
    earlier iterate of the same run; the manifest's sha256 becomes the shipped file's), copy its
    curves to `stem`_dapg.csv/.png (_dapg2... for a later stage); returns its sessions' commands."""
    from dexdrake.learn.policy import load_policy
    from dexdrake.objects.augment import augment_command

    run = json.loads((dapg / "dapg_manifest.json").read_text())
    _, meta = load_policy(target)
    training = manifest["training"]
    earlier = shipped_dapg_entry(manifest, dapg)
    if earlier:
        training["dapg"].remove(earlier)
    elif "dapg" in training:
        training["stages"] += "; then DAPG again from that policy"
    else:
        training["stages"] = training["stages"].replace("; no DAPG", "") + "; then DAPG (natural policy gradient with the DAgger data as its demonstration term)"
    stage = len(training.setdefault("dapg", [])) + 1
    curves = stem.with_name(f"{stem.name}_dapg{stage if stage > 1 else ''}")  # one pair of files per DAPG stage
    for suffix in (".csv", ".png"):
        write_atomic(curves.with_suffix(suffix), (dapg / f"dapg_log{suffix}").read_bytes())
    training["dapg"].append({
        "folder": str(dapg), "config": meta["dapg_config"], "demos": meta.get("dataset_metadata"),
        "init": meta.get("init"), "init_sha256": earlier["init_sha256"] if earlier else meta["init_sha256"],
        "chosen_update": meta.get("updates"), "chosen_because": "highest mean return on its own rollouts",
        "chosen_mean_return": meta.get("mean_return"), "iterations_done": run["iterations_done"],
        "env_steps": run["env_steps"], "cpu_hours": run["cpu_hours"], "cpu_note": run["cpu_note"], "seeds": run["seeds"],
        "curves": [f"models/weights/{curves.name}.csv", f"models/weights/{curves.name}.png"]})
    manifest["sha256"] = sha256(target)
    made_by = augment_command(meta.get("objects", []))
    objects = [{"command": made_by, "note": "makes the augmented objects the DAPG run trains on"}] if made_by else []
    return objects + [{"command": s["command"], "note": f"DAPG session from iteration {s['from_iteration']}"} for s in run["sessions"]]


def new_manifest(args: argparse.Namespace, dagger: Path, target: Path, log: list[dict], metrics: dict,
                 start: float) -> dict:
    """The manifest of a policy newly shipped from the DAgger folder `dagger`."""
    import torch

    from dexdrake.dexrep.pointnet import default_encoder_path
    from dexdrake.learn.curves import read_csv
    from dexdrake.learn.dagger import init_sha256
    from dexdrake.learn.policy import load_policy

    net, meta = load_policy(target)
    dagger_config = meta.get("dagger_config") or {}
    iterations = read_csv(dagger / "dagger_log.csv")
    samples = meta.get("samples") or next((int(r["samples_total"]) for r in iterations
                                           if int(r["iteration"]) == meta.get("iteration")), None)
    if args.dagger:
        log.insert(0, {"command": meta.get("command"), "note": f"the last command that ran DAgger in {dagger} "
                       "(earlier iterations may have run under the arguments their data files record)"})
    encoder = default_encoder_path()
    return {
        "policy": f"models/weights/{target.name}",
        "sha256": sha256(target),
        "hand": net.config.hand,
        "feature_set": net.config.feature_set,
        "observation_blocks": dict(net.config.blocks),
        "parameters": sum(p.numel() for p in net.parameters()),
        "pointnet_encoder": {"path": "models/weights/pointnet_encoder.pt", "sha256": sha256(encoder)},
        "training": {
            "stages": "DAgger (behaviour cloning on expert-labelled states, aggregated over iterations); no DAPG",
            "dagger": dagger_config,
            "init_sha256": init_sha256(dagger),  # the policy DAgger started from (its "init"), recorded then
            "iterations": iterations,
            "paper": "BC 150 epochs, batch 64, lr 1e-5 on retargeted human demos; then 500 DAPG iterations",
        },
        "dataset": {"source": DATA_SOURCE, "path": str(dagger), "objects": meta.get("objects", args.objects),
                    "chosen_iteration": meta.get("iteration"), "samples": samples,
                    "seeds": f"iteration i, episode k: {dagger_config.get('seed', 0)} * 10**6 + i * 10**4 + k, "
                             "every training object"},
        "commands": log + [{"command": shlex.join(["python", *sys.argv])}],
        "compute": {"cpu_cores": os.cpu_count(), "gpu": None, "torch_threads": "the DAgger command's --threads for the BC fits, 1 per rollout worker", "platform": platform.platform(),
                    "load_average_at_end": round(os.getloadavg()[0], 1), "note": "2 CPU cores shared with other jobs",
                    "pipeline_wall_s_this_run": round(time.perf_counter() - start, 1), "torch": torch.__version__},
        "metrics": metrics,
    }


if __name__ == "__main__":
    main()
