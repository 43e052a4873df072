"""The evaluation protocol (reserved seeds, Wilson intervals, Table I layout), the demo's
measured rates, and `dexdrake train dapg` from DAgger data with --resume on the grasp env."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from dexdrake.cli import main
from dexdrake.episode import EpisodeResult
from dexdrake.errors import DexdrakeError
from dexdrake.eval.evaluate import EvalReport, evaluate_policy, wilson_interval
from dexdrake.eval.seeds import (CUSTOM_SEEDS, EVALUATION_SEEDS, FIRST_TEST_SEED, FIRST_VALIDATION_SEED, TEST_SEEDS,
                                 TRAINING_SEEDS, VALIDATION_SEEDS, check_evaluation_seeds, check_training_seeds)
from dexdrake.eval.tables import csv_table, markdown_table
from dexdrake.learn.curves import read_csv
from dexdrake.learn.dagger import DaggerData
from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig, load_policy, save_policy
from dexdrake.systems.env_factory import GraspEnvFactory, env_factory_for_policy

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TRAIN_OBJECTS = ("sphere_small", "can_soda")
UNSEEN_OBJECT = "star"


@pytest.fixture(scope="module")
def env_blocks() -> tuple[dict[str, int], int]:
    env = GraspEnvFactory("adroit", "Hand2obj", (TRAIN_OBJECTS[0],), horizon=3)()
    return dict(env.observation_blocks), env.action_dim


def _policy(path, blocks, action_dim, seed=0):
    torch.manual_seed(seed)
    config = PolicyConfig.from_blocks(blocks, action_dim, feature_set="Hand2obj", hand="adroit")
    return save_policy(path, DexRepNetPolicy(config))


# -- seeds and intervals -----------------------------------------------------------------------
def test_seed_ranges_are_disjoint_and_checked():
    assert TRAINING_SEEDS.stop == EVALUATION_SEEDS.start == CUSTOM_SEEDS.start
    assert CUSTOM_SEEDS.stop == VALIDATION_SEEDS.start and VALIDATION_SEEDS.stop == TEST_SEEDS.start
    assert TEST_SEEDS.stop == EVALUATION_SEEDS.stop < 2**31
    assert 1_000_000_100 + 9 in CUSTOM_SEEDS  # the blocks that chose earlier policies are neither
    assert check_evaluation_seeds(FIRST_VALIDATION_SEED, 10) == "validation"
    assert check_evaluation_seeds(FIRST_TEST_SEED, 10) == "test"
    assert check_evaluation_seeds(1_000_000_000, 10) == "custom"
    for first, count in ((900, 10), (EVALUATION_SEEDS.start - 1, 2), (VALIDATION_SEEDS.start - 1, 2),
                         (TEST_SEEDS.start - 1, 2), (EVALUATION_SEEDS.stop - 1, 2)):
        with pytest.raises(DexdrakeError, match="must lie in one of validation"):
            check_evaluation_seeds(first, count)
    check_training_seeds([0, TRAINING_SEEDS.stop - 1])
    with pytest.raises(DexdrakeError, match="below the validation"):
        check_training_seeds([TRAINING_SEEDS.stop])


@pytest.mark.parametrize("wins, n, low, high", [(0, 10, 0.0, 0.2775), (5, 10, 0.2366, 0.7634), (10, 10, 0.7225, 1.0),
                                                (1, 106, 0.00167, 0.0515)])
def test_wilson_interval_matches_reference_values(wins, n, low, high):
    got = wilson_interval(wins, n)
    assert got == pytest.approx((low, high), abs=2e-4)
    with pytest.raises(DexdrakeError):
        wilson_interval(3, 2)


def _report(seed: int) -> EvalReport:
    report = EvalReport("p.pt", "unseen", ["mug", "pear"], 10, seed, 100, command="dexdrake eval --policy p.pt",
                        hand="allegro_z1", feature_set="DexRep")
    for name, wins in (("mug", 5), ("pear", 0)):
        report.episodes += [EpisodeResult(name, seed + i, i < wins, 0.1, 100, 1.0) for i in range(10)]
    return report


def test_placement_interval_resamples_the_shared_placements():
    """Successes that follow the placement (the same seeds win on every object) are not 20
    independent trials: the interval over resampled seeds is wider than the pooled Wilson one,
    and the table says so; one seed per object gives none."""
    report = EvalReport("p.pt", "seen", ["mug", "pear"], 10, FIRST_TEST_SEED, 100)
    for name in ("mug", "pear"):
        report.episodes += [EpisodeResult(name, FIRST_TEST_SEED + i, i < 5, 0.1, 100, 1.0) for i in range(10)]
    (low, high), (w_low, w_high) = report.placement_ci95_pct(), report.average_ci95_pct()
    assert low < w_low and high > w_high and low < 50 < high
    assert low == report.placement_ci95_pct()[0]  # a fixed generator
    assert f"the average's 95 % interval is {low:.1f}-{high:.1f} %" in markdown_table(report)
    one = EvalReport("p.pt", "seen", ["mug"], 1, FIRST_TEST_SEED, 100,
                     episodes=[EpisodeResult("mug", FIRST_TEST_SEED, True, 0.1, 100, 1.0)])
    assert one.placement_ci95_pct() is None and "resampling them" not in markdown_table(one)


def test_table_gives_intervals_hand_and_the_seed_range():
    md = markdown_table(_report(FIRST_TEST_SEED))
    assert "| mug | 5/10 | 50.0 | 100.0 | 0.100 | 23.7-76.3 |" in md
    assert "| **average** | 5/20 | 25.0 | 83.9 | 0.100 | 11.2-46.9 |" in md
    assert "hand allegro_z1, features DexRep" in md and "test seeds (range [2000000000, 2100000000)" in md
    assert "validation seeds (range [1500000000, 2000000000)" in markdown_table(_report(FIRST_VALIDATION_SEED))
    assert "95 % Wilson interval 11.2-46.9 %" in md
    assert "NOT in the range reserved" in markdown_table(_report(900))
    assert csv_table(_report(FIRST_TEST_SEED)).splitlines()[0].endswith(",ci95_pct,category")
    assert "ended on a fault" not in md
    report = _report(FIRST_TEST_SEED)
    report.episodes[0].fault = "driver fault at step 7 (seed 1): overspeed: joint3 at 4.85 rad/s (...)"
    report.episodes[1].fault = "simulation diverged at step 9 (seed 2): the solver failed"
    report.episodes[2].fault = "driver fault at step 50 (seed 3): overspeed: joint4 at 5.00 rad/s (...)"
    assert ("- 3 of 20 episodes ended on a fault, each a failure: 2 driver fault (overspeed), 1 simulation "
            "diverged") in markdown_table(report)
    d = _report(1_000_000_100).to_dict()
    assert d["seeds_reserved_for_evaluation"] and d["seed_range"] == "custom" and d["per_object"]["pear"]["ci95_pct"][0] == 0.0


def test_eval_cli_defaults_to_validation_seeds_says_its_range_and_refuses_others(tmp_path, env_blocks, capsys):
    blocks, a = env_blocks
    path = _policy(tmp_path / "p.pt", blocks, a)
    assert main(["eval", "--policy", str(path), "--objects", UNSEEN_OBJECT, "--seed", "0"]) == 2
    assert "must lie in one of validation" in capsys.readouterr().err
    argv = ["eval", "--policy", str(path), "--objects", UNSEEN_OBJECT, "--episodes-per-object", "2", "--horizon", "3", "--out",
            str(tmp_path / "ev")]
    assert main(argv) == 0
    assert "validation range [1500000000, 2000000000)" in capsys.readouterr().out
    report = json.loads((tmp_path / "ev" / "eval_selected.json").read_text())
    assert report["seed"] == FIRST_VALIDATION_SEED and report["seed_range"] == "validation"
    assert report["hand"] == "adroit" and report["average_ci95_pct"][1] > 0
    command = report["command"]
    assert command.startswith("dexdrake eval --policy") and f"--seed {FIRST_VALIDATION_SEED}" in command
    assert main(command.split()[1:]) == 0  # the recorded command runs as written
    again = json.loads((tmp_path / "ev" / "eval_selected.json").read_text())
    assert [e["total_reward"] for e in again["episodes"]] == [e["total_reward"] for e in report["episodes"]]


def test_api_evaluation_reports_the_hand_of_the_policy(tmp_path, env_blocks):
    blocks, a = env_blocks
    path = _policy(tmp_path / "p.pt", blocks, a)
    report = evaluate_policy(path, env_factory_for_policy, [TRAIN_OBJECTS[0]], episodes=1, seed=7, horizon=2, progress=False)
    assert (report.hand, report.feature_set) == ("adroit", "Hand2obj") and not report.seeds_reserved()


# -- demo --------------------------------------------------------------------------------------
def test_demo_runs_any_object_and_prints_the_measured_rates(tmp_path, env_blocks, capsys):
    blocks, a = env_blocks
    path = _policy(tmp_path / "p.pt", blocks, a)
    rrd = str(tmp_path / "d.rrd")
    assert main(["demo", "--policy", str(path), "--object", UNSEEN_OBJECT, "--seed", "12", "--horizon", "2", "--rrd", rrd]) == 0
    out = capsys.readouterr().out
    assert f"object={UNSEEN_OBJECT} (unseen) seed=12" in out and "measured rates: none" in out
    metrics = {"seen": {"average_pct": 41.5, "average_ci95_pct": [38.0, 45.1], "per_object": {"x": {}, "y": {}},
                        "episodes_per_object": 10, "seed": 1000000000},
               "unseen": {"average_pct": 7.7, "per_object": {"x": {}}, "episodes_per_object": 10}}
    path.with_suffix(".json").write_text(json.dumps({"metrics": metrics}))
    assert main(["demo", "--policy", str(path), "--object", TRAIN_OBJECTS[1], "--horizon", "2", "--rrd", rrd]) == 0
    out = capsys.readouterr().out
    assert f"object={TRAIN_OBJECTS[1]} (train) seed=0" in out
    assert ("seen 41.5 % (95 % CI 38.0-45.1) over 2 objects x 10 episodes from seed 1000000000; "
            "unseen 7.7 % over 1 objects x 10 episodes") in out


# -- DAPG from DAgger data, stopped and resumed --------------------------------------------------
def test_train_dapg_from_dagger_data_resumes_where_it_stopped(tmp_path, env_blocks, capsys):
    blocks, a = env_blocks
    init = _policy(tmp_path / "init.pt", blocks, a)
    folder = tmp_path / "dagger"
    folder.mkdir()
    rng = np.random.default_rng(0)
    n = 40
    starts = np.zeros(n, bool)
    starts[0] = True
    DaggerData([TRAIN_OBJECTS[0]], np.array([0]), np.array([False]), starts, np.zeros((n, 3)),
               rng.normal(size=(n, sum(blocks.values()))).astype(np.float32),
               rng.uniform(-0.3, 0.3, (n, a)).astype(np.float32)).save(folder / "data_00.npz", {"iteration": 0})
    out = tmp_path / "dapg"
    argv = ["train", "dapg", "--init", str(init), "--demos", str(folder), "--out", str(out), "--episodes-per-object", "1",
            "--objects", ",".join(TRAIN_OBJECTS), "--horizon", "3", "--backend", "sequential", "--seed", "3"]
    assert main([UNSEEN_OBJECT if w == ",".join(TRAIN_OBJECTS) else w for w in argv]) == 2
    assert f"['{UNSEEN_OBJECT}'] are held-out objects" in capsys.readouterr().err
    assert main([*argv, "--iterations", "1"]) == 0
    assert main([*argv, "--iterations", "1"]) == 2  # a fresh start never overwrites a run
    assert "--resume" in capsys.readouterr().err
    assert main([*argv, "--iterations", "2", "--resume"]) == 0
    rows = read_csv(out / "dapg_log.csv")
    assert [int(r["iteration"]) for r in rows] == [0, 1] and [int(r["env_steps"]) for r in rows] == [6, 12]
    manifest = json.loads((out / "dapg_manifest.json").read_text())
    assert manifest["env_steps"] == 12 and manifest["cpu_hours"] > 0 and len(manifest["sessions"]) == 2
    assert manifest["sessions"][1]["command"].endswith("--resume --seed 3")
    assert manifest["metadata"]["demo_pairs"] == n and manifest["metadata"]["dataset_metadata"]["source"] == "dagger"
    policy, meta = load_policy(out / "dapg_policy_last.pt")
    assert meta["updates"] == 2 and meta["objects"] == list(TRAIN_OBJECTS)
    assert np.allclose(meta["initial_std"], np.clip(0.5 * np.load(folder / "data_00.npz")["labels"].std(0),
                                                    np.exp(-3), 1), rtol=1e-4)
    assert (out / "dapg_log.png").stat().st_size > 0
    per_object = read_csv(out / "dapg_objects.csv")  # one rollout per object and iteration, across the resume
    assert [(int(r["iteration"]), r["object"], int(r["rollouts"])) for r in per_object] == \
        [(k, name, 1) for k in (0, 1) for name in TRAIN_OBJECTS]
    assert [sum(int(r["successes"]) for r in per_object if int(r["iteration"]) == k) for k in (0, 1)] == \
        [round(len(TRAIN_OBJECTS) * float(r["success_rate"])) for r in rows]
    assert (out / "dapg_objects.png").stat().st_size > 0
