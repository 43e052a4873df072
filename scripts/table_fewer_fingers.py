"""Table II beside the paper's: the fewer-finger Adroit policies' unseen success from their recipe runs.

    python scripts/table_fewer_fingers.py --runs DIR_4F DIR_3F DIR_2F --out models/weights/table2_fewer_fingers.md

Each DIR is the --out folder of `dexdrake train recipe configs/recipes/adroit_<n>f.yaml` once its
test stage finished; the finger count comes from the run's hand (its fingertips). A row gives the
run's unseen successes over all episodes (test/eval_unseen.json) with the 95 % Wilson interval,
the paper's Hand2obj / pGlo / DexRep figures for that many fingers, and the budget and command
of the run (recipe.json and the stages' done.json).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from dexdrake.errors import DexdrakeError
from dexdrake.eval.evaluate import wilson_interval
from dexdrake.eval.paper import PAPER_FEWER_FINGERS
from dexdrake.hands.description import load_hand
from dexdrake.objects.meshfile import write_atomic

PAPER_COLUMNS = ("Hand2obj", "pGlo", "DexRep")


def _json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except OSError as exc:
        raise DexdrakeError(f"cannot read {path}: {exc.strerror} (has the run's test stage finished?)") from exc


def budget(recipe: dict[str, Any], objects: int) -> str:
    """The training budget of a recipe (recipe.json's settings) on `objects` DAgger objects, in words."""
    dagger = recipe["dagger"]["config"]
    text = (f"DAgger {dagger['iterations']} iterations x {dagger['episodes_per_object']} episodes x {objects} objects "
            f"({dagger['horizon']} steps), {dagger['epochs']} epochs/iteration")
    stages = [f"{s['config']['iterations']} iterations x {s['episodes_per_object']} episode(s)/object"
              for s in recipe["dapg"]]
    return text + (f"; DAPG {', '.join(stages)}" if stages else "; no DAPG")


def run_row(run: Path) -> dict[str, Any]:
    """One run's row: fingers, hand, feature set, unseen successes/episodes, interval, budget, the expert's
    success, command, wall time."""
    record = _json(run / "recipe.json")["recipe"]
    report = _json(run / "test" / "eval_unseen.json")
    done = {name: _json(run / name / "done.json") for name in ("expert", "dagger", "test")}
    hand = record["dagger"]["config"]["hand"]
    wins = sum(int(o["successes"]) for o in report["per_object"].values())
    episodes = sum(int(o["episodes"]) for o in report["per_object"].values())
    low, high = wilson_interval(wins, episodes)
    wall = sum(json.loads(p.read_text()).get("wall_s", 0.0) for p in run.glob("*/done.json"))
    return {"fingers": len(load_hand(hand).fingertips), "hand": hand, "feature_set": report["feature_set"],
            "successes": wins, "episodes": episodes, "objects": len(report["objects"]),
            "per_object": report["episodes_per_object"], "pct": 100.0 * wins / episodes,
            "ci95": (100.0 * low, 100.0 * high), "budget": budget(record, int(done["dagger"]["objects"])),
            "command": done["test"]["command"], "wall_h": wall / 3600.0,
            "expert": f"{done['expert']['success_pct']:.1f} % of {done['expert']['episodes']} episodes"}


def markdown(rows: list[dict[str, Any]]) -> str:
    """The table (rows by finger count) and each run's budget and command."""
    rows = sorted(rows, key=lambda r: r["fingers"])
    lines = ["# Table II: hands with fewer fingers, unseen objects", "",
             "Success % on the unseen objects at the test seeds. Ours: the policy each recipe made (its feature set "
             "named), all episodes pooled, with the 95 % Wilson interval. The paper's columns are its Table II on "
             "the unseen GRAB objects; our unseen objects are procedural, so the columns compare hands and "
             "feature sets, not objects.", "",
             "| fingers | hand | ours: successes | ours % | 95 % CI | " + " | ".join(f"paper {c}" for c in PAPER_COLUMNS)
             + " |", "|---|---|---|---|---|" + "---|" * len(PAPER_COLUMNS)]
    for r in rows:
        paper = PAPER_FEWER_FINGERS.get(r["fingers"], {})
        cells = " | ".join(f"{paper[c]:.1f}" if c in paper else "-" for c in PAPER_COLUMNS)
        lines.append(f"| {r['fingers']} | {r['hand']} ({r['feature_set']}) | {r['successes']}/{r['episodes']} | "
                     f"{r['pct']:.1f} | {r['ci95'][0]:.1f}-{r['ci95'][1]:.1f} | {cells} |")
    lines += ["", "## Runs", ""]
    for r in rows:
        lines += [f"- **{r['fingers']} fingers** ({r['objects']} unseen objects x {r['per_object']} episodes): "
                  f"{r['budget']}; the expert grasps {r['expert']} on the DAgger objects; {r['wall_h']:.2f} h wall in "
                  f"all. Made by `{r['command']}`."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", nargs="+", type=Path, required=True, help="recipe run folders (--out of each)")
    parser.add_argument("--out", type=Path, default=Path("models/weights/table2_fewer_fingers.md"))
    args = parser.parse_args(argv)
    try:
        text = markdown([run_row(run) for run in args.runs])
    except DexdrakeError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    write_atomic(args.out, text.encode())
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
