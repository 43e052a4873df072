"""A user's bad input, command family by command family: exit status 2 (130 for Ctrl-C), one
line on stderr naming the thing and the fix, and nothing written. The CLI runs in-process; a
new sub-command's --out/--rrd gets the same checks from `dexdrake.cli.check_outputs`."""

from __future__ import annotations

import json
import os
import pickle
import re
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from dexdrake.cli import main
from dexdrake.errors import DexdrakeError, UnknownNameError

PROGRESS = re.compile(r"\d+%\|")  # a tqdm progress bar's line
HAND_ACTIONS = 30  # Adroit's policy joints (checked against the hand description below)


def _tree(root: Path) -> dict[str, int]:
    """Every path under `root`, with its modification time if a file."""
    return {str(p.relative_to(root)): 0 if p.is_dir() else p.stat().st_mtime_ns for p in root.rglob("*")}


def _fails(argv: list[str], capsys, root: Path, code: int = 2, log: str = "") -> str:
    """Run the CLI; assert `code`, one stderr line without a traceback, nothing written under
    `root` (but the training log `log`, if given)."""
    before = _tree(root)
    try:
        got = main([str(a) for a in argv])
    except SystemExit as e:  # argparse's own errors
        got = e.code
    err = "\n".join(line for line in capsys.readouterr().err.replace("\r", "\n").splitlines()
                    if line.strip() and not PROGRESS.search(line))
    assert got == code, (argv, got, err)
    assert len(err.splitlines()) == 1 and "Traceback" not in err, (argv, err)
    assert err.startswith("dexdrake") and (": error: " in err or "interrupted" in err), err
    after = {k: v for k, v in _tree(root).items() if not log or not (k == log or log.startswith(k + os.sep))}
    assert after == before, (argv, sorted(set(after) ^ set(before)))
    return err


@pytest.fixture
def world(tmp_path, monkeypatch):
    """A working folder with inputs of every kind (good and damaged)."""
    from dexdrake.dexrep.feature_sets import observation_blocks
    from dexdrake.hands.description import load_hand
    from dexdrake.learn.demo_dataset import save_demo_dataset
    from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig, save_policy

    monkeypatch.setenv("DEXDRAKE_DATA", str(tmp_path / "data"))
    (tmp_path / "data").mkdir()  # made on demand by any command that lists objects
    monkeypatch.chdir(tmp_path)
    hand = load_hand("adroit")
    assert len(hand.policy_joints) == HAND_ACTIONS
    blocks = observation_blocks(hand, "Hand2obj")
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(64, sum(blocks.values()))).astype(np.float32)
    act = rng.uniform(-0.5, 0.5, size=(64, HAND_ACTIONS)).astype(np.float32)
    save_demo_dataset(tmp_path / "data.npz", obs, act, None,
                      {"hand": "adroit", "feature_set": "Hand2obj", "observation_blocks": blocks})
    (tmp_path / "trunc.npz").write_bytes((tmp_path / "data.npz").read_bytes()[:300])
    policy = DexRepNetPolicy(PolicyConfig.from_blocks(blocks, HAND_ACTIONS, feature_set="Hand2obj", hand="adroit"))
    save_policy(tmp_path / "policy.pt", policy)
    save_policy(tmp_path / "changed.pt", policy)  # not the file its manifest records
    (tmp_path / "changed.json").write_text(json.dumps({"sha256": "0" * 64, "hand": "adroit", "metrics": {}}))
    state = torch.load(tmp_path / "policy.pt", weights_only=True)
    next(v for v in state["state_dict"].values() if v.is_floating_point()).fill_(float("nan"))
    torch.save(state, tmp_path / "nan.pt")
    np.save(tmp_path / "zero.npy", np.zeros((5, 21, 3)))
    np.savez(tmp_path / "same.npz", keypoints=np.zeros((5, 21, 3)))
    (tmp_path / "notes.txt").write_text("not anything")
    (tmp_path / "folder").mkdir()
    (tmp_path / "demos").mkdir()
    (tmp_path / "time_step.yaml").write_text("time_step: fast\n")
    (tmp_path / "empty.yaml").write_text("")
    (tmp_path / "seed.yaml").write_text("seed: -1\n")
    return tmp_path


# -- every output, checked before any work ------------------------------------------------
# (command, flag, kind): kind "file" or "folder" is what the flag names
OUTPUTS = [
    (["sim"], "--rrd", ".rrd"),
    (["features", "show", "--object", "apple"], "--rrd", ".rrd"),
    (["demo"], "--rrd", ".rrd"),
    (["hil"], "--rrd", ".rrd"),
    (["parity"], "--out", ".md"),
    (["eval", "--policy", "policy.pt"], "--rrd", ".rrd"),
    (["eval", "--policy", "policy.pt"], "--out", "/"),
    (["demos", "import", "zero.npy"], "--out", ".npz"),
    (["demos", "synth", "--objects", "apple"], "--out", "/"),
    (["demos", "replay", "--hand", "adroit", "--demos", "demos"], "--out", ".npz"),
    (["retarget", "zero.npy", "--hand", "allegro"], "--out", ".npz"),
    (["retarget", "zero.npy", "--hand", "allegro"], "--rrd", ".rrd"),
    (["train", "bc", "--data", "data.npz"], "--out", "/"),
    (["train", "dagger", "--objects", "sphere_small"], "--out", "/"),
    (["train", "dapg", "--init", "policy.pt", "--demos", "data.npz"], "--out", "/"),
    (["encoder", "train"], "--out", ".pt"),
    (["expert", "table"], "--out", ".md"),
    (["expert", "choose"], "--out", ".json"),
    (["objects", "novelty"], "--out", ".md"),
]
BAD_PLACES = [("/proc/dexdrake_no/x", "cannot write to '/proc'"),  # unwritable even for root
              ("notes.txt/x", "is a file, not a folder")]          # a file where a folder is needed


@pytest.mark.parametrize("words, flag, kind", OUTPUTS, ids=[" ".join(w + [f]) for w, f, _ in OUTPUTS])
def test_every_output_is_checked_before_any_work(world, capsys, words, flag, kind):
    for place, message in BAD_PLACES:
        err = _fails([*words, flag, place + ("" if kind == "/" else kind)], capsys, world)
        assert f"argument {flag}" in err and message in err, err
    wrong = "notes.txt" if kind == "/" else "folder" + kind
    (world / wrong).mkdir(exist_ok=True) if kind != "/" else None
    err = _fails([*words, flag, wrong], capsys, world)
    assert ("is a file; give a folder" if kind == "/" else "is a folder; give a file name") in err, err


@pytest.mark.parametrize("argv, message", [
    (["retarget", "same.npz", "--hand", "allegro", "--out", "same.npz"], "--out same.npz is the input demo"),
    (["demos", "import", "same.npz", "--out", "same.npz"], "--out same.npz is the input file"),
    (["demos", "import", "same.npz", "--out", "./same.npz"], "is the input file"),
])
def test_an_output_equal_to_an_input_is_refused(world, capsys, argv, message):
    assert message in _fails(argv, capsys, world)


# -- writers of a named thing and run folders --------------------------------------------
@pytest.fixture
def live_pid():
    process = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    yield process.pid
    process.kill()
    process.wait()


@pytest.mark.parametrize("argv, folder", [
    (["objects", "import", "mesh.stl", "--name", "racer"], "data/objects"),
    (["train", "dagger", "--objects", "sphere_small", "--out", "run"], "run"),
    (["train", "bc", "--data", "data.npz", "--out", "run"], "run"),
    (["train", "dapg", "--init", "policy.pt", "--demos", "data.npz", "--out", "run"], "run"),
])
def test_a_second_writer_is_refused(world, capsys, live_pid, argv, folder):
    import trimesh

    trimesh.creation.box((0.05, 0.05, 0.05)).export(world / "mesh.stl")
    (world / folder).mkdir(parents=True)
    (world / folder / ".dexdrake.lock").write_text(f"{live_pid}\n")
    assert f"another dexdrake process (pid {live_pid})" in _fails(argv, capsys, world)


def test_a_stale_lock_is_taken_over_and_a_killed_import_cleaned(world):
    import trimesh

    from dexdrake.objects import store
    from dexdrake.objects.library import import_mesh
    from dexdrake.outputs import OutputError, WriterLock

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    root = store.user_root()
    root.mkdir(parents=True)
    (root / ".dexdrake.lock").write_text(dead.stdout)
    (root / ".racer.x1y2").mkdir()  # what a SIGKILLed import leaves
    trimesh.creation.box((0.05, 0.05, 0.05)).export(world / "mesh.stl")
    import_mesh(world / "mesh.stl", "racer")
    assert sorted(p.name for p in root.iterdir()) == ["racer"]  # lock released, temporaries gone
    with WriterLock(world / "run"):
        assert (world / "run" / ".dexdrake.lock").read_text().strip() == str(os.getpid())
    assert not (world / "run").exists()  # a folder the lock made and nothing was written into
    (world / "folder" / ".dexdrake.lock").write_text("1\n")  # held by pid 1, alive
    with pytest.raises(OutputError, match="pid 1"):
        with WriterLock(world / "folder"):
            pass


@pytest.mark.parametrize("argv, held", [
    (["train", "bc", "--data", "data.npz", "--out", "run"], "DAgger"),
    (["train", "bc", "--data", "data.npz", "--out", "run"], "DAPG"),
    (["train", "dagger", "--objects", "sphere_small", "--out", "run"], "BC"),
    (["train", "dagger", "--objects", "sphere_small", "--out", "run"], "DAPG"),
    (["train", "dapg", "--init", "policy.pt", "--demos", "data.npz", "--out", "run"], "BC"),
    (["train", "dapg", "--init", "policy.pt", "--demos", "data.npz", "--out", "run"], "DAgger"),
])
def test_a_run_folder_of_another_kind_is_refused(world, capsys, argv, held):
    from dexdrake.outputs import RUN_LOGS

    (world / "run").mkdir()
    (world / "run" / RUN_LOGS[held]).write_text("iteration\n")
    err = _fails(argv, capsys, world)
    assert f"--out run holds a {held} run ({RUN_LOGS[held]}); give this" in err, err


def test_a_changed_setting_on_an_existing_dagger_run_is_refused(world, capsys):
    from dataclasses import asdict, replace

    from dexdrake.learn.dagger import DaggerConfig, check_resume

    run = world / "run"
    run.mkdir()
    made = DaggerConfig(feature_set="Hand2obj", iterations=30)
    for it in (0, 1):
        meta = {"objects": ["sphere_small"], "config": asdict(made)}
        np.savez(run / f"data_{it:02d}.npz", metadata=np.array(json.dumps(meta)))
    err = _fails(["train", "dagger", "--out", run, "--objects", "sphere_small", "--feature-set", "Hand2obj",
                  "--iterations", "10"], capsys, world)
    assert "iterations 30 (now 10)" in err and "--resume-changed" in err
    check_resume(run, replace(made, iterations=10), ["sphere_small"], resume_changed=True)  # asked for: goes on
    check_resume(run, replace(made, workers=7, backend="sequential"), ["sphere_small"])  # where it runs: no change


# -- numbers: non-finite losses and weights, bounds --------------------------------------
@pytest.mark.parametrize("argv, message", [
    (["train", "bc", "--data", "data.npz", "--out", "run/bc", "--lr", "1e30", "--epochs", "3"], "loss is nan"),
    (["eval", "--policy", "nan.pt", "--objects", "apple", "--episodes-per-object", "1"], "non-finite weights"),
    (["train", "dagger", "--out", "run", "--objects", "sphere_small", "--feature-set", "Hand2obj", "--init", "nan.pt",
      "--backend", "sequential"], "non-finite weights"),
    (["train", "dapg", "--init", "nan.pt", "--demos", "data.npz", "--out", "run"], "non-finite weights"),
    (["encoder", "train", "--meshes", "primitives", "--lr", "1e30", "--epochs", "2", "--steps-per-epoch", "2",
      "--batch-size", "2", "--out", "enc.pt"], "the loss is"),
    (["objects", "augment", "--copies", "100000"], "at most 50"),
    (["objects", "augment", "--shapes", "5000"], "at most 999"),
    (["objects", "novelty", "--copies", "100000"], "at most 50"),
    (["sim", "--time-step", "1e-9"], "--time-step"),
    (["features", "show", "--object", "apple", "--horizon", "0"], "--horizon"),
    (["sim", "--horizon", "10001"], "argument --horizon: must be at most 10000"),
    (["features", "show", "--object", "apple", "--horizon", "1000000"], "argument --horizon: must be at most 10000"),
    (["demo", "--horizon", "10001"], "argument --horizon: must be at most 10000"),
    (["eval", "--policy", "policy.pt", "--episodes-per-object", "100000000"], "argument --episodes-per-object: must be at most 10000"),
    (["eval", "--policy", "policy.pt", "--horizon", "10001"], "argument --horizon: must be at most 10000"),
    (["eval", "--policy", "policy.pt", "--pose-noise", "0.02"], "argument --pose-noise: expected POS,ROT"),
    (["eval", "--policy", "policy.pt", "--pose-noise", "0.02,-1"], "argument --pose-noise: expected POS,ROT"),
    (["train", "dagger", "--out", "run", "--horizon", "99999"], "argument --horizon: must be at most 10000"),
    (["train", "dagger", "--out", "run", "--episodes-per-object", "99999"], "argument --episodes-per-object: must be at most 10000"),
    (["train", "dapg", "--init", "policy.pt", "--demos", "data.npz", "--out", "run", "--horizon", "99999"],
     "argument --horizon: must be at most 10000"),
    (["demos", "replay", "--hand", "adroit", "--demos", "demos", "--out", "r.npz", "--horizon", "99999"],
     "argument --horizon: must be at most 10000"),
    (["demos", "synth", "--objects", "apple", "--out", "demos", "--demos-per-object", "99999"],
     "argument --demos-per-object: must be at most 10000"),
    (["expert", "table", "--horizon", "10001"], "argument --horizon: must be at most 10000"),
    (["expert", "choose", "--episodes-per-object", "99999"], "argument --episodes-per-object: must be at most 10000"),
], ids=["bc-nan", "eval-nan", "dagger-init-nan", "dapg-init-nan", "encoder-nan", "augment-copies",
        "augment-shapes", "novelty-copies", "sim-time-step", "features-horizon", "sim-horizon", "features-horizon-bound", "demo-horizon",
        "eval-episodes-per-object", "eval-horizon", "eval-pose-noise-count", "eval-pose-noise-negative", "dagger-horizon", "dagger-episodes-per-object", "dapg-horizon",
        "replay-horizon", "synth-demos-per-object", "expert-table-horizon", "expert-choose-episodes-per-object"])
def test_numbers_that_would_lose_work_or_never_finish(world, capsys, argv, message, one_torch_thread):
    err = _fails(argv, capsys, world, log="run/bc/bc_log.csv")  # BC's log keeps the epochs it ran
    assert message in err, err


@pytest.mark.parametrize("words, flag", [(["sim"], "--horizon"), (["features", "show"], "--horizon"), (["demo"], "--horizon"),
                                         (["hil"], "--horizon"), (["real"], "--horizon"),
                                         (["ablations"], "--episodes-per-object"), (["eval"], "--episodes-per-object"), (["eval"], "--horizon"),
                                         (["train", "dagger"], "--horizon"), (["train", "dagger"], "--episodes-per-object"),
                                         (["train", "dapg"], "--horizon"), (["train", "dapg"], "--episodes-per-object"),
                                         (["demos", "replay"], "--horizon"), (["demos", "synth"], "--demos-per-object"),
                                         (["expert", "table"], "--horizon"), (["expert", "table"], "--episodes-per-object"),
                                         (["expert", "choose"], "--horizon"), (["expert", "choose"], "--episodes-per-object")])
def test_help_states_the_bound(capsys, words, flag):
    from dexdrake import argtypes

    with pytest.raises(SystemExit):
        main([*words, "--help"])
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps the help
    bound = argtypes.MAX_EPISODES if flag.endswith("-per-object") else argtypes.MAX_STEPS
    options = text[text.index("options:"):]
    after = options[options.index(flag + " "):]
    end = after.find(" --", len(flag))
    assert f"at most {bound})" in after[:None if end < 0 else end], after[:300]


@pytest.mark.parametrize("init, demos, objective", [("policy.pt", "huge.npz", "-inf"), ("big.pt", "data.npz", "nan")],
                         ids=["huge-demo-actions", "huge-policy-weights"])
def test_a_non_finite_dapg_objective_stops_with_nothing_written(world, capsys, one_torch_thread, init, demos, objective):
    from dexdrake.dexrep.feature_sets import observation_blocks
    from dexdrake.hands.description import load_hand
    from dexdrake.learn.demo_dataset import save_demo_dataset

    blocks = observation_blocks(load_hand("adroit"), "Hand2obj")
    obs = np.zeros((8, sum(blocks.values())), np.float32)
    huge = np.full((8, HAND_ACTIONS), 1e30, np.float32)  # finite, but its squared distance overflows
    save_demo_dataset(world / "huge.npz", obs, huge, None,
                      {"hand": "adroit", "feature_set": "Hand2obj", "observation_blocks": blocks})
    state = torch.load(world / "policy.pt", weights_only=True)
    for name, weights in state["state_dict"].items():  # finite weights whose actions overflow to nan
        if name.endswith("weight") and weights.is_floating_point():
            weights.fill_(1e30)
    torch.save(state, world / "big.pt")
    err = _fails(["train", "dapg", "--init", init, "--demos", demos, "--out", "run", "--objects", "sphere_small",
                  "--episodes-per-object", "1", "--horizon", "3", "--iterations", "1", "--backend", "sequential",
                  "--workers", "1"], capsys, world)
    assert f"DAPG iteration 0: the objective or its gradient is not finite (objective {objective})" in err, err


def test_a_retarget_config_field_that_is_no_number_is_named(world):
    import yaml

    from dexdrake.hands.description import load_hand
    from dexdrake.retarget.config import CONFIG_DIR, load_config

    hand = load_hand("allegro")
    shipped = yaml.safe_load((CONFIG_DIR / "allegro.yaml").read_text())
    for field, value, message in [("filter", "fast", "solver.filter must be a number, got 'fast'"),
                                  ("filter", 2.0, "solver.filter must be in (0, 1], got 2.0"),
                                  ("filter_speed", [1], "solver.filter_speed must be a number, got [1]"),
                                  ("iterations", "ten", "solver.iterations must be an integer, got 'ten'"),
                                  ("damping", None, "solver.damping must be a number, got None")]:
        config = {**shipped, "solver": {**(shipped.get("solver") or {}), field: value}}
        (world / "config.yaml").write_text(yaml.safe_dump(config))
        with pytest.raises(DexdrakeError) as err:
            load_config(hand, world / "config.yaml")
        assert str(err.value) == f"retarget config allegro: {message}"


def test_no_non_finite_policy_is_saved_and_the_bc_loss_check_stops_early(world):
    from dexdrake.errors import NonFiniteError
    from dexdrake.learn.policy import load_policy, save_policy

    policy, _ = load_policy(world / "policy.pt")
    with torch.no_grad():
        next(policy.parameters()).fill_(float("inf"))
    with pytest.raises(NonFiniteError, match="not finite"):
        save_policy(world / "bad.pt", policy)
    assert not (world / "bad.pt").exists()


# -- names, files and YAML fields --------------------------------------------------------
@pytest.mark.parametrize("argv, message", [
    (["objects", "import", "folder", "--name", "x"], "folder is a folder; give a mesh file"),
    (["retarget", "folder", "--hand", "allegro"], "folder is a folder; give a demo or keypoint file"),
    (["demos", "import", "folder", "--out", "x.npz"], "folder is a folder"),
    (["train", "bc", "--data", "folder", "--out", "run"], "folder is a folder; give a .npz file"),
    (["train", "dagger", "--out", "run", "--objects", "sphere_small", "--init", "folder"], "is a folder; give the .pt"),
    (["eval", "--policy", "folder"], "is a folder; give the .pt"),
    (["train", "retest", "folder"], "is a folder; give the .pt"),
    (["train", "retest", "policy.pt"], "policy.pt has no manifest policy.json beside it"),
    (["train", "retest", "changed.pt"], "changed.pt is not the file its manifest changed.json records"),
    (["hil", "--config", "folder"], "is a folder; give a .yaml file"),
    (["hil", "--config", "time_step.yaml"], "field time_step must be a number, got 'fast'"),
    (["hil", "--config", "empty.yaml"], "empty.yaml: the file holds nothing"),
    (["hil", "--config", "seed.yaml"], "seed must be at least 0, got -1"),
    (["parity", "--config", "sim"], "sim is a sim scenario; `parity` needs emulated drivers"),
    (["parity", "--objects", "bogus"], "unknown object 'bogus'"),
    (["train", "bc", "--data", "trunc.npz", "--out", "run"], "trunc.npz is not a readable .npz file, damaged"),
    (["train", "dapg", "--init", "policy.pt", "--demos", "trunc.npz", "--out", "run"], "trunc.npz is not a readable"),
    (["train", "dagger", "--out", "run", "--objects", "sphere_small", "--feature-set", "bogus"],
     "unknown feature set 'bogus'"),
    (["encoder", "train", "--meshes", "demos", "--out", "e.pt"], "holds 0 meshes"),
], ids=lambda v: v if isinstance(v, str) else " ".join(v[:2]))
def test_errors_name_the_thing_and_the_fix(world, capsys, argv, message):
    err = _fails(argv, capsys, world)
    assert message in err, err


def test_a_damaged_file_in_a_dagger_run_is_named(world, capsys):
    run = world / "run"
    run.mkdir()
    (run / "data_00.npz").write_bytes((world / "data.npz").read_bytes()[:300])
    err = _fails(["train", "dagger", "--out", run, "--objects", "sphere_small"], capsys, world)
    assert "data_00.npz is not a readable .npz file" in err


def test_an_unusable_demo_in_a_replay_folder_is_named(world, capsys):
    assert main(["demos", "synth", "--objects", "apple", "--out", "demos", "--demos-per-object", "1"]) == 0
    (good,) = (world / "demos").glob("*.npz")
    with np.load(good) as d:
        arrays = dict(d)
    np.savez(world / "demos" / "nan.npz", **{**arrays, "keypoints": np.full_like(arrays["keypoints"], np.nan)})
    np.savez(world / "demos" / "ghost.npz", **{**arrays, "object_name": np.array("noobject")})
    good.unlink()
    capsys.readouterr()
    assert main(["demos", "replay", "--hand", "adroit", "--demos", "demos", "--out", "r.npz"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert any("warning: skipping" in l and "nan.npz" in l for l in lines), lines
    assert any("warning: skipping" in l and "ghost.npz" in l and "unknown object" in l for l in lines), lines
    assert lines[-1].startswith("dexdrake demos replay: error: no demo-format") and not (world / "r.npz").exists()


def test_errors_in_worker_processes_keep_their_one_line():
    err = pickle.loads(pickle.dumps(UnknownNameError("feature set", "bogus", ["DexRep", "Hand2obj"])))
    assert isinstance(err, DexdrakeError) and str(err) == "unknown feature set 'bogus'; valid: DexRep, Hand2obj"


# -- library warnings and Ctrl-C ---------------------------------------------------------
def test_library_warnings_never_precede_the_error_line(world, capsys, monkeypatch):
    import dexdrake.cli.sim as sim

    def warn_then_fail(args):
        warnings.warn("a library's warning", UserWarning)
        raise DexdrakeError("the user's mistake")

    def to_stderr(message, category, filename, lineno, file=None, line=None):  # as outside pytest
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))

    monkeypatch.setattr(sim, "run_sim", warn_then_fail)
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = to_stderr
        assert "the user's mistake" in _fails(["sim"], capsys, world)


def test_ctrl_c_is_one_line_and_exit_130(world, capsys, monkeypatch):
    import dexdrake.cli.sim as sim

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(sim, "run_sim", interrupted)
    assert "dexdrake sim: interrupted" in _fails(["sim"], capsys, world, code=130)


@pytest.mark.slow
def test_ctrl_c_during_a_replay_with_workers(world):
    assert main(["demos", "synth", "--objects", "apple", "--out", "demos", "--demos-per-object", "4"]) == 0
    process = subprocess.Popen([sys.executable, "-m", "dexdrake.cli", "demos", "replay", "--hand", "adroit", "--demos",
                                "demos", "--out", "r.npz", "--workers", "2"], stderr=subprocess.PIPE, text=True,
                               start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    err = ""
    while "demo/s" not in err and process.poll() is None:  # the replay has started (its progress bar)
        err += process.stderr.read(1)
    time.sleep(1.0)  # into the first demo (each takes seconds)
    os.killpg(process.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the whole process group
    err += process.communicate(timeout=60)[1]
    lines = [line for line in err.replace("\r", "\n").splitlines() if line.strip() and not PROGRESS.search(line)]
    assert process.returncode == 130 and lines == [lines[0]] and "interrupted" in lines[0], err
    assert not (world / "r.npz").exists()


def _group_alive(pgid: int) -> list[int]:
    """Processes of process group `pgid` still running (zombies, dead but unreaped, excluded)."""
    alive = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            alive.append(int(stat.parent.name))
    return alive


def _interrupt(argv: list[str], cwd: Path, ready) -> tuple[int, list[str]]:
    """Run `dexdrake argv` in its own process group (SIGINT at its default, as in a terminal),
    send the group SIGINT once `ready()` holds; (exit status, stderr lines but progress bars).
    Asserts no process of the group outlives it."""
    process = subprocess.Popen([sys.executable, "-m", "dexdrake.cli", *argv], cwd=cwd, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True, start_new_session=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 180
    while not ready() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert process.poll() is None, "finished before the interrupt"
    os.killpg(process.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the whole process group
    err = process.communicate(timeout=120)[1]
    time.sleep(1)
    assert not _group_alive(process.pid), "a worker outlived the command"
    return process.returncode, [l for l in err.replace("\r", "\n").splitlines() if l.strip() and not PROGRESS.search(l)]


DAGGER_RUN = ["train", "dagger", "--out", "run", "--objects", "sphere_small", "--feature-set", "Hand2obj",
              "--iterations", "3", "--episodes-per-object", "1", "--horizon", "5", "--epochs", "1"]


@pytest.mark.slow
@pytest.mark.parametrize("backend", [["--backend", "process", "--workers", "2"], ["--backend", "sequential"]],
                         ids=["process", "sequential"])
def test_ctrl_c_during_dagger_then_it_resumes(world, backend):
    code, lines = _interrupt([*DAGGER_RUN, *backend], world, lambda: (world / "run" / "data_01.npz").exists())
    assert code == 130 and len(lines) == 1 and "dexdrake train dagger: interrupted" in lines[0], lines
    assert not (world / "run" / ".dexdrake.lock").exists()
    done = subprocess.run([sys.executable, "-m", "dexdrake.cli", *DAGGER_RUN, *backend], cwd=world,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    with open(world / "run" / "dagger_log.csv") as log:
        assert [row.split(",")[0] for row in log.read().splitlines()[1:]] == ["0", "1", "2"]


@pytest.mark.slow
def test_ctrl_c_during_dapg_with_workers(world):
    code, lines = _interrupt(["train", "dapg", "--init", "policy.pt", "--demos", "data.npz", "--out", "run", "--objects",
                              "sphere_small", "--episodes-per-object", "2", "--horizon", "20", "--iterations", "500",
                              "--workers", "2"], world, lambda: (world / "run" / "dapg_log.csv").exists())
    assert code == 130 and len(lines) == 1 and "dexdrake train dapg: interrupted" in lines[0], lines


@pytest.mark.slow
def test_ctrl_c_during_eval_with_workers(world):
    start = time.monotonic()
    code, lines = _interrupt(["eval", "--policy", "policy.pt", "--objects", "apple,sphere_small", "--episodes-per-object", "200",
                              "--workers", "2"], world, lambda: time.monotonic() > start + 15)
    assert code == 130 and len(lines) == 1 and "dexdrake eval: interrupted" in lines[0], lines


def test_a_broken_user_object_is_named_with_the_fix(world, capsys):
    import trimesh

    from dexdrake.objects.library import import_mesh
    from dexdrake.objects.meshfile import BrokenMeshFileError, load_obj

    trimesh.creation.box((0.05, 0.05, 0.05)).export(world / "mesh.stl")
    mesh = import_mesh(world / "mesh.stl", "boxy").mesh_path
    mesh.write_text("")
    err = _fails(["sim", "--object", "boxy", "--horizon", "1"], capsys, world)
    assert f"{mesh} holds no triangle mesh" in err and "objects import FILE --name NAME --overwrite" in err
    mesh.unlink()  # removed while a simulation uses it
    with pytest.raises(BrokenMeshFileError, match="is gone"):
        load_obj(mesh)
