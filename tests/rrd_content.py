"""Test helper: what a rerun recording (.rrd) holds, read back with rerun's own reader."""

from pathlib import Path

from rerun.chunk import RrdReader


def logged_rows(path: Path) -> dict[str, int]:
    """Entity path -> number of time-stamped rows logged there (0 for static-only entities)."""
    rows: dict[str, int] = {}
    for chunk in RrdReader(path).stream().collect().stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + (0 if chunk.is_static else chunk.num_rows)
    return rows
