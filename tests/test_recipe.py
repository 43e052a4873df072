"""`dexdrake train recipe`: a recipe is checked before any work, runs every stage end to end,
resumes without redoing a finished stage, and refuses a change a started stage reads."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dexdrake.cli import main
from dexdrake.errors import DexdrakeError
from dexdrake.eval.seeds import FIRST_TEST_SEED, FIRST_VALIDATION_SEED, check_evaluation_seeds
from dexdrake.learn import pipeline
from dexdrake.learn.policy import load_policy
from dexdrake.learn.recipe import changed_fields, load_recipe, recipe_dict, recipe_sha256, reads, stage_plan

pytestmark = pytest.mark.usefixtures("one_torch_thread")

RECIPES = Path(__file__).resolve().parents[1] / "configs" / "recipes"
TINY = RECIPES / "tiny.yaml"


@pytest.mark.parametrize("name", ["tiny", "adroit", "allegro_z1", "adroit_4f", "adroit_3f", "adroit_2f"])
def test_shipped_recipes_load(name):
    recipe = load_recipe(RECIPES / f"{name}.yaml")
    assert [s.name for s in stage_plan(recipe)][-2:] == ["choose", "test"]


@pytest.mark.parametrize("text, field", [
    ("dagger: {config: {epoch: 3}}", "dagger.config.epoch is unknown"),
    ("dagger: {config: {epochs: two}}", "dagger.config.epochs: expected int, got 'two'"),
    ("dagger: {config: {lr: true}}", "dagger.config.lr: expected float, got True"),
    ("dapg: [{config: {lam0: 0.1}}, {config: {seed_groups: 3}}]", "dapg.1.config.seed_groups is set by the pipeline"),
    ("dagger: {config: {workers: 4}}", "dagger.config.workers is set by the pipeline (--workers)"),
    ("dapg: [{config: {reward: best}}]", "dapg.0.config.reward: 'best' is not one of"),
    ("dagger: {config: {hand: shadow}}", "dagger.config.hand: 'shadow' is not one of"),
    ("dagger: {config: {arm_action: palm_pose}}", "dagger.config.arm_action: hand 'adroit' has no palm_pose arm action"),
    ("dagger: {config: {arm_action: ik}}", "dagger.config.arm_action: unknown arm action 'ik'"),
    ("test: {episodes_per_object: 0}", "test.episodes_per_object: need >= 1"),
    ("test: {episodes: 10}", "test.episodes is now test.episodes_per_object"),
    ("choose: {episodes: 3}", "choose.episodes is now choose.episodes_per_object"),
    ("dapg: [{per_object: 1}]", "dapg.0.per_object is now dapg.0.episodes_per_object"),
    ("choose: [1]", "recipe field choose: expected a mapping"),
    ("dagger: {objects: star}", "dagger.objects: ['star'] are held-out objects"),
    ("test: {unseen: no_such_thing}", "test.unseen: "),
])
def test_a_recipe_mistake_is_refused_in_one_line_before_any_work(tmp_path, capsys, text, field):
    path = tmp_path / "r.yaml"
    path.write_text(text)
    with pytest.raises(DexdrakeError, match="recipe field"):
        load_recipe(path)
    out = tmp_path / "run"
    assert main(["train", "recipe", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dexdrake train recipe: error: recipe field") and field in err and err.count("\n") == 1
    assert not out.exists()


def test_a_perception_model_the_control_loop_cannot_run_is_refused_in_one_line_before_any_work(tmp_path, capsys):
    path, out = tmp_path / "r.yaml", tmp_path / "run"
    path.write_text("perception: {period_s: 0.03}")  # frames between control steps
    assert main(["train", "recipe", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dexdrake train recipe: error: recipe field: perception.period_s (0.03) must be 0 or a whole "
                          "multiple of the control period (0.02)") and err.count("\n") == 1
    assert not out.exists()


def test_changed_fields_are_named_and_attributed_to_the_stages_that_read_them():
    old = recipe_dict(load_recipe(TINY))
    new = json.loads(json.dumps(old))
    new["dagger"]["config"]["epochs"] = 5
    new["dapg"].append(new["dapg"][0])
    changes = changed_fields(old, new)
    assert [c[0] for c in changes] == ["dagger.config.epochs", "dapg.1"] and changes[0][1:] == (1, 5)
    plan = {s.name: s for s in stage_plan(load_recipe(TINY))}
    assert reads(plan["dagger"], "dagger.config.epochs") and not reads(plan["expert"], "dagger.config.epochs")
    assert reads(plan["expert"], "dagger.config.hand") and reads(plan["choose"], "dapg.1")
    assert recipe_sha256(load_recipe(TINY)) == recipe_sha256(load_recipe(TINY))


def test_validation_and_test_blocks_are_reserved_and_apart():
    check_evaluation_seeds(FIRST_VALIDATION_SEED, 1000)
    check_evaluation_seeds(FIRST_TEST_SEED, 1000)
    assert FIRST_VALIDATION_SEED + 10**6 < FIRST_TEST_SEED


def test_until_names_a_stage_and_a_shipped_run_has_every_stage(tmp_path, capsys):
    out = tmp_path / "run"
    for extra, message in ((["--until", "train"], "--until 'train' is not a stage of this recipe; its stages: expert, "
                                                  "dagger, dapg1, choose, test"),
                           (["--until", "choose", "--ship"], "--ship needs every stage (its test tables)")):
        assert main(["train", "recipe", str(TINY), "--out", str(out), *extra]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1
    assert not out.exists()


def _files(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in sorted(folder.rglob("*")) if p.is_file()}


def test_tiny_recipe_runs_end_to_end_ships_resumes_and_refuses_an_early_change(tmp_path, capsys, monkeypatch):
    out, weights = tmp_path / "run", tmp_path / "weights"
    argv = ["train", "recipe", str(TINY), "--out", str(out), "--backend", "sequential", "--workers", "1"]

    def stop(*args):
        raise DexdrakeError("stopped")

    assert main([*argv, "--until", "expert"]) == 0  # a candidate run stops where it is told
    assert "stopped after expert (--until)" in capsys.readouterr().out
    assert (out / "expert" / "done.json").is_file() and not (out / "dagger").exists()
    with monkeypatch.context() as patch:  # stopped in the choice of iterate
        patch.setitem(pipeline.STAGES, "choose", stop)
        assert main(argv) == 2
    assert (out / "dapg1" / "done.json").is_file() and not (out / "choose" / "done.json").exists()
    capsys.readouterr()
    assert main([*argv, "--ship", "--weights", str(weights)]) == 0
    assert capsys.readouterr().out.count("done, skipped") == 3
    recipe = load_recipe(TINY)
    manifest = json.loads((weights / "tiny_policy.json").read_text())
    assert manifest["recipe"]["sha256"] == recipe_sha256(recipe) and manifest["recipe"]["settings"] == recipe_dict(recipe)
    assert [s["stage"] for s in manifest["stages"]] == ["expert", "dagger", "dapg1", "choose", "test"]
    assert all(s["command"].startswith(f"dexdrake train recipe {TINY}") for s in manifest["stages"])
    assert manifest["stages"][0]["settings"]["dagger.objects"] == "sphere_small,can_soda"
    dapg = manifest["stages"][2]
    assert dapg["settings"]["dapg.0"] == recipe_dict(recipe)["dapg"][0]
    assert dapg["config"]["rollouts_per_iteration"] == 2 and dapg["config"]["time_scale"] == 4 and dapg["env_steps"] == 8
    assert manifest["stages"][1]["config"]["workers"] == 1 and manifest["stages"][1]["config"]["backend"] == "sequential"
    assert manifest["metrics"]["seen"]["seed"] == FIRST_TEST_SEED and manifest["metrics"]["unseen"]["per_object"].keys() == {"star"}
    chosen = manifest["stages"][3]["chosen"]
    assert chosen["candidate"] == "dapg1/dapg_iter_0001.pt" and manifest["stages"][3]["policy_sha256"] == manifest["sha256"]
    validation = json.loads((out / "choose" / "dapg1_0001" / "eval_validation.json").read_text())
    assert validation["seed"] == FIRST_VALIDATION_SEED and validation["seeds_reserved_for_evaluation"]
    assert (weights / "tiny_policy.pt").read_bytes() == (out / "choose" / "chosen.pt").read_bytes()
    _, meta = load_policy(weights / "tiny_policy.pt")
    assert meta["updates"] == 1 and "validation seeds" in meta["selection"] and meta["recipe_stage"] == "dapg1"
    perception = recipe_dict(recipe)["perception"]  # the training scenario, its noise included, recorded
    assert perception["pose_noise_position_m"] == 0.02 and perception["latency_s"] == 0.04
    assert meta["scenario"]["perception"] == perception and manifest["scenario"] == meta["scenario"]
    assert load_policy(out / "dagger" / "dagger_policy.pt")[1]["scenario"] == meta["scenario"]
    for name in ("eval_tiny_seen.md", "eval_tiny_unseen.csv", "tiny_policy_expert.md", "tiny_policy_dagger.png",
                 "tiny_policy_dapg.csv", "tiny_policy_choice.png"):
        assert (weights / name).stat().st_size > 0, name
    assert "models/weights/tiny_policy.pt" in (weights / "eval_tiny_seen.md").read_text()

    before = _files(out)
    assert main(argv) == 0  # resumed: every stage finished, nothing redone
    assert capsys.readouterr().out.count("done, skipped") == 5 and _files(out) == before

    changed = tmp_path / "changed.yaml"
    changed.write_text(TINY.read_text().replace("    epochs: 1", "    epochs: 2").replace("tables: eval_tiny", "tables: x"))
    assert main(["train", "recipe", str(changed), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "dagger.config.epochs 1 (now 2) is read by started stage dagger" in err and "ship.tables" not in err
    assert _files(out) == before
    later = tmp_path / "later.yaml"  # a change no started stage reads goes on
    later.write_text(TINY.read_text().replace("tables: eval_tiny", "tables: eval_later"))
    assert main([*argv[:2], str(later), *argv[3:]]) == 0
    assert "no started stage reads it: ship.tables" in capsys.readouterr().out


def test_more_dagger_iterations_go_on_from_the_last_one_until_a_later_stage_has_started(tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["--out", str(out), "--backend", "sequential", "--workers", "1"]
    assert main(["train", "recipe", str(TINY), *argv, "--until", "dagger"]) == 0
    first = (out / "dagger" / "data_00.npz").stat().st_mtime_ns
    longer = tmp_path / "longer.yaml"
    longer.write_text(TINY.read_text().replace("    iterations: 1\n    episodes_per_object: 1\n    horizon: 4\n    epochs",
                                               "    iterations: 2\n    episodes_per_object: 1\n    horizon: 4\n    epochs"))
    capsys.readouterr()
    assert main(["train", "recipe", str(longer), *argv, "--until", "dapg1"]) == 0
    assert "DAgger goes on from 1 to 2 iterations" in capsys.readouterr().out
    assert (out / "dagger" / "data_00.npz").stat().st_mtime_ns == first and (out / "dagger" / "policy_01.pt").is_file()
    done = json.loads((out / "dagger" / "done.json").read_text())
    assert done["config"]["iterations"] == 2 and [d["config"]["iterations"] for d in done["earlier"]] == [1]
    more = tmp_path / "more.yaml"  # DAPG has started from the 2-iteration policy: refused, the reason named
    more.write_text(longer.read_text().replace("    iterations: 2\n", "    iterations: 3\n"))
    assert main(["train", "recipe", str(more), *argv]) == 2
    err = capsys.readouterr().err
    assert "dagger.config.iterations 2 (now 3) is read by started stage dagger (more DAgger iterations go on only " \
           "while no later stage has started: dapg1 has)" in err and err.count("\n") == 1
    fewer = tmp_path / "fewer.yaml"
    fewer.write_text(TINY.read_text())
    assert main(["train", "recipe", str(fewer), *argv]) == 2
    assert "dagger.config.iterations 2 (now 1) is read by started stage dagger; restore" in capsys.readouterr().err


def _shipped(weights: Path, manifest: dict) -> Path:
    """A tiny Adroit policy in `weights` with `manifest` beside it (its sha256 and hand filled in)."""
    from dexdrake.dexrep.feature_sets import observation_blocks
    from dexdrake.hands.description import load_hand
    from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig, save_policy
    from dexdrake.learn.ship import sha256

    hand = load_hand("adroit")
    config = PolicyConfig.from_blocks(observation_blocks(hand, "Hand2obj"), len(hand.policy_joints),
                                      feature_set="Hand2obj", hand="adroit")
    weights.mkdir()
    path = save_policy(weights / "tiny_policy.pt", DexRepNetPolicy(config))
    manifest = {"policy": "models/weights/tiny_policy.pt", "sha256": sha256(path), "hand": "adroit", **manifest}
    path.with_suffix(".json").write_text(json.dumps(manifest))
    return path


def test_retest_rewrites_a_shipped_policys_tables_and_metrics_and_keeps_its_record(tmp_path, capsys):
    weights = tmp_path / "weights"
    trained = {"command": f"dexdrake train recipe {TINY} --ship", "note": "ran every stage"}
    policy = _shipped(weights, {"recipe": {"settings": recipe_dict(load_recipe(TINY))}, "stages": ["kept"],
                                "commands": [trained], "metrics": {"seen": {"average_pct": -1.0}}})
    for episodes in (1, 2):  # a second re-evaluation replaces the first one's command
        assert main(["train", "retest", str(policy), "--workers", "1", "--episodes-per-object", str(episodes)]) == 0
        assert "re-tested" in capsys.readouterr().out
        manifest = json.loads(policy.with_suffix(".json").read_text())
        assert manifest["stages"] == ["kept"] and manifest["commands"][0] == trained and len(manifest["commands"]) == 2
        assert manifest["commands"][1]["command"].startswith(f"dexdrake train retest {policy} --episodes-per-object "
                                                             f"{episodes}")
        seen, unseen = manifest["metrics"]["seen"], manifest["metrics"]["unseen"]
        assert seen["per_object"].keys() == {"sphere_small", "can_soda"} and unseen["per_object"].keys() == {"star"}
        assert seen["seed"] == unseen["seed"] == FIRST_TEST_SEED and seen["horizon"] == 4
        assert seen["episodes_per_object"] == episodes and seen["command"] == manifest["commands"][1]["command"]
    table = (weights / "eval_tiny_seen.md").read_text()
    assert "models/weights/tiny_policy.pt" in table and str(policy) not in table
    assert (weights / "eval_tiny_unseen.csv").stat().st_size > 0


def test_a_policy_shipped_before_recipes_is_retested_as_its_tables_were_made(tmp_path):
    from dexdrake.learn.recipe import TestStage
    from dexdrake.learn.retest import read_shipped

    made = {"episodes_per_object": 7, "horizon": 90}
    shipped = read_shipped(_shipped(tmp_path / "weights", {"commands": [], "metrics": {"seen": made, "unseen": made}}))
    assert shipped.test == TestStage("seen", "unseen", 7, 90) and shipped.tables == tmp_path / "weights" / "eval"
