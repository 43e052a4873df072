"""How new the held-out objects are: each one's nearest training or augmented object.

    python scripts/object_novelty.py [--copies 4] [--shapes 100] [--out models/objects/novelty.md]

Distances are mean surface Chamfer, best over yaw (dexdrake.objects.similarity), against the
training objects, their scaled copies and the procedural shapes (the augmented split the
shipped policy trained on: `dexdrake objects augment --copies 4 --shapes 100`). The
threshold is the median over training objects of the distance to the nearest other training
object. Writes a markdown table naming this command.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from dexdrake.objects import similarity
from dexdrake.objects.library import list_objects
from dexdrake.objects.meshfile import load_obj, write_atomic

SPLITS = ("unseen", "validation", "near")


def training_median_nn(points: dict[str, np.ndarray], train: list[str]) -> float:
    """Median over training objects of the distance (m) to the nearest other training object."""
    return float(np.median([similarity.nearest(points[n], [points[m] for m in train if m != n])[1]
                            for n in tqdm(train, desc="training neighbours", unit="obj")]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--copies", type=int, default=4)
    parser.add_argument("--shapes", type=int, default=100)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "models" / "objects" / "novelty.md")
    args = parser.parse_args()
    refs = similarity.reference_meshes(args.copies, args.shapes)
    names = list(refs)
    points = {n: similarity.surface_points(m) for n, m in refs.items()}
    train = [i.name for i in list_objects("train")]
    threshold = training_median_nn(points, train)
    lines = ["# Held-out objects against the training and augmented objects", "",
             f"- command: `{shlex.join(['python', *sys.argv])}`",
             (f"- {len(names)} reference objects: {len(train)} training objects, {args.copies} scaled copies of each, "
              f"{args.shapes} procedural shapes"),
             ("- distance: mean surface Chamfer, best over yaw (dexdrake.objects.similarity, "
              f"{similarity.POINTS} points, {similarity.YAWS} turns)"),
             ("- threshold: the median training object's distance to its nearest training neighbour, "
              f"{1000 * threshold:.1f} mm"), "",
             "| object | split | category | nearest reference | distance (mm) | beyond the threshold |", "|---|---|---|---|---|---|"]
    for split in SPLITS:
        for info in tqdm(list_objects(split), desc=split, unit="obj"):
            k, d = similarity.nearest(similarity.surface_points(load_obj(info.mesh_path)), [points[n] for n in names])
            lines.append(f"| {info.name} | {split} | {info.category} | {names[k]} | {1000 * d:.1f} | "
                         f"{'yes' if d > threshold else 'no'} |")
    write_atomic(args.out, ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
