"""Training/evaluation workflows: `dexdrake train bc|dapg`, `dexdrake eval`, `dexdrake demo`, tables."""

from __future__ import annotations

import csv
import hashlib
import json

import numpy as np
import pytest
import torch
from rrd_content import logged_rows

from dexdrake.cli import main
from dexdrake.episode import EpisodeResult, run_episode
from dexdrake.eval.evaluate import UNKNOWN_CATEGORY, EvalReport, evaluate_policy, object_categories, wilson_interval
from dexdrake.eval.paper import PAPER_UNSEEN
from dexdrake.eval.tables import category_rows, csv_from_markdown, csv_table, markdown_table, table_rows, write_report
from dexdrake.learn.curves import read_csv
from dexdrake.learn.demo_dataset import save_demo_dataset
from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig, load_policy, save_policy
from dexdrake.objects.library import list_objects, resolve_objects
from dexdrake.systems.env_factory import GraspEnvFactory, env_factory_for_policy
from dexdrake.systems.scripted_grasp import ScriptedGrasp
from dexdrake.task import TaskSpec

OBJECT = "sphere_small"


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def env_blocks() -> tuple[dict[str, int], int]:
    """Observation blocks and action size of the real Hand2obj Adroit grasp env."""
    env = GraspEnvFactory("adroit", "Hand2obj", (OBJECT,), horizon=3)()
    return dict(env.observation_blocks), env.action_dim


def _dataset(path, blocks, action_dim, n=96, metadata=None, seed=0):
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(n, sum(blocks.values()))).astype(np.float32)
    w = rng.normal(size=(obs.shape[1], action_dim)) * 0.05
    act = np.tanh(obs @ w).astype(np.float32)
    starts = np.zeros(n, bool)
    starts[:: n // 4] = True
    meta = {"hand": "adroit", "feature_set": "Hand2obj", "observation_blocks": blocks} if metadata is None else metadata
    return save_demo_dataset(path, obs, act, starts, meta)


def _random_policy(path, blocks, action_dim, seed=0):
    torch.manual_seed(seed)
    config = PolicyConfig.from_blocks(blocks, action_dim, feature_set="Hand2obj", hand="adroit", init_log_std=-1.0)
    return save_policy(path, DexRepNetPolicy(config))


# -- behaviour cloning ---------------------------------------------------------------------
def test_train_bc_cli_writes_checkpoints_and_curves(tmp_path, env_blocks):
    blocks, a = env_blocks
    data = _dataset(tmp_path / "d.npz", blocks, a)
    rc = main(["train", "bc", "--data", str(data), "--out", str(tmp_path / "bc"), "--epochs", "2", "--batch-size", "16",
               "--lr", "1e-3"])
    assert rc == 0
    for name in ("bc_best.pt", "bc_last.pt", "bc_log.csv", "bc_log.png"):
        assert (tmp_path / "bc" / name).is_file(), name
    policy, meta = load_policy(tmp_path / "bc" / "bc_last.pt")
    assert dict(policy.config.blocks) == blocks
    assert (policy.config.hand, policy.config.feature_set) == ("adroit", "Hand2obj")
    assert meta["dataset"] == str(data) and meta["command"].startswith("dexdrake train bc")
    assert len((tmp_path / "bc" / "bc_log.csv").read_text().strip().splitlines()) == 3  # header + 2 epochs


def test_train_bc_rejects_dataset_without_metadata(tmp_path, capsys):
    data = _dataset(tmp_path / "d.npz", {"hand": 3}, 2, metadata={})
    assert main(["train", "bc", "--data", str(data), "--out", str(tmp_path / "bc"), "--epochs", "1"]) == 2
    assert "observation_blocks" in capsys.readouterr().err


def test_train_bc_rejects_blocks_that_do_not_match_observations(tmp_path, capsys):
    meta = {"hand": "adroit", "feature_set": "Hand2obj", "observation_blocks": {"hand": 5}}
    data = _dataset(tmp_path / "d.npz", {"hand": 3}, 2, metadata=meta)
    assert main(["train", "bc", "--data", str(data), "--out", str(tmp_path / "bc"), "--epochs", "1"]) == 2
    assert "sum to 5" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [
    ["train", "bc", "--data", "x.npz", "--out", "o", "--epochs", "0"],
    ["train", "bc", "--data", "x.npz", "--out", "o", "--lr", "-1"],
    ["train", "bc", "--out", "o"],
    ["train", "dapg", "--init", "p.pt", "--demos", "d.npz", "--out", "o", "--backend", "gpu"],
    ["eval", "--policy", "p.pt", "--episodes-per-object", "zero"],
    ["demo", "--seed", "one"],
])
def test_cli_argument_errors_exit_with_usage(argv):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2


def test_the_train_flags_are_the_settings_dataclasses_fields(capsys):
    """Without flags `train bc|dagger|dapg` and `encoder train` make their settings
    dataclasses' defaults; a flag reaches its field (named apart, a path as a string)."""
    from dataclasses import replace

    from dexdrake.cli import build_parser
    from dexdrake.cli.flags import settings_from_args
    from dexdrake.dexrep.train_encoder import TrainConfig
    from dexdrake.learn.bc import BCConfig
    from dexdrake.learn.dagger import DaggerConfig
    from dexdrake.learn.dapg import DAPGConfig
    from dexdrake.learn.recipe import DaggerStage, DapgStage

    parse = build_parser().parse_args
    assert settings_from_args(BCConfig, parse(["train", "bc", "--data", "d.npz", "--out", "o"])) == BCConfig()
    assert settings_from_args(TrainConfig, parse(["encoder", "train"])) == TrainConfig()
    where = {"envs_per_worker": DaggerConfig.envs_per_worker, "backend": DaggerConfig.backend}
    args = parse(["train", "dagger", "--out", "o"])
    assert settings_from_args(DaggerConfig, args, **where) == DaggerConfig() and args.objects == DaggerStage.objects
    args = parse(["train", "dagger", "--out", "o", "--episodes-per-object", "3", "--init", "p.pt", "--prior", "a", "b",
                  "--residual-arm", "--weight-decay", "0.01"])
    assert settings_from_args(DaggerConfig, args, **where) == replace(
        DaggerConfig(), episodes_per_object=3, init="p.pt", prior=("a", "b"), residual_arm=True, weight_decay=0.01)
    args = parse(["train", "dapg", "--init", "p.pt", "--demos", "d.npz", "--out", "o"])
    assert settings_from_args(DAPGConfig, args) == DAPGConfig()
    assert (args.objects, args.episodes_per_object, args.demo_samples) == (DapgStage.objects, DapgStage.episodes_per_object,
                                                                              DapgStage.demo_pairs)
    args = parse(["train", "dapg", "--init", "p.pt", "--demos", "d.npz", "--out", "o", "--demo-weight", "0.2",
                  "--horizon", "50", "--reward", "aligned"])
    assert settings_from_args(DAPGConfig, args) == replace(DAPGConfig(), lam0=0.2, time_scale=50, reward="aligned")
    with pytest.raises(SystemExit):
        parse(["train", "--help"])
    listed = capsys.readouterr().out.splitlines()
    for command in ("bc", "dagger", "dapg", "recipe"):  # each with its one-line help
        assert any(line.split()[:1] == [command] and len(line.split()) > 1 for line in listed), listed


def test_cli_reports_missing_files_and_bad_objects(tmp_path, capsys):
    assert main(["train", "bc", "--data", str(tmp_path / "none.npz"), "--out", str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["eval", "--policy", str(tmp_path / "none.pt"), "--objects", "no_such_object"]) == 2
    assert "unknown object 'no_such_object'" in capsys.readouterr().err


# -- DAPG on the real grasp env ---------------------------------------------------------------
def test_train_dapg_two_iterations_on_grasp_env(tmp_path, env_blocks):
    blocks, a = env_blocks
    init = _random_policy(tmp_path / "init.pt", blocks, a)
    demos = _dataset(tmp_path / "d.npz", blocks, a, n=32)
    out = tmp_path / "dapg"
    argv = ["train", "dapg", "--init", str(init), "--demos", str(demos), "--out", str(out), "--iterations", "2",
            "--episodes-per-object", "2", "--objects", OBJECT, "--horizon", "4", "--backend", "sequential", "--seed", "3",
            "--demo-weight", "0.002", "--reward", "aligned"]
    assert main(argv) == 0
    rows = (out / "dapg_log.csv").read_text().strip().splitlines()
    assert len(rows) == 3 and rows[0].startswith("iteration,mean_return")
    weights = [float(r["demo_weight"]) for r in read_csv(out / "dapg_log.csv")]
    assert weights == pytest.approx([0.002, 0.002 * 0.95])  # lambda0 from --demo-weight, lambda1 the paper's
    for name in ("dapg_state.pt", "dapg_policy_last.pt", "dapg_policy_best.pt", "dapg_log.png"):
        assert (out / name).is_file(), name
    trained, meta = load_policy(out / "dapg_policy_last.pt")
    start, _ = load_policy(init)
    moved = [not torch.equal(trained.state_dict()[k], start.state_dict()[k]) for k in start.state_dict()]
    assert any(moved), "two NPG steps left every parameter unchanged"
    assert meta["objects"] == [OBJECT] and meta["updates"] == 2
    assert meta["dapg_config"]["reward"] == "aligned" and "--reward aligned" in meta["command"]
    started_from = hashlib.sha256(init.read_bytes()).hexdigest()
    assert meta["init_sha256"] == started_from
    _random_policy(init, blocks, a, seed=9)  # the init file changes (e.g. replaced by the run's result)
    assert main([*argv[:argv.index("--iterations") + 1], "3", *argv[argv.index("--iterations") + 2:], "--resume"]) == 0
    assert len((out / "dapg_log.csv").read_text().strip().splitlines()) == 4
    assert load_policy(out / "dapg_policy_last.pt")[1]["init_sha256"] == started_from  # the run's start, kept


def test_env_factory_builds_envs_with_its_task():
    env = GraspEnvFactory("adroit", "Hand2obj", (OBJECT,), horizon=3, task=TaskSpec(reward="aligned"))()
    env.reset(0)
    assert env.task.reward == "aligned" and env.tracker.spec.reward == "aligned"


def test_train_dapg_refuses_evaluation_splits(tmp_path, env_blocks, capsys):
    blocks, a = env_blocks
    init = _random_policy(tmp_path / "init.pt", blocks, a)
    demos = _dataset(tmp_path / "d.npz", blocks, a, n=32)
    argv = ["train", "dapg", "--init", str(init), "--demos", str(demos), "--out", str(tmp_path / "o"),
            "--objects", "unseen"]
    assert main(argv) == 2
    assert "evaluation splits" in capsys.readouterr().err


# -- evaluation --------------------------------------------------------------------------------
def _report(label: str, objects: list[str], wins: dict[str, int], n: int = 3) -> EvalReport:
    report = EvalReport("p.pt", label, objects, n, 10, 100, command="dexdrake eval --policy p.pt")
    for name in objects:
        report.episodes += [EpisodeResult(name, 10 + i, i < wins[name], 0.1 * (i < wins[name]), 100, 1.0)
                            for i in range(n)]
    return report


def test_table_has_paper_column_and_average():
    report = _report("unseen", ["mug", "pear", "pyramid_small"], {"mug": 3, "pear": 1, "pyramid_small": 0})
    rows = {r["object"]: r for r in table_rows(report)}
    assert rows["mug"]["ours_pct"] == "100.0" and rows["mug"]["paper_pct"] == "100.0"
    assert rows["pear"]["paper_pct"] == "" and rows["pear"]["ours_pct"] == "33.3"
    assert rows["pyramid_small"]["paper_pct"] == "3.3"
    assert rows["average"]["ours_pct"] == "44.4" and rows["average"]["paper_pct"] == "83.9"
    assert rows["average"]["successes"] == "4/9"
    md = markdown_table(report)
    assert "dexdrake eval --policy p.pt" in md and "seeds 10..12" in md and "`p.pt`" in md
    assert "| mug | 3/3 | 100.0 | 100.0 |" in md
    assert "ours 50.0 %, paper 51.6 %" in md  # mug + pyramid_small, the objects with a paper number
    lines = csv_table(report).strip().splitlines()
    assert lines[0] == "object,successes,ours_pct,paper_pct,mean_max_lift_m,ci95_pct,category"
    assert lines[4].startswith("average,4/9,44.4,83.9") and lines[5] == ",4/9,44.4,,,18.9-73.3,unknown"


def test_seen_table_uses_the_seen_average_only(tmp_path):
    report = _report("seen", ["mug", "banana"], {"mug": 1, "banana": 2}, n=2)
    rows = {r["object"]: r for r in table_rows(report)}
    assert rows["mug"]["paper_pct"] == "" and rows["average"]["paper_pct"] == "93.0"
    paths = write_report(report, tmp_path)
    assert paths["md"].name == "eval_seen.md" and paths["csv"].name == "eval_seen.csv"
    assert json.loads(paths["json"].read_text())["average_pct"] == 75.0
    # the csv, made from the markdown, holds the rows exactly; nothing else is left in the folder
    with open(paths["csv"], newline="") as f:
        assert list(csv.DictReader(f)) == ([{**r, "category": ""} for r in table_rows(report)]
                                           + [{"object": "", "paper_pct": "", "mean_max_lift_m": "", **r}
                                              for r in category_rows(report)])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eval_seen.csv", "eval_seen.json", "eval_seen.md"]
    with pytest.raises(ValueError, match="not an evaluation table"):
        csv_from_markdown("| feature set | obs dim |\n|---|---|\n| DexRep | 2601 |\n")


def test_tables_pool_the_episodes_of_each_category(tmp_path):
    """Objects of a category pool their episodes into one row (categories sorted), in the
    markdown, the CSV made from it and the json; an object the library lacks is 'unknown'."""
    objects = ["plate_dinner", "book_thin", "plate_side", "book_novel", "my_thing"]
    report = _report("seen", objects, {"plate_dinner": 1, "book_thin": 3, "plate_side": 0, "book_novel": 2,
                                       "my_thing": 3}, n=3)
    report.categories = object_categories(objects)
    assert report.categories == {"plate_dinner": "plate", "book_thin": "book", "plate_side": "plate",
                                 "book_novel": "book", "my_thing": UNKNOWN_CATEGORY}
    md = markdown_table(report)
    body = md[md.index("| category |"):]
    assert body.startswith("| category | successes | ours (%) | 95 % CI (%) |\n|---|---|---|---|\n"
                           "| book | 5/6 | 83.3 | 43.6-97.0 |\n| plate | 1/6 | 16.7 | 3.0-56.4 |\n"
                           "| unknown | 3/3 | 100.0 | 43.9-100.0 |\n")
    assert md.index("| **average** |") < md.index("| category |")
    paths = write_report(report, tmp_path)
    with open(paths["csv"], newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["object"] for r in rows[:6]] == [*objects, "average"] and all(r["category"] == "" for r in rows[:6])
    assert [(r["object"], r["category"], r["successes"], r["ours_pct"], r["ci95_pct"]) for r in rows[6:]] == [
        ("", "book", "5/6", "83.3", "43.6-97.0"), ("", "plate", "1/6", "16.7", "3.0-56.4"),
        ("", "unknown", "3/3", "100.0", "43.9-100.0")]
    saved = json.loads(paths["json"].read_text())
    assert saved["categories"] == report.categories
    assert {c: (r["objects"], r["successes"], r["episodes"]) for c, r in saved["per_category"].items()} == {
        "book": (["book_thin", "book_novel"], 5, 6), "plate": (["plate_dinner", "plate_side"], 1, 6),
        "unknown": (["my_thing"], 3, 3)}
    assert list(saved["per_category"]) == ["book", "plate", "unknown"]
    assert saved["per_category"]["plate"]["ci95_pct"] == pytest.approx([100 * x for x in wilson_interval(1, 6)])


def test_paper_numbers_cover_the_ten_namesakes_of_the_unseen_grab_objects():
    _, near = resolve_objects("near")
    assert set(PAPER_UNSEEN) <= set(near) and len(PAPER_UNSEEN) == 10
    assert abs(sum(PAPER_UNSEEN.values()) / 10 - 83.9) < 0.05


def test_resolve_objects():
    label, names = resolve_objects("seen")
    assert label == "seen" and len(names) == 53
    assert resolve_objects("mug, apple") == ("selected", ["mug", "apple"])
    for split in ("unseen", "validation", "near"):
        label, names = resolve_objects(split)
        assert label == split and names == [i.name for i in list_objects(split)] and names
    with pytest.raises(Exception, match="repeats"):
        resolve_objects("mug,mug")


def test_evaluate_policy_runs_seeded_episodes(tmp_path, env_blocks):
    blocks, a = env_blocks
    path = _random_policy(tmp_path / "p.pt", blocks, a)
    report = evaluate_policy(path, env_factory_for_policy, [OBJECT], episodes=2, seed=5, horizon=3, progress=False)
    assert [(e.object, e.seed, e.steps) for e in report.episodes] == [(OBJECT, 5, 3), (OBJECT, 6, 3)]
    assert report.average_pct() == 0.0  # 3 steps cannot hold the object for 50
    assert report.categories == {OBJECT: "sphere"} and list(report.per_category()) == ["sphere"]
    again = evaluate_policy(path, env_factory_for_policy, [OBJECT], episodes=2, seed=5, horizon=3, progress=False)
    assert [e.total_reward for e in again.episodes] == [e.total_reward for e in report.episodes]


def _scripted(env):
    """The scripted grasp as `run_episode`'s act: planned on the first step after reset."""
    controller = None

    def act(obs):
        nonlocal controller
        controller = controller or ScriptedGrasp(env)
        return env.normalise(controller(env))

    return act


def test_success_is_counted_on_a_real_grasp():
    env = GraspEnvFactory("adroit", "Hand2obj", ("sphere_medium",), horizon=150)()
    grasp = run_episode(env, _scripted(env), seed=0, horizon=150)
    hold = env.normalise(env.scene.hand.pregrasp_vector())
    still = run_episode(env, lambda obs: hold, seed=1, horizon=150)
    assert grasp.success and grasp.max_lift > 0.1, grasp
    assert not still.success and abs(still.max_lift) < 0.01, still
    assert (grasp.object, grasp.seed, grasp.steps) == ("sphere_medium", 0, 150)
    report = EvalReport("scripted", "selected", ["sphere_medium", "sphere_small"], 2, 0, 150, "")
    small = EpisodeResult("sphere_small", 0, still.success, still.max_lift, still.steps, still.total_reward)
    report.episodes = [grasp, still, small, small]
    rows = report.per_object()
    assert rows["sphere_medium"]["successes"] == 1 and rows["sphere_medium"]["success_pct"] == 50.0
    assert rows["sphere_small"]["successes"] == 0 and report.average_pct() == 25.0


# -- demo -------------------------------------------------------------------------------------
def test_demo_says_clearly_when_the_policy_file_is_missing(tmp_path, capsys):
    assert main(["demo", "--policy", str(tmp_path / "missing.pt")]) == 2
    err = capsys.readouterr().err
    assert "missing.pt not found" in err and "policy" in err


def test_demo_runs_a_policy_and_writes_a_recording(tmp_path, env_blocks, capsys):
    blocks, a = env_blocks
    path = _random_policy(tmp_path / "p.pt", blocks, a)
    rrd = tmp_path / "demo.rrd"
    assert main(["demo", "--policy", str(path), "--object", OBJECT, "--horizon", "3", "--rrd", str(rrd)]) == 0
    out = capsys.readouterr().out
    assert f"object={OBJECT}" in out and "steps=3" in out and "success=False" in out
    rows = logged_rows(rrd)
    assert all(rows[e] == 3 for e in ("/reward/total", "/task/lift", "/task/success")), rows
    assert rows["/world/object"] >= 3 and "/world/object/mesh" in rows and "/world/hand/palm" in rows


# -- scripted demos, re-featurised -------------------------------------------------------------
def test_refeaturised_scripted_states_match_online_observations(tmp_path):
    from dexdrake.systems.scripted_data import featurise, load_raw, record_object, save_raw

    raw = record_object("adroit", OBJECT, [7], horizon=4)
    assert raw.states.shape[0] == 4 and raw.episode_starts.tolist() == [True, False, False, False]
    assert np.all(np.abs(raw.actions) <= 1.0) and not raw.success[0]
    raw, _ = load_raw(save_raw(tmp_path / "raw.npz", raw, {"seeds": [7]}))
    obs, blocks = featurise(raw, "DexRep+Vel")  # the velocity group needs the recorded velocities
    env = GraspEnvFactory("adroit", "DexRep+Vel", (OBJECT,), horizon=4)()
    online = [env.reset(7)]
    for a in raw.actions[:-1]:
        online.append(env.step(a)[0])
    assert blocks == env.observation_blocks
    np.testing.assert_allclose(obs, np.asarray(online, dtype=np.float32), atol=1e-5)
    np.testing.assert_array_equal(featurise(raw, "DexRep+Vel", workers=2)[0], obs)  # worker processes: the same


def test_ou_action_noise_is_stationary_correlated_and_seeded():
    from dexdrake.eval.action_noise import OUActionNoise

    noise = OUActionNoise(4, std=0.1, rho=0.9, seed=3)
    x = np.array([noise.sample() for _ in range(20000)])
    assert x.std(0) == pytest.approx([0.1] * 4, rel=0.1)
    lag1 = np.mean([np.corrcoef(x[:-1, j], x[1:, j])[0, 1] for j in range(4)])
    assert lag1 == pytest.approx(0.9, abs=0.03)
    again = OUActionNoise(4, std=0.1, rho=0.9, seed=3)
    np.testing.assert_array_equal(again.sample(), x[0])
    for bad in ({"std": -0.1}, {"std": 0.1, "rho": 1.0}):
        with pytest.raises(Exception, match="noise"):
            OUActionNoise(4, **{"rho": 0.9, **bad})


def test_noisy_recording_executes_noise_but_labels_clean_expert_actions():
    from dexdrake.systems.scripted_data import record_object

    clean = record_object("adroit", OBJECT, [7], horizon=5)
    noisy = record_object("adroit", OBJECT, [7], horizon=5, noise=0.1, noise_seed=1)
    # The script is planned at reset, so its set-points do not depend on the noisy states:
    # the labels must be exactly the clean expert's while the visited states differ.
    np.testing.assert_array_equal(noisy.actions, clean.actions)
    np.testing.assert_array_equal(noisy.states[0], clean.states[0])
    assert np.abs(noisy.states[1:] - clean.states[1:]).max() > 1e-3
    same = record_object("adroit", OBJECT, [7], horizon=5, noise=0.1, noise_seed=1)
    np.testing.assert_array_equal(same.states, noisy.states)
    other = record_object("adroit", OBJECT, [7], horizon=5, noise=0.1, noise_seed=2)
    assert not np.array_equal(other.states, noisy.states)
    with pytest.raises(Exception, match="noise"):
        record_object("adroit", OBJECT, [7], horizon=2, noise=-0.1)


def test_early_lift_timing_grasps_within_the_evaluation_episode():
    from dexdrake.systems.scripted_data import EARLY_LIFT, record_object, timing_named

    assert timing_named("early_lift") == EARLY_LIFT
    with pytest.raises(Exception, match="early_lift"):
        timing_named("slow")
    raw = record_object("adroit", OBJECT, [1000], horizon=100, timing=EARLY_LIFT)
    assert raw.success.tolist() == [True] and len(raw.actions) == 100
