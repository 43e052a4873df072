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


def write_csv(path: str | Path, columns: Sequence[str], rows: Sequence[Mapping[str, float | int | str]]) -> Path:
    """Write all rows to a CSV file atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.csv")
    with open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(columns))
        writer.writeheader()
        writer.writerows(rows)
    tmp.replace(path)
    return path


def read_csv(path: str | Path) -> list[dict[str, str]]:
    """All rows of a CSV file as dicts of strings."""
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def plot_curves(
    csv_path: str | Path, png_path: str | Path, x: str | Sequence[str], ys: Sequence[str], title: str = ""
) -> Path:
    """Plot columns `ys` of a CSV log against column `x` (or each of several x columns, one
    panel column per x), one panel row per y, to a PNG written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_csv(csv_path)
    xs_names = [x] if isinstance(x, str) else list(x)
    fig, axes = plt.subplots(len(ys), len(xs_names), figsize=(6 * len(xs_names), 2.2 * len(ys)), sharex="col",
                             squeeze=False)
    for j, x_name in enumerate(xs_names):
        xs = [float(r[x_name]) for r in rows]
        for ax, col in zip(axes[:, j], ys):
            vals = [float(r[col]) if r.get(col, "") != "" else float("nan") for r in rows]
            ax.plot(xs, vals, marker="." if len(xs) < 50 else None)
            ax.set_ylabel(col)
            ax.grid(alpha=0.3)
        axes[-1, j].set_xlabel(x_name)
        if title:
            axes[0, j].set_title(title)
    return _save(fig, png_path)


def plot_success_map(csv_path: str | Path, png_path: str | Path, title: str = "") -> Path:
    """Success rate per object (rows) and iteration (columns) of a per-object log with columns
    iteration, object, rollouts, successes (DAPG's dapg_objects.csv), as an image (PNG, atomic)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = read_csv(csv_path)
    if not rows:
        raise DexdrakeError(f"{csv_path} has no rows to plot")
    objects = sorted({r["object"] for r in rows})
    iterations = sorted({int(r["iteration"]) for r in rows})
    row_of, col_of = {o: i for i, o in enumerate(objects)}, {k: j for j, k in enumerate(iterations)}
    grid = np.full((len(objects), len(iterations)), np.nan)
    for r in rows:
        grid[row_of[r["object"]], col_of[int(r["iteration"])]] = int(r["successes"]) / int(r["rollouts"])
    fig, ax = plt.subplots(figsize=(min(4 + 0.08 * len(iterations), 20), min(1.5 + 0.15 * len(objects), 40)))
    image = ax.imshow(grid, aspect="auto", interpolation="nearest", cmap="viridis", vmin=0.0, vmax=1.0,
                      extent=(iterations[0] - 0.5, iterations[-1] + 0.5, len(objects) - 0.5, -0.5))
    ax.set_yticks(range(len(objects)), objects, fontsize=6)
    ax.set_xlabel("iteration")
    fig.colorbar(image, ax=ax, label="success rate of its rollouts")
    if title:
        ax.set_title(title)
    return _save(fig, png_path)


def _save(fig, png_path: str | Path) -> Path:
    """Write `fig` to png_path atomically and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    png_path = Path(png_path)
    tmp = png_path.with_name(png_path.stem + ".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(png_path)
    return png_path
