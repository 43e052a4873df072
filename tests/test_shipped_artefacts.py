"""The shipped tables agree with each other and with the weights they describe: each policy's
manifest, its evaluation tables (markdown and csv) and the README give the same numbers, the
ablation table's markdown and csv hold the same rows, and every command a table names parses as written."""

from __future__ import annotations

import argparse
import csv
import hashlib
import itertools
import json
import re
import shlex
import sys
from pathlib import Path

import pytest

from dexdrake.cli import build_parser
from dexdrake.eval.paper import PAPER_AVERAGE, PAPER_UNSEEN
from dexdrake.paths import models_dir

ROOT = Path(__file__).resolve().parents[1]
WEIGHTS = models_dir() / "weights"
POLICIES = {"adroit_dexrep_policy": "eval", "allegro_z1_dexrep_policy": "eval_allegro_z1",
            **{f"adroit_{n}f_dexrep_policy": f"eval_adroit_{n}f" for n in (4, 3, 2)}}


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def _table_rows(md: str) -> list[list[str]]:
    """The cells of the body rows of the first markdown table in `md` (header and rule skipped)."""
    lines = md.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("|"))
    table = list(itertools.takewhile(lambda line: line.startswith("|"), lines[start:]))
    return [_cells(line) for line in table[2:]]


def _table_dicts(md: str) -> dict[str, dict[str, str]]:
    """First cell -> {column header: cell} for each body row of a markdown table."""
    header = _cells(next(line for line in md.splitlines() if line.startswith("|")))
    return {row[0]: dict(zip(header, row)) for row in _table_rows(md)}


def _manifest(name: str) -> dict:
    return json.loads((WEIGHTS / f"{name}.json").read_text())


@pytest.mark.parametrize("name", POLICIES)
def test_manifest_names_the_shipped_weights(name):
    manifest = _manifest(name)
    assert manifest["policy"] == f"models/weights/{name}.pt"
    assert manifest["sha256"] == hashlib.sha256((WEIGHTS / f"{name}.pt").read_bytes()).hexdigest()


@pytest.mark.parametrize("name", POLICIES)
@pytest.mark.parametrize("label", ["seen", "unseen"])
def test_eval_table_matches_the_manifest(name, label):
    metrics = _manifest(name)["metrics"][label]
    per_object = metrics["per_object"]
    md = (WEIGHTS / f"{POLICIES[name]}_{label}.md").read_text()
    rows = _table_dicts(md)
    average = rows.pop("**average**")
    assert list(rows) == list(per_object)
    for obj, m in per_object.items():
        assert rows[obj]["successes"] == f"{m['successes']}/{m['episodes']}", obj
        assert rows[obj]["ours (%)"] == f"{m['success_pct']:.1f}", obj
        assert rows[obj]["mean max lift (m)"] == f"{m['mean_max_lift']:.3f}", obj
    wins = sum(m["successes"] for m in per_object.values())
    episodes = sum(m["episodes"] for m in per_object.values())
    assert average["successes"] == f"{wins}/{episodes}" and average["ours (%)"] == f"{metrics['average_pct']:.1f}"
    # the summary line above the table says the same
    summary = re.search(r"^- average ([\d.]+) % over (\d+) objects, .* \((\d+) episodes pooled\)", md, re.MULTILINE)
    assert summary, md[:500]
    assert summary.groups() == (f"{metrics['average_pct']:.1f}", str(len(per_object)), str(episodes))


@pytest.mark.parametrize("name", POLICIES)
@pytest.mark.parametrize("label", ["seen", "unseen"])
def test_eval_csv_matches_the_manifest_and_its_markdown(name, label):
    metrics = _manifest(name)["metrics"][label]
    per_object = metrics["per_object"]
    stem = WEIGHTS / f"{POLICIES[name]}_{label}"
    with open(stem.with_suffix(".csv"), newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0])[:6] == ["object", "successes", "ours_pct", "paper_pct", "mean_max_lift_m", "ci95_pct"]
    # the object rows and the average; category rows (tables made with them) have no object
    rows = [{k: v for k, v in r.items() if k != "category"} for r in rows if r["object"]]
    average = rows.pop()
    assert [r["object"] for r in rows] == list(per_object) and average["object"] == "average"
    for row in rows:
        m = per_object[row["object"]]
        assert row["successes"] == f"{m['successes']}/{m['episodes']}", row
        assert row["ours_pct"] == f"{m['success_pct']:.1f}", row
        assert row["mean_max_lift_m"] == f"{m['mean_max_lift']:.3f}", row
        assert row["ci95_pct"] == "{:.1f}-{:.1f}".format(*m["ci95_pct"]), row
        paper = PAPER_UNSEEN.get(row["object"]) if label == "unseen" else None
        assert row["paper_pct"] == ("" if paper is None else f"{paper:.1f}"), row
    wins = sum(m["successes"] for m in per_object.values())
    episodes = sum(m["episodes"] for m in per_object.values())
    lift = sum(m["mean_max_lift"] * m["episodes"] for m in per_object.values()) / episodes
    assert average == {"object": "average", "successes": f"{wins}/{episodes}",
                       "ours_pct": f"{metrics['average_pct']:.1f}", "paper_pct": f"{PAPER_AVERAGE[label]:.1f}",
                       "mean_max_lift_m": f"{lift:.3f}", "ci95_pct": "{:.1f}-{:.1f}".format(*metrics["average_ci95_pct"])}
    # the markdown table holds the same cells in the same order (the average row's name in bold)
    md_rows = _table_rows(stem.with_suffix(".md").read_text())
    assert [[r[0].strip("*"), *r[1:]] for r in md_rows] == [list(r.values()) for r in [*rows, average]]


@pytest.mark.parametrize("name", POLICIES)
def test_readme_quotes_the_manifest(name):
    metrics = _manifest(name)["metrics"]
    row = next(line for line in (ROOT / "README.md").read_text().splitlines() if line.startswith(f"| `{name}.pt`"))
    quoted = re.findall(r"([\d.]+) % \((\d+)/(\d+)\)", row)
    assert len(quoted) == 2, row
    for (pct, wins, episodes), label in zip(quoted, ("seen", "unseen")):
        per_object = metrics[label]["per_object"].values()
        assert float(pct) == pytest.approx(metrics[label]["average_pct"], abs=0.05 + 1e-9), (label, row)
        assert (int(wins), int(episodes)) == (sum(m["successes"] for m in per_object),
                                              sum(m["episodes"] for m in per_object)), (label, row)


def test_ablation_markdown_and_csv_hold_the_same_rows():
    from dexdrake.eval.ablations import COLUMNS

    md_rows = _table_rows((WEIGHTS / "eval_ablations.md").read_text())
    with open(WEIGHTS / "eval_ablations.csv", newline="") as f:
        reader = csv.reader(f)
        header = next(reader)
        csv_rows = list(reader)
    assert tuple(header) == COLUMNS
    assert csv_rows == md_rows


def _commands() -> list[str]:
    """Every command a shipped table or manifest says made it."""
    found = []
    for md in sorted(WEIGHTS.glob("*.md")):
        found += re.findall(r"^[-\s]*command: `([^`]+)`", md.read_text(), flags=re.MULTILINE | re.IGNORECASE)
    for manifest in sorted(WEIGHTS.glob("*.json")):
        text = manifest.read_text()
        found += [c for c in re.findall(r'"command": "([^"]+)"', text) if c.startswith(("dexdrake ", "python "))]
    return found


class _Parsed(Exception):
    pass


def _parse_script(argv: list[str], monkeypatch, load_script) -> None:
    """Parse `python scripts/x.py ARGS` with the script's own parser, stopping right after."""
    original = argparse.ArgumentParser.parse_args

    def parse_then_stop(self, args=None, namespace=None):
        original(self, args, namespace)
        raise _Parsed

    module = load_script(Path(argv[0]).stem)
    with monkeypatch.context() as patch, pytest.raises(_Parsed):
        patch.setattr(argparse.ArgumentParser, "parse_args", parse_then_stop)
        patch.setattr(sys, "argv", argv)
        module.main()


def test_every_command_in_a_table_parses_as_written(monkeypatch, load_script):
    commands = _commands()
    assert len(commands) >= 8
    for command in commands:
        argv = shlex.split(command)
        assert not any(a.startswith("(") or a.endswith(")") for a in argv), command  # no prose in arguments
        if argv[0] == "dexdrake":
            args = build_parser().parse_args(argv[1:])
            if getattr(args, "policy", None) and str(args.policy).startswith("models/"):
                assert (ROOT / str(args.policy)).is_file(), command
        else:
            assert argv[0] == "python" and argv[1].startswith("scripts/"), command
            _parse_script(argv[1:], monkeypatch, load_script)
