"""Shipping a policy into a weights folder: its evaluation tables and their metrics.

`ship_eval_table` copies an evaluation's markdown table (written by
`eval.tables.write_report`) beside the shipped policy, naming the shipped file instead of
the evaluated one, with its CSV; it returns the metrics a manifest keeps of it (averages,
intervals, per object, seeds and the successful ones, the command that measured it).
`ship_test_tables` does so for the seen and unseen test tables (TABLES_seen.md, TABLES_unseen.md).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from dexdrake.eval.tables import write_csv_beside
from dexdrake.objects.meshfile import write_atomic

METRIC_KEYS = ("average_pct", "average_ci95_pct", "per_object", "episodes_per_object", "seed",
               "seed_range", "horizon", "command", "wall_s", "workers")


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def eval_metrics(report: dict[str, Any]) -> dict[str, Any]:
    """What a manifest keeps of an evaluation report (`EvalReport.to_dict`, as eval_<label>.json)."""
    metrics = {k: report[k] for k in METRIC_KEYS}
    metrics["successful_seeds"] = {name: [e["seed"] for e in report["episodes"] if e["object"] == name and e["success"]]
                                   for name in report["per_object"]}
    return metrics


def ship_eval_table(eval_dir: Path, label: str, evaluated: Path | str, table: Path, shipped: str,
                    note: str = "") -> dict[str, Any]:
    """Copy eval_dir/eval_<label>.md to `table` (.md, and its .csv), the evaluated policy's path
    replaced by `shipped` and `note` appended; returns the evaluation's manifest metrics."""
    text = (eval_dir / f"eval_{label}.md").read_text().replace(str(evaluated), shipped)
    write_atomic(table, (text + (f"\n{note}\n" if note else "")).encode())
    write_csv_beside(table)
    return eval_metrics(json.loads((eval_dir / f"eval_{label}.json").read_text()))


TEST_LABELS = ("seen", "unseen")


def ship_test_tables(eval_dir: Path, evaluated: Path | str, tables: Path, shipped: str,
                     note: str = "") -> dict[str, dict[str, Any]]:
    """`ship_eval_table` of eval_dir's seen and unseen evaluations to TABLES_seen.md and
    TABLES_unseen.md (`tables` is the path without the suffix); the metrics per label."""
    return {label: ship_eval_table(eval_dir, label, evaluated, tables.with_name(f"{tables.name}_{label}.md"), shipped,
                                   note) for label in TEST_LABELS}
