"""`dexdrake train recipe`: every stage of a `Recipe`, resumable, in one output folder.

OUT/recipe.json records the recipe (its settings and sha256); OUT/<stage>/ holds each
stage's outputs and, once it finished, done.json (its summary and the command that ran it).
A re-run skips finished stages and resumes a stopped one (DAgger and DAPG per iteration, the
choice of iterate per candidate). A changed recipe is refused, with the fields named, when a
changed field is read by a stage that has started; otherwise the new recipe is recorded and
the run goes on with it. One such change goes on too: more DAgger iterations, while no stage
after DAgger has started; DAgger then continues from its last iteration (its earlier ones kept,
their record in done.json's "earlier").

Stages: augment (optional) -> expert (the expert alone per DAgger object, on validation
seeds: expert_table.md/.csv) -> dagger (dagger_log.csv/.png) -> dapg1..n (each from the
previous stage's policy, DAgger's data as demonstrations: dapg_log.csv/.png,
dapg_objects.csv/.png) -> choose (every candidate iterate of the last training stage on the
validation seeds: choice.md/.csv/.png, chosen.pt) -> test (chosen.pt on the seen and unseen
objects at the test seeds: eval_seen/eval_unseen .md/.csv/.json). `ship_run` then copies the
policy, tables and curves into a weights folder with a manifest naming the recipe, its hash
and every stage's command and settings.

The concrete env factories and the expert come from the caller (`Runtime`), so the core
never imports the Drake systems.
"""

from __future__ import annotations

import json
import os
import platform
import re
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from dexdrake.errors import DexdrakeError
from dexdrake.eval.seeds import FIRST_TEST_SEED, FIRST_VALIDATION_SEED
from dexdrake.learn.dagger import MakeExpert
from dexdrake.learn.env_protocol import EnvFactory, MakeEnvFactory
from dexdrake.learn.recipe import (Recipe, StagePlan, TestStage, changed_fields, from_dict, reads, recipe_dict,
                                   recipe_sha256, stage_plan)
from dexdrake.learn.ship import sha256, ship_test_tables
from dexdrake.objects.meshfile import write_atomic

RECIPE_FILE = "recipe.json"
DONE_FILE = "done.json"
EARLIER_FILE = "done_earlier.json"  # a re-opened stage's earlier done.json records (a list)
EXTENDABLE = "dagger.config.iterations"  # a started run may grow it (open_run)


@dataclass(frozen=True)
class Runtime:
    """What the command line passes in: picklable env factories (under the recipe's
    perception model) and expert (systems/), the record of the training scenario, and where
    rollouts run."""

    make_env: MakeEnvFactory  # systems.env_factory.GraspEnvFactory
    env_for_policy: Callable[..., EnvFactory]  # systems.env_factory.env_factory_for_policy
    make_expert: MakeExpert  # systems.reactive_grasp.ReactiveGrasp
    workers: int = 2
    backend: str = "process"
    address: str | None = None
    command: str = ""  # the command line, recorded with every stage it finishes
    progress: bool = True
    scenario: dict[str, Any] = field(default_factory=dict)  # systems.scenario_record, in every checkpoint

    @property
    def eval_workers(self) -> int:
        """Evaluation worker processes (local; one with the sequential backend)."""
        return 1 if self.backend == "sequential" else self.workers


def _write_json(path: Path, data: Any) -> None:
    write_atomic(path, (json.dumps(data, indent=1, default=str) + "\n").encode())


def open_run(recipe: Recipe, source: Path, out: Path) -> None:
    """Record `recipe` in `out`, or check it against the recipe recorded there: a changed field
    that a started stage reads is refused (all such fields named)."""
    out.mkdir(parents=True, exist_ok=True)
    record = out / RECIPE_FILE
    now = recipe_dict(recipe)
    if record.is_file():
        old = json.loads(record.read_text())["recipe"]
        try:
            recorded = from_dict(Recipe, old)
        except DexdrakeError as err:
            raise DexdrakeError(f"{record}: {err}") from None
        changes = changed_fields(old, now)
        started = [s for s in stage_plan(recorded) if (out / s.name).is_dir()]
        refused = [(f, a, b, [s.name for s in started if reads(s, f)]) for f, a, b in changes]
        refused = [r for r in refused if r[3]]
        later = [s.name for s in started if s.name not in ("augment", "expert", "dagger")]
        extend = [r for r in refused if r[0] == EXTENDABLE and r[2] > r[1]]
        if extend and len(refused) == 1 and not later:
            _reopen(out / "dagger")
            print(f"DAgger goes on from {extend[0][1]} to {extend[0][2]} iterations", flush=True)
            refused = []
        if refused:
            hint = (f" (more DAgger iterations go on only while no later stage has started: {', '.join(later)} has)"
                    if extend else "")
            raise DexdrakeError(f"{out} was made with another recipe: " + "; ".join(
                f"{f} {json.dumps(a)} (now {json.dumps(b)}) is read by started stage {', '.join(s)}"
                for f, a, b, s in refused) + hint + "; restore those fields or use another --out")
        if not changes:
            return
        print(f"recipe changed where no started stage reads it: {', '.join(f for f, _, _ in changes)}", flush=True)
    _write_json(record, {"source": str(source), "sha256": recipe_sha256(recipe), "recipe": now})


def _reopen(folder: Path) -> None:
    """Mark a finished stage unfinished, its done.json kept in EARLIER_FILE."""
    done = folder / DONE_FILE
    if done.is_file():
        earlier = folder / EARLIER_FILE
        records = json.loads(earlier.read_text()) if earlier.is_file() else []
        _write_json(earlier, [*records, json.loads(done.read_text())])
        done.unlink()


def run_recipe(recipe: Recipe, source: Path, out: Path, runtime: Runtime, until: str | None = None) -> Path:
    """Run (or resume) every stage of `recipe` in `out`, or those up to the stage named `until`
    (e.g. "choose": the test seeds stay unused until the run is to be shipped); returns the
    chosen policy (choose/chosen.pt)."""
    from dexdrake.learn.samplers import check_backend

    plan = stage_plan(recipe)
    names = [stage.name for stage in plan]
    if until is not None and until not in names:
        raise DexdrakeError(f"--until {until!r} is not a stage of this recipe; its stages: {', '.join(names)}")
    check_backend(runtime.backend, runtime.address)
    open_run(recipe, source, out)
    if until is not None:
        plan = plan[: names.index(until) + 1]
    for k, stage in enumerate(plan):
        folder = out / stage.name
        if (folder / DONE_FILE).is_file():
            print(f"[{k + 1}/{len(plan)}] {stage.name}: done, skipped", flush=True)
            continue
        print(f"[{k + 1}/{len(plan)}] {stage.name}", flush=True)
        folder.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        summary = STAGES[_kind(stage)](recipe, stage, out, runtime)
        earlier = folder / EARLIER_FILE
        if earlier.is_file():
            summary["earlier"] = json.loads(earlier.read_text())
        _write_json(folder / DONE_FILE, {"stage": stage.name, "command": runtime.command,
                                         "wall_s": round(time.perf_counter() - start, 1), **summary})
    return out / "choose" / "chosen.pt"


def _kind(stage: StagePlan) -> str:
    return re.sub(r"\d+$", "", stage.name)


def _dapg_index(stage: StagePlan) -> int:
    return int(stage.name.removeprefix("dapg")) - 1


# ---------------------------------------------------------------------------------- stages
def run_augment(recipe: Recipe, stage: StagePlan, out: Path, rt: Runtime) -> dict[str, Any]:
    from dexdrake.objects.augment import build_augmented

    assert recipe.augment is not None
    names = build_augmented(recipe.augment.copies, recipe.augment.shapes)
    return {"objects": len(names)}


def run_expert(recipe: Recipe, stage: StagePlan, out: Path, rt: Runtime) -> dict[str, Any]:
    """The expert alone, `episodes_per_object` episodes per DAgger object from the first
    validation seed: expert_table.md/.csv (dexdrake.eval.expert's per-object table)."""
    from dexdrake.eval.expert import controller_table
    from dexdrake.learn.samplers import make_sampler
    from dexdrake.objects.library import get_object, training_objects

    objects = training_objects(recipe.dagger.objects)
    n = recipe.expert.episodes_per_object
    factory = rt.make_env(recipe.hand, None, tuple(objects), recipe.expert.horizon)
    with make_sampler(factory, rt.backend, rt.workers, rt.address) as sampler:
        table = controller_table(sampler, rt.make_expert, objects, {name: get_object(name).category for name in objects},
                                 FIRST_VALIDATION_SEED, n, recipe.expert.horizon, "expert")
    table.write(out / stage.name / "expert_table.md", f"The expert alone on the {recipe.hand} training objects",
                [f"{n} episodes per object of {recipe.expert.horizon} control steps, seeds {table.seeds_text()} "
                 f"(validation block); ms = CPU time per expert call. Made by `{rt.command}`."])
    return {"success_pct": round(table.success_pct(), 2), "episodes": len(objects) * n}


def run_dagger(recipe: Recipe, stage: StagePlan, out: Path, rt: Runtime) -> dict[str, Any]:
    from dexdrake.learn.curves import plot_curves
    from dexdrake.learn.dagger import train_dagger
    from dexdrake.objects.library import resolve_objects, training_objects

    objects = training_objects(recipe.dagger.objects)
    config = replace(recipe.dagger.config, workers=rt.workers, backend=rt.backend)
    probes = resolve_objects("validation")[1] if config.probe_per_object else []
    folder = out / stage.name
    final = train_dagger(objects, folder, rt.make_env, rt.make_expert, config,  # open_run lets a started run
                         {"command": rt.command, "recipe_stage": stage.name, "scenario": rt.scenario}, rt.address,
                         probes, resume_changed=True)  # differ only in more iterations
    plot_curves(folder / "dagger_log.csv", folder / "dagger_log.png", "iteration", ["success_rate", "val_loss"],
                title="DAgger")
    return {"policy": final.name, "objects": len(objects), "config": asdict(config)}


def stage_init(recipe: Recipe, index: int, out: Path) -> Path:
    """The policy DAPG stage `index` starts from: DAgger's chosen one, or the previous stage's best."""
    return out / "dagger" / "dagger_policy.pt" if index == 0 else out / f"dapg{index}" / "dapg_policy_best.pt"


def run_dapg(recipe: Recipe, stage: StagePlan, out: Path, rt: Runtime) -> dict[str, Any]:
    from dexdrake.learn.dapg import load_demo_term, train_dapg
    from dexdrake.learn.policy import load_policy
    from dexdrake.learn.samplers import make_sampler
    from dexdrake.objects.library import training_objects
    from dexdrake.task import TaskSpec

    index = _dapg_index(stage)
    spec, folder = recipe.dapg[index], out / stage.name
    init = folder / "init.pt"  # a copy: the run's start stays put whatever happens to its source
    if not init.is_file():
        write_atomic(init, stage_init(recipe, index, out).read_bytes())
    policy, init_meta = load_policy(init)
    policy.train()
    objects = training_objects(spec.objects)
    config = replace(spec.config, rollouts_per_iteration=spec.episodes_per_object * len(objects), seed_groups=len(objects),
                     time_scale=spec.horizon, progress=rt.progress)
    demos = load_demo_term(out / "dagger", policy.config.obs_dim, policy.config.action_dim, spec.demo_pairs,
                           config.seed)
    factory = rt.env_for_policy(policy.config, objects, spec.horizon, object_from_seed=True,
                                task=TaskSpec(reward=config.reward))
    meta = {"command": rt.command, "recipe_stage": stage.name, "scenario": rt.scenario, "init": str(init),
            "init_sha256": sha256(init),
            "demos": str(out / "dagger"), "dataset_metadata": demos.metadata, "demo_pairs": len(demos),
            "objects": objects, "init_metadata": {k: v for k, v in init_meta.items()
                                                  if k in ("command", "epoch", "iteration", "updates")}}
    with make_sampler(factory, rt.backend, rt.workers, rt.address) as sampler:
        result = train_dapg(policy, sampler, folder, config, demos, resume=True, metadata=meta)
    run = json.loads((folder / "dapg_manifest.json").read_text())
    return {"iterations_done": result.iterations_done, "env_steps": run["env_steps"], "cpu_hours": run["cpu_hours"],
            "config": asdict(config)}


def candidates(recipe: Recipe, out: Path) -> list[tuple[int, Path]]:
    """(iteration, policy file) of every candidate iterate of the last training stage, in order:
    the last DAPG stage's checkpoints and last policy, else DAgger's per-iteration policies."""
    if not recipe.dapg:
        return [(int(p.stem.split("_")[1]), p) for p in sorted((out / "dagger").glob("policy_[0-9][0-9].pt"))]
    folder = out / f"dapg{len(recipe.dapg)}"
    found = {int(p.stem.split("_")[-1]): p for p in sorted(folder.glob("dapg_iter_[0-9][0-9][0-9][0-9].pt"))}
    done = recipe.dapg[-1].config.iterations
    found.setdefault(done, folder / "dapg_policy_last.pt")
    return sorted(found.items())


def _evaluate(path: Path, objects: list[str], episodes: int, seed: int, horizon: int, label: str, folder: Path,
              env_for_policy: Callable[..., EnvFactory], workers: int, command: str, progress: bool = True,
              envs_per_worker: int = 1) -> dict[str, Any]:
    """evaluate_policy into folder/eval_<label>.* unless that evaluation is there; its report dict."""
    from dexdrake.eval.evaluate import evaluate_policy
    from dexdrake.eval.tables import write_report

    report_path = folder / f"eval_{label}.json"
    if not report_path.is_file():
        report = evaluate_policy(path, env_for_policy, objects, episodes, seed, workers, horizon, label=label,
                                 command=command, progress=progress, envs_per_worker=envs_per_worker)
        write_report(report, folder)
    return json.loads(report_path.read_text())


def evaluate_test(policy: Path, test: TestStage, folder: Path, env_for_policy: Callable[..., EnvFactory], workers: int,
                  command: str, progress: bool = True, envs_per_worker: int = 1) -> dict[str, float]:
    """`policy` on `test.seen` and `test.unseen` at the test seeds into folder/eval_seen|unseen.md/.csv/.json
    (an evaluation already there is kept); the average success (%) per label."""
    from dexdrake.objects.library import resolve_objects

    averages = {}
    for label, objects in (("seen", test.seen), ("unseen", test.unseen)):
        report = _evaluate(policy, resolve_objects(objects)[1], test.episodes_per_object, FIRST_TEST_SEED,
                           test.horizon, label, folder, env_for_policy, workers, command, progress, envs_per_worker)
        averages[label] = round(report["average_pct"], 2)
    return averages


SELECTION = ("the candidate iterate with the highest average success on the validation seeds (ties: the later one); "
             "candidates: the last training stage's checkpoints and last policy")


def run_choose(recipe: Recipe, stage: StagePlan, out: Path, rt: Runtime) -> dict[str, Any]:
    """Every candidate on the validation seeds; the highest average success is chosen (ties: later)."""
    from dexdrake.learn.curves import plot_curves, write_csv
    from dexdrake.learn.policy import load_policy, save_policy
    from dexdrake.objects.library import resolve_objects

    spec, folder = recipe.choose, out / stage.name
    _, objects = resolve_objects(spec.objects)
    n = spec.episodes_per_object
    rows = []
    for iteration, path in candidates(recipe, out):
        report = _evaluate(path, objects, n, FIRST_VALIDATION_SEED, spec.horizon, "validation",
                           folder / f"{path.parent.name}_{iteration:04d}", rt.env_for_policy, rt.eval_workers,
                           rt.command, rt.progress)
        low, high = report["average_ci95_pct"]
        rows.append({"iteration": iteration, "candidate": str(path.relative_to(out)),
                     "average_pct": round(report["average_pct"], 2), "ci95_low": round(low, 2),
                     "ci95_high": round(high, 2), "sha256": sha256(path)})
    best = max(rows, key=lambda r: (r["average_pct"], r["iteration"]))
    write_csv(folder / "choice.csv", list(rows[0]), rows)
    plot_curves(folder / "choice.csv", folder / "choice.png", "iteration", ["average_pct"],
                title="validation success per candidate")
    lines = ["# Choice of iterate", "",
             f"Each candidate on {len(objects)} objects x {n} episodes of {spec.horizon} steps, seeds "
             f"{FIRST_VALIDATION_SEED}..{FIRST_VALIDATION_SEED + n - 1} (validation block); chosen: the "
             f"highest average (ties: the later iterate). Made by `{rt.command}`.", "",
             "| iteration | candidate | average % | 95 % CI | chosen |", "|---|---|---|---|---|",
             *(f"| {r['iteration']} | {r['candidate']} | {r['average_pct']:.1f} | {r['ci95_low']:.1f}-"
               f"{r['ci95_high']:.1f} | {'**yes**' if r is best else ''} |" for r in rows), ""]
    write_atomic(folder / "choice.md", "\n".join(lines).encode())
    policy, meta = load_policy(out / best["candidate"])  # the policy alone (a DAPG checkpoint is a whole state)
    key = "updates" if recipe.dapg else "iteration"
    save_policy(folder / "chosen.pt", policy, {**meta, key: best["iteration"], "selection": SELECTION})
    return {"chosen": best, "candidates": len(rows), "objects": objects, "policy_sha256": sha256(folder / "chosen.pt")}


def run_test(recipe: Recipe, stage: StagePlan, out: Path, rt: Runtime) -> dict[str, Any]:
    """The chosen policy on the seen and unseen objects at the test seeds."""
    chosen = out / "choose" / "chosen.pt"
    averages = evaluate_test(chosen, recipe.test, out / stage.name, rt.env_for_policy, rt.eval_workers, rt.command,
                             rt.progress)
    return {"average_pct": averages, "policy_sha256": sha256(chosen)}


STAGES: dict[str, Callable[[Recipe, StagePlan, Path, Runtime], dict[str, Any]]] = {
    "augment": run_augment, "expert": run_expert, "dagger": run_dagger, "dapg": run_dapg, "choose": run_choose,
    "test": run_test}


# ---------------------------------------------------------------------------------- shipping
def _field(data: Any, dotted: str) -> Any:
    """The value at a dotted recipe field ("dagger.config.hand", "dapg.0") of a recipe dict."""
    for key in dotted.split("."):
        data = data[int(key)] if isinstance(data, list) else data[key]
    return data


def ship_run(recipe: Recipe, out: Path, weights: Path, command: str) -> Path:
    """Copy the finished run in `out` into `weights`: NAME.pt, its manifest NAME.json, the test
    tables TABLES_seen/_unseen.md/.csv, and NAME_expert.md/.csv, NAME_dagger.csv/.png,
    NAME_dapg{,2,..}.csv/.png and NAME_choice.md/.csv/.png; returns the manifest's path."""
    import torch

    from dexdrake.learn.policy import load_policy

    plan = stage_plan(recipe)
    missing = [s.name for s in plan if not (out / s.name / DONE_FILE).is_file()]
    if missing:
        raise DexdrakeError(f"{out}: stages {missing} have not finished; run the recipe to the end before shipping")
    name, chosen = recipe.policy_name, out / "choose" / "chosen.pt"
    target = weights / f"{name}.pt"
    write_atomic(target, chosen.read_bytes())
    shown = f"models/weights/{target.name}"
    note = f"The evaluated file was {chosen}, copied byte for byte to {shown}."
    metrics = ship_test_tables(out / "test", chosen, weights / recipe.tables_name, shown, note)
    copies = {"expert": ["expert/expert_table.md", "expert/expert_table.csv"],
              "dagger": ["dagger/dagger_log.csv", "dagger/dagger_log.png"],
              "choose": ["choose/choice.md", "choose/choice.csv", "choose/choice.png"]}
    for k in range(len(recipe.dapg)):
        copies[f"dapg{k + 1}"] = [f"dapg{k + 1}/dapg_log.csv", f"dapg{k + 1}/dapg_log.png"]
    files = {}
    for stage, paths in copies.items():
        suffix = {"dapg1": "dapg", "choose": "choice"}.get(stage, stage)
        files[stage] = []
        for rel in paths:
            shipped = weights / f"{name}_{suffix}{Path(rel).suffix}"
            write_atomic(shipped, (out / rel).read_bytes())
            files[stage].append(f"models/weights/{shipped.name}")
    net, net_meta = load_policy(target)
    record = json.loads((out / RECIPE_FILE).read_text())
    stages = []
    for stage in plan:
        done = json.loads((out / stage.name / DONE_FILE).read_text())
        settings = {prefix: _field(record["recipe"], prefix) for prefix in stage.reads}
        stages.append({**done, "settings": settings, "folder": str(out / stage.name), "files": files.get(stage.name, [])})
    manifest = {
        "policy": shown, "sha256": sha256(target), "hand": net.config.hand, "feature_set": net.config.feature_set,
        "observation_blocks": dict(net.config.blocks), "parameters": sum(p.numel() for p in net.parameters()),
        "scenario": net_meta["scenario"],
        "recipe": {"source": record["source"], "sha256": record["sha256"], "settings": record["recipe"]},
        "commands": [{"command": command, "note": "ran (or resumed) every stage of the recipe and shipped"}],
        "stages": stages,
        "seeds": {"validation": FIRST_VALIDATION_SEED, "test": FIRST_TEST_SEED,
                  "note": "the iterate was chosen on the validation block; the tables are the test block's"},
        "compute": {"cpu_cores": os.cpu_count(), "platform": platform.platform(), "torch": torch.__version__},
        "metrics": metrics,
    }
    path = weights / f"{name}.json"
    _write_json(path, manifest)
    return path
