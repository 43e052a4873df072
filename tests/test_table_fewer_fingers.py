"""scripts/table_fewer_fingers.py: Table II rows from recipe run folders."""

from __future__ import annotations

import json

import pytest


def _run(root, hand: str, wins: list[int], episodes: int = 10):
    """A finished recipe run folder with only what the table reads."""
    for stage in ("expert", "dagger", "test"):
        (root / stage).mkdir(parents=True)
    recipe = {"dagger": {"config": {"hand": hand, "iterations": 4, "episodes_per_object": 2, "horizon": 100,
                                    "epochs": 3}},
              "dapg": [{"objects": "train", "episodes_per_object": 1, "config": {"iterations": 10}}]}
    (root / "expert" / "done.json").write_text(json.dumps({"success_pct": 21.53, "episodes": 209, "wall_s": 0.0}))
    (root / "recipe.json").write_text(json.dumps({"recipe": recipe}))
    (root / "dagger" / "done.json").write_text(json.dumps({"objects": 53, "wall_s": 1800.0}))
    (root / "test" / "done.json").write_text(json.dumps({"command": f"dexdrake train recipe {hand}", "wall_s": 1800.0}))
    per_object = {f"obj{k}": {"successes": w, "episodes": episodes} for k, w in enumerate(wins)}
    report = {"feature_set": "DexRep+Vel", "objects": list(per_object), "episodes_per_object": episodes,
              "per_object": per_object}
    (root / "test" / "eval_unseen.json").write_text(json.dumps(report))
    return root


def test_rows_pool_episodes_with_wilson_interval_beside_the_paper(load_script, tmp_path):
    table = load_script("table_fewer_fingers")
    runs = [_run(tmp_path / "r4", "adroit_4f", [0, 0]), _run(tmp_path / "r2", "adroit_2f", [3, 4])]
    out = tmp_path / "table.md"
    assert table.main(["--runs", *map(str, runs), "--out", str(out)]) == 0
    rows = [line for line in out.read_text().splitlines() if line.startswith("| 2 ") or line.startswith("| 4 ")]
    # 7/20 pooled: Wilson 95 % 18.1-56.7 %; the paper's 2-finger row 9.0 / 38.3 / 68.8
    assert rows[0] == "| 2 | adroit_2f (DexRep+Vel) | 7/20 | 35.0 | 18.1-56.7 | 9.0 | 38.3 | 68.8 |"
    assert rows[1] == "| 4 | adroit_4f (DexRep+Vel) | 0/20 | 0.0 | 0.0-16.1 | 0.0 | 18.6 | 83.9 |"
    text = out.read_text()
    assert ("DAgger 4 iterations x 2 episodes x 53 objects (100 steps), 3 epochs/iteration; DAPG 10 iterations x 1 "
            "episode(s)/object; the expert grasps 21.5 % of 209 episodes on the DAgger objects; 1.00 h") in text
    assert "`dexdrake train recipe adroit_2f`" in text


def test_wilson_interval_known_value(load_script):
    table = load_script("table_fewer_fingers")
    low, high = table.wilson_interval(7, 10)
    assert (low, high) == pytest.approx((0.3968, 0.8922), abs=1e-4)


def test_unfinished_run_is_one_line(load_script, tmp_path, capsys):
    table = load_script("table_fewer_fingers")
    assert table.main(["--runs", str(tmp_path), "--out", str(tmp_path / "t.md")]) == 2
    assert "has the run's test stage finished?" in capsys.readouterr().err
