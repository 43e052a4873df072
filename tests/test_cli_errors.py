"""Every sub-command answers a user's mistake with one line on stderr and exit status 2,
naming the offending flag or field, never with a traceback (run in-process: fast)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from dexdrake import argtypes
from dexdrake.cli import build_parser, main

NUMBER_TYPES = {"integer", "number"}
REAL_YAML = str(Path(__file__).resolve().parents[1] / "configs" / "real.yaml")  # argtypes' checked numeric types


def _leaves(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()):
    """(command words, parser) for every runnable sub-command."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield prefix, parser
        return
    for name, sub in subs[0].choices.items():
        yield from _leaves(sub, prefix + (name,))


LEAVES = list(_leaves(build_parser()))


def _run(argv, capsys) -> str:
    """Run the CLI; assert exit 2 and exactly one line on stderr without a traceback."""
    try:
        code = main(list(argv))
    except SystemExit as e:  # argparse's own errors
        code = e.code
    err = capsys.readouterr().err.strip()
    assert code == 2, (argv, code, err)
    assert "Traceback" not in err and len(err.splitlines()) == 1, (argv, err)
    assert err.startswith("dexdrake") and ": error: " in err, err
    return err


def test_every_sub_command_is_walked():
    names = {" ".join(words) for words, _ in LEAVES}
    assert {"sim", "retarget", "demos import", "objects remove", "eval", "train dagger",
            "hil"} <= names


@pytest.mark.parametrize("words, parser", LEAVES, ids=[" ".join(w) for w, _ in LEAVES])
def test_unknown_flag_and_bad_numbers(words, parser, capsys):
    _run([*words, "--no-such-flag"], capsys)
    for action in parser._actions:
        kind = getattr(action.type, "__name__", "")
        if not action.option_strings or kind not in NUMBER_TYPES:
            continue
        flag = action.option_strings[0]
        for bad in ("abc", "-1", "nan"):
            err = _run([*words, flag, bad], capsys)
            assert f"argument {flag}" in err, err


def test_number_types_name_the_problem():
    for parse, text, message in ((argtypes.seed, "-3", "at least 0"),
                                 (argtypes.count, "0", "at least 1"),
                                 (argtypes.count, "x", "an integer"),
                                 (argtypes.positive, "0", r"\(0, inf\]"),
                                 (argtypes.label, "a/b", "no slashes")):
        with pytest.raises(argparse.ArgumentTypeError, match=message):
            parse(text)


@pytest.fixture
def files(tmp_path, monkeypatch):
    monkeypatch.setenv("DEXDRAKE_DATA", str(tmp_path / "data"))
    monkeypatch.chdir(tmp_path)
    np.save(tmp_path / "zero.npy", np.zeros((5, 21, 3)))
    (tmp_path / "notes.txt").write_text("not keypoints")
    (tmp_path / "folder").mkdir()
    (tmp_path / "bad.yaml").write_text("hand: [unclosed")
    (tmp_path / "bad.json").write_text("{}")
    return tmp_path


BAD = [
    (["sim", "--horizon", "0"], "--horizon"),
    (["sim", "--time-step", "0.5"], "--time-step"),
    (["sim", "--time-step", "0.003"], "--time-step"),
    (["sim", "--seed", "-1"], "--seed"),
    (["sim", "--hand", "nohand"], "unknown hand"),
    (["sim", "--object", "noobject"], "unknown object"),
    (["sim", "--rrd", "folder"], "--rrd"),
    (["sim", "--config", "hil"], "is a hil scenario; `sim` needs simulated drivers"),
    (["sim", "--config", "missing.yaml"], "missing.yaml does not exist"),
    (["sim", "--policy", "p.pt"], "give --config"),
    (["sim", "--controller", "nope"], "unknown controller"),
    (["sim", "--config", "sim", "--object", "noobject"], "unknown object"),
    (["retarget", "missing.npy", "--hand", "allegro"], "no such file"),
    (["retarget", "notes.txt", "--hand", "allegro"], "not a demo or keypoint file"),
    (["retarget", "zero.npy", "--hand", "allegro"], "every frame is empty"),
    (["retarget", "zero.npy", "--hand", "nohand"], "unknown hand"),
    (["retarget", "zero.npy", "--hand", "allegro", "--out", "folder"], "--out"),
    (["retarget", "zero.npy", "--hand", "allegro", "--out", "notes.txt/x.npz"], "--out"),
    (["retarget", "zero.npy", "--hand", "allegro", "--fps", "0"], "--fps"),
    (["retarget", "zero.npy", "--hand", "allegro", "--units", "km"], "--units"),
    (["demos", "import", "zero.npy", "--out", "x.npz"], "every frame is empty"),
    (["demos", "import", "zero.npy", "--out", "x.npz", "--object-pose", "1,2,3"], "--object"),
    (["demos", "import", "zero.npy", "--out", "x.txt"], "--out"),
    (["demos", "synth", "--objects", "noobject", "--out", "o", "--demos-per-object", "0"],
     "--demos-per-object"),
    (["objects", "import", "missing.stl", "--name", "x"], "no such file"),
    (["objects", "import", "notes.txt", "--name", "Bad Name"], "invalid object name"),
    (["objects", "import", "notes.txt", "--name", "x", "--up-axis", "w"], "--up-axis"),
    (["objects", "import", "notes.txt", "--name", "x", "--scale", "-1"], "--scale"),
    (["objects", "remove", "nothing"], "unknown user object"),
    (["objects", "novelty", "--out", "novelty.txt"], "--out"),
    (["eval", "--policy", "missing.pt", "--label", "a/b"], "--label"),
    (["eval", "--policy", "missing.pt", "--out", "notes.txt"], "--out"),
    (["eval", "--policy", "missing.pt", "--rrd", "folder"], "--rrd"),
    (["eval", "--policy", "missing.pt", "--workers", "2", "--rrd", "e.rrd"], "--workers 1"),
    (["features", "show", "--object", "apple", "--rrd", "folder"], "--rrd"),
    (["hil", "--horizon", "0"], "--horizon"),
    (["hil", "--rrd", "folder"], "--rrd"),
    (["demo", "--seed", "-2"], "--seed"),
    (["demo", "--rrd", "folder"], "--rrd"),
    (["demos", "replay", "--hand", "adroit", "--demos", "d", "--out", "folder"], "--out"),
    (["encoder", "train", "--lr", "0"], "--lr"),
    (["real", "--config", "bad.yaml"], "bad.yaml"),
    (["real", "--config", REAL_YAML], "a real episode moves the robot and waits for the operator's Enter"),
    (["hil", "--config", "missing.yaml"], "missing.yaml"),
    (["eval", "--policy", "missing.pt"], "missing.pt"),
    (["train", "dagger", "--out", "o", "--hand", "nohand", "--objects", "can_soda"], "unknown hand"),
    (["train", "dagger", "--out", "o", "--objects", "can_soda,mug"], "held-out objects, kept for evaluation"),
    (["expert", "table", "--hand", "nohand"], "unknown hand"),
    (["expert", "table", "--objects", "noobject"], "unknown object"),
    (["expert", "table", "--controller", "nope"], "--controller"),
    (["expert", "table", "--out", "folder"], "--out"),
    (["expert", "table", "--out", "t.txt"], "--out"),
    (["expert", "choose", "--hand", "nohand"], "unknown hand"),
    (["expert", "choose", "--objects", "mug"], "unknown training object 'mug'"),
    (["expert", "choose", "--objects", "can_soda", "--out", "notes.txt"], "--out"),
    (["expert", "choose", "--objects", "can_soda", "--out", "bad.json"], "bad.json is not a readable expert grasp table"),
    (["features", "describe", "--hand", "nohand"], "unknown hand"),
]


@pytest.mark.parametrize("argv, names", BAD, ids=[" ".join(a) for a, _ in BAD])
def test_user_mistakes_are_one_line(files, capsys, argv, names):
    assert names in _run(argv, capsys)


def test_scenario_control_period_must_be_a_multiple_of_time_step():
    from dexdrake.systems.scenario import ScenarioError, is_multiple, parse_scenario

    assert is_multiple(0.02, 0.002) and is_multiple(0.02, 0.001) and is_multiple(0.02, 0.02)
    assert not is_multiple(0.02, 0.003) and not is_multiple(0.02, 0.5)
    with pytest.raises(ScenarioError, match="whole multiple of time_step"):
        parse_scenario("time_step: 0.003\ncontrol_period: 0.02", source="bad.yaml")
    parse_scenario("time_step: 0.001\ncontrol_period: 0.02", source="good.yaml")


def test_a_renamed_scenario_field_is_refused_naming_its_name_now(tmp_path, capsys):
    from dexdrake.systems.scenario import parse_scenario

    assert parse_scenario("real: {horizon: 7}").real.horizon == 7
    path = tmp_path / "old.yaml"
    path.write_text("real: {steps: 7}\n")
    assert _run(["real", "--config", str(path), "--dry-run"], capsys).endswith(
        f"{path}: field real.steps is now real.horizon")


def test_dagger_refuses_to_resume_a_folder_made_with_other_arguments(tmp_path, capsys):
    import json
    from dataclasses import asdict

    from dexdrake.learn.dagger import DaggerConfig

    out = tmp_path / "run"
    out.mkdir()
    meta = {"format": "x", "objects": ["can_soda", "can_soda"], "config": asdict(DaggerConfig(hand="adroit"))}
    np.savez(out / "data_00.npz", metadata=np.array(json.dumps(meta)))
    err = _run(["train", "dagger", "--out", str(out), "--hand", "allegro", "--objects", "can_soda,banana"], capsys)
    assert "hand 'adroit' (now 'allegro')" in err and "objects can_soda (now banana,can_soda)" in err
