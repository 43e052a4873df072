"""Test helper: what a rerun recording (.rrd) holds, read back with rerun's own reader."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from rerun.chunk import RrdReader

CONTAINER_KINDS = {1: "tabs", 2: "horizontal", 3: "vertical", 4: "grid"}  # rerun's ContainerKind


def logged_rows(path: Path) -> dict[str, int]:
    """Entity path -> number of time-stamped rows logged there (0 for static-only entities)."""
    rows: dict[str, int] = {}
    for chunk in RrdReader(path).stream().collect().stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + (0 if chunk.is_static else chunk.num_rows)
    return rows


def text_logs(path: Path, entity: str) -> list[tuple[str | None, str]]:
    """(level, text) of every TextLog row logged at `entity`, in the order logged."""
    out = []
    for chunk in RrdReader(path).stream().collect().stream():
        if chunk.entity_path == entity:
            batch = chunk.to_record_batch()
            levels = batch.column("TextLog:level").to_pylist() if "TextLog:level" in batch.schema.names else None
            for i, text in enumerate(batch.column("TextLog:text").to_pylist()):
                out.append(((levels[i] or [None])[0] if levels else None, text[0]))
    return out


@dataclass
class Node:
    """A view or container of a blueprint: `kind` is a view class ("3D", "TimeSeries", ...)
    or a container kind ("tabs", "horizontal", "vertical", "grid")."""

    kind: str
    name: str | None = None
    origin: str | None = None
    queries: list[str] = field(default_factory=list)
    eye: dict[str, list[float]] = field(default_factory=dict)
    shares: list[float] | None = None
    children: list[Node] = field(default_factory=list)

    def walk(self):
        yield self
        for child in self.children:
            yield from child.walk()

    def views(self) -> list[Node]:
        return [n for n in self.walk() if n.kind not in CONTAINER_KINDS.values()]


def blueprint_tree(path: Path) -> Node:
    """The root container of the recording's (only) blueprint, views and containers resolved."""
    reader = RrdReader(path)
    (store,) = reader.blueprints()
    parts: dict[str, dict[str, list]] = {}
    for chunk in reader.stream(store=store).collect().stream():
        batch = chunk.to_record_batch()
        columns = parts.setdefault(chunk.entity_path.lstrip("/"), {})
        for name in batch.schema.names:
            if ":" in name:
                columns[name.split(":", 1)[1]] = batch.column(name).to_pylist()[-1]

    def node(key: str) -> Node:
        p = parts[key]
        if key.startswith("container/"):
            return Node(CONTAINER_KINDS[p["container_kind"][0]], p.get("display_name", [None])[0],
                        shares=p.get("col_shares") or p.get("row_shares"),
                        children=[node(child) for child in p.get("contents", [])])
        contents = parts.get(f"{key}/ViewContents", {})
        eye = parts.get(f"{key}/EyeControls3D", {})
        return Node(p["class_identifier"][0], p["display_name"][0], p["space_origin"][0],
                    contents.get("query", []), {k: v[0] for k, v in eye.items()})

    root_id = bytes(parts["viewport"]["root_container"][0]).hex()
    uuid = f"{root_id[:8]}-{root_id[8:12]}-{root_id[12:16]}-{root_id[16:20]}-{root_id[20:]}"
    return node(f"container/{uuid}")


def matches(view: Node, entity: str) -> bool:
    """Whether `entity` (e.g. "/task/lift") is in the view's contents (rerun's query rules:
    `+`/`-` lines, `$origin`, `/**` for a subtree; the last matching line wins)."""
    included = False
    for line in view.queries:
        sign, expr = (line[0], line[1:].strip()) if line[:1] in "+-" else ("+", line.strip())
        expr = expr.replace("$origin", "/" + view.origin.strip("/")).replace("//", "/")
        pattern = "^" + re.escape(expr).replace(r"/\*\*", "(/.*)?") + "$"
        if re.match(pattern, entity):
            included = sign == "+"
    return included
