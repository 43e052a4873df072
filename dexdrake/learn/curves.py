"""Learning-curve artefacts: an append-only CSV log and a PNG plot of its columns."""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from pathlib import Path

from dexdrake.errors import DexdrakeError


class CsvLog:
    """Append rows (dicts with a fixed set of keys) to a CSV file, flushing each row.

    With `resume=True` an existing file is kept and rows whose `key` column is >=
    `resume_from` are dropped first, so a resumed run does not duplicate rows.
    """

    def __init__(
        self, path: str | Path, columns: Sequence[str], resume: bool = False, key: str = "", resume_from: int = 0
    ):
        self.path = Path(path)
        self.columns = list(columns)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        kept: list[dict[str, str]] = []
        if resume and self.path.is_file():
            kept = [r for r in read_csv(self.path) if not key or int(float(r[key])) < resume_from]
        with open(self.path, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.columns)
            writer.writeheader()
            writer.writerows({c: r.get(c, "") for c in self.columns} for r in kept)

    def append(self, row: Mapping[str, float | int | str]) -> None:
        unknown = set(row) - set(self.columns)
        if unknown:
            raise DexdrakeError(f"CSV row has unknown columns {sorted(unknown)}; known: {self.columns}")
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=self.columns).writerow(dict(row))


def read_csv(path: str | Path) -> list[dict[str, str]]:
    """All rows of a CSV file as dicts of strings."""
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def plot_curves(csv_path: str | Path, png_path: str | Path, x: str, ys: Sequence[str], title: str = "") -> Path:
    """Plot columns `ys` of a CSV log against column `x`, one panel each, to a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_csv(csv_path)
    xs = [float(r[x]) for r in rows]
    fig, axes = plt.subplots(len(ys), 1, figsize=(6, 2.2 * len(ys)), sharex=True, squeeze=False)
    for ax, col in zip(axes[:, 0], ys):
        vals = [float(r[col]) if r.get(col, "") != "" else float("nan") for r in rows]
        ax.plot(xs, vals, marker="." if len(xs) < 50 else None)
        ax.set_ylabel(col)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel(x)
    if title:
        axes[0, 0].set_title(title)
    fig.tight_layout()
    png_path = Path(png_path)
    fig.savefig(png_path, dpi=100)
    plt.close(fig)
    return png_path
