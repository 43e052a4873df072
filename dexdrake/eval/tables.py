"""Result tables in the layout of the paper's Table I (markdown and CSV).

One row per object (successes, our rate, the paper's DexRep rate on the GRAB object our
procedural stand-in is named after, where it has one, mean lift, 95 % Wilson interval) and
an average row; then a table with one row per object category (sorted; its objects' episodes
pooled, `EvalReport.per_category`; an object the library does not hold is in category
"unknown"). The markdown header names the command that made the tables, runnable as written,
and the seed range. The CSV is made from the markdown (`csv_from_markdown`), so the two never
disagree, and a shipped markdown table gets its CSV without evaluating again: the object rows
and the average in the object table's columns, then the category rows, their category in a
last column "category" and the object cell empty (a markdown without a category table gives
the CSV without that column).
"""

from __future__ import annotations

import csv
import io
import json
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING

from dexdrake.eval.paper import PAPER_AVERAGE, PAPER_UNSEEN
from dexdrake.eval.seeds import SEED_RANGES, describe
from dexdrake.objects.meshfile import write_atomic

if TYPE_CHECKING:
    from dexdrake.eval.evaluate import EvalReport


# (CSV column, markdown header) of the object table and of the category table, in order
COLUMNS = (("object", "object"), ("successes", "successes"), ("ours_pct", "ours (%)"),
           ("paper_pct", "paper DexRep, GRAB namesake (%)"), ("mean_max_lift_m", "mean max lift (m)"), ("ci95_pct", "95 % CI (%)"))
CATEGORY_COLUMNS = (("category", "category"), ("successes", "successes"), ("ours_pct", "ours (%)"),
                    ("ci95_pct", "95 % CI (%)"))


def _fmt(value: float | None) -> str:
    return "" if value is None else f"{value:.1f}"


def _fmt_ci(ci: tuple[float, float] | list[float]) -> str:
    return f"{ci[0]:.1f}-{ci[1]:.1f}"


def table_rows(report: EvalReport) -> list[dict[str, str]]:
    """One row per object plus an 'average' row: object, successes, ours %, paper %, lift, 95 % CI."""
    rows = []
    for name, r in report.per_object().items():
        paper = PAPER_UNSEEN.get(name) if report.label != "seen" else None
        rows.append({
            "object": name,
            "successes": f"{int(r['successes'])}/{int(r['episodes'])}",
            "ours_pct": _fmt(r["success_pct"]),
            "paper_pct": _fmt(paper),
            "mean_max_lift_m": f"{r['mean_max_lift']:.3f}",
            "ci95_pct": _fmt_ci(r["ci95_pct"]),
        })
    total = sum(int(r["successes"]) for r in report.per_object().values())
    rows.append({
        "object": "average",
        "successes": f"{total}/{len(report.episodes)}",
        "ours_pct": _fmt(report.average_pct()),
        "paper_pct": _fmt(report.paper_average()),
        "mean_max_lift_m": f"{sum(e.max_lift for e in report.episodes) / len(report.episodes):.3f}",
        "ci95_pct": _fmt_ci(report.average_ci95_pct()),
    })
    return rows


def category_rows(report: EvalReport) -> list[dict[str, str]]:
    """One row per object category, sorted: category, successes, ours %, 95 % CI."""
    return [{"category": category, "successes": f"{r['successes']}/{r['episodes']}", "ours_pct": _fmt(r["success_pct"]),
             "ci95_pct": _fmt_ci(r["ci95_pct"])} for category, r in report.per_category().items()]


def _markdown_rows(columns: tuple[tuple[str, str], ...], rows: list[dict[str, str]]) -> list[str]:
    """A markdown table of `rows` (CSV column -> cell) under the headers of `columns`; the average row's name in bold."""
    lines = ["| " + " | ".join(header for _, header in columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        cells = [row[key] for key, _ in columns]
        if row.get("object") == "average":
            cells[0] = "**average**"
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def paper_subset_average(report: EvalReport) -> tuple[float, float, int] | None:
    """(ours, paper, count) averaged over the objects that have a paper number, if any."""
    ours = report.per_object()
    common = [n for n in ours if n in PAPER_UNSEEN]
    if report.label == "seen" or not common:
        return None
    return (
        sum(ours[n]["success_pct"] for n in common) / len(common),
        sum(PAPER_UNSEEN[n] for n in common) / len(common),
        len(common),
    )


def _fault_kind(fault: str) -> str:
    """'driver fault (overspeed)', 'simulation diverged', ...: a fault's text before " at step",
    with a driver fault's rule (systems/grasp_env.py words them)."""
    head = fault.split(" at step", 1)[0]
    if head == "driver fault" and "): " in fault:
        return f"{head} ({fault.split('): ', 1)[1].split(':', 1)[0]})"
    return head


def fault_lines(episodes) -> list[str]:
    """A header line counting the episodes a fault ended (each a failure) by kind; none
    without faults."""
    kinds = Counter(_fault_kind(e.fault) for e in episodes if e.fault)
    if not kinds:
        return []
    named = ", ".join(f"{n} {kind}" for kind, n in kinds.most_common())
    return [f"- {sum(kinds.values())} of {len(episodes)} episodes ended on a fault, each a failure: {named}"]


def _placement_line(report: EvalReport) -> list[str]:
    ci = report.placement_ci95_pct()
    if ci is None:
        return []
    return [f"- every object runs the same {report.episodes_per_object} placements (a seed fixes the placement): "
            f"resampling them too (bootstrap over the seeds), the average's 95 % interval is {ci[0]:.1f}-{ci[1]:.1f} %"]


def markdown_table(report: EvalReport) -> str:
    """The report as markdown: a header naming command, policy and seeds, then the object and category tables."""
    part = report.seed_range()
    seeds = (f"{part} seeds (range {describe(SEED_RANGES[part])}, disjoint from every training seed)" if part
             else "NOT in the range reserved for evaluation: they may repeat training episodes")
    low, high = report.average_ci95_pct()
    lines = [
        f"# Evaluation on {report.label} objects",
        "",
        f"- command: `{report.command}`" if report.command else "- command: (API call)",
        f"- policy: `{report.policy}`" + (f" (hand {report.hand}, features {report.feature_set})" if report.hand else ""),
        f"- seeds {report.seeds_text()} per object ({report.episodes_per_object} episodes), {seeds}; "
        f"{report.horizon} control steps (50 Hz), deterministic mean actions",
        "- success: object within 10 cm of the target (15 cm above its start) for 50 consecutive steps",
        f"- average {report.average_pct():.1f} % over {len(report.objects)} objects, 95 % Wilson interval "
        f"{low:.1f}-{high:.1f} % ({len(report.episodes)} episodes pooled)",
        *_placement_line(report),
        f"- wall time {report.wall_s:.0f} s with {report.workers} worker(s) x {report.envs_per_worker} env(s) in lockstep",
        *fault_lines(report.episodes),
        "",
        *_markdown_rows(COLUMNS, table_rows(report)),
        "",
        *_markdown_rows(CATEGORY_COLUMNS, category_rows(report)),
    ]
    sub = paper_subset_average(report)
    if sub is not None:
        lines += ["", f"Average over the {sub[2]} objects with a paper number: ours {sub[0]:.1f} %, paper {sub[1]:.1f} %."]
    if report.label == "seen":
        lines += ["", f"Paper: {PAPER_AVERAGE['seen']:.0f} % average on seen GRAB objects (no per-object numbers)."]
    return "\n".join(lines) + "\n"


def csv_table(report: EvalReport) -> str:
    """The tables as CSV text (`table_rows`, then `category_rows`), made from their markdown."""
    return csv_from_markdown(markdown_table(report))


def _markdown_tables(md: str) -> list[list[list[str]]]:
    """The cells of each markdown table in `md` (runs of lines starting with '|'), header first, rule dropped."""
    tables: list[list[list[str]]] = []
    previous = False
    for line in md.splitlines():
        is_row = line.startswith("|")
        if is_row and not previous:
            tables.append([])
        if is_row and not set(line) <= set("|-: "):
            tables[-1].append([cell.strip() for cell in line.strip().strip("|").split("|")])
        previous = is_row
    return tables


def csv_from_markdown(md: str) -> str:
    """The tables of an evaluation's markdown (`markdown_table`) as CSV text: the same cells,
    headed by the CSV column names (COLUMNS, then "category" if there is a category table),
    the average row's name without its bold marks, a category row's cells in the columns
    their headers name."""
    tables = _markdown_tables(md)
    header = tables[0][0] if tables else []
    if header != [h for _, h in COLUMNS] or any(t[0] != [h for _, h in CATEGORY_COLUMNS] for t in tables[1:]):
        raise ValueError(f"not an evaluation table: headers {[t[0] for t in tables]}")
    keys = [key for key, _ in COLUMNS] + (["category"] if len(tables) > 1 else [])
    buf = io.StringIO()
    writer = csv.DictWriter(buf, keys, restval="", lineterminator="\n")
    writer.writeheader()
    for cells in tables[0][1:]:
        writer.writerow(dict(zip(keys, [cells[0].strip("*"), *cells[1:]])))
    for table in tables[1:]:
        writer.writerows(dict(zip([key for key, _ in CATEGORY_COLUMNS], cells)) for cells in table[1:])
    return buf.getvalue()


def write_csv_beside(md_path: str | Path) -> Path:
    """Writes the CSV of an evaluation's markdown table beside it (same stem), atomically."""
    md_path = Path(md_path)
    path = md_path.with_suffix(".csv")
    write_atomic(path, csv_from_markdown(md_path.read_text()).encode())
    return path


def write_report(report: EvalReport, out_dir: str | Path, stem: str | None = None) -> dict[str, Path]:
    """Write eval_<label>.md, .csv and .json (every episode) into out_dir, each atomically;
    returns the paths."""
    out_dir = Path(out_dir)
    stem = stem or f"eval_{report.label}"
    paths = {"md": out_dir / f"{stem}.md", "csv": out_dir / f"{stem}.csv", "json": out_dir / f"{stem}.json"}
    write_atomic(paths["md"], markdown_table(report).encode())
    write_atomic(paths["csv"], csv_table(report).encode())
    write_atomic(paths["json"], json.dumps(report.to_dict(), indent=1).encode())
    return paths
