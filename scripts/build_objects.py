"""Generate the shipped object set into models/objects/<name>/ (mesh.obj, meta.json, convex/).

    python scripts/build_objects.py               # build what changed (mesh hash / CoACD params)
    python scripts/build_objects.py --force       # rebuild everything, CoACD included
    python scripts/build_objects.py --only mug apple
    python scripts/build_objects.py --check       # verify the shipped files match the recipes

Meshes are deterministic functions of the recipes in dexdrake/objects/shapes.py; the
convex pieces are CoACD with fixed parameters and seed (dexdrake/objects/convex.py).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

from tqdm import tqdm

from dexdrake.objects import shapes, store
from dexdrake.objects.convex import decompose, pieces_key
from dexdrake.objects.meshfile import content_hash, is_stable_rest, obj_bytes

REPO_OBJECTS = Path(__file__).resolve().parents[1] / "models" / "objects"


def recipe_meta(recipe: shapes.Recipe) -> dict:
    params = {k: list(v) if isinstance(v, tuple) else v for k, v in recipe.params.items()}
    return {"name": recipe.name, "category": recipe.category, "split": recipe.split,
            "recipe": {"builder": recipe.builder.__name__, "params": params}}


def up_to_date(folder: Path, mesh_hash: str, meta: dict) -> bool:
    if not (folder / store.META_FILE).is_file():
        return False
    old = store.read_meta(folder)
    same_meta = all(old.get(k) == v for k, v in meta.items())
    return same_meta and old.get("content_hash") == mesh_hash and old.get("convex", {}).get("key") == pieces_key(mesh_hash)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="+", metavar="NAME", help="recipes to build (default: all)")
    ap.add_argument("--force", action="store_true", help="rebuild even if up to date")
    ap.add_argument("--check", action="store_true", help="only verify; exit 1 if anything is stale")
    ap.add_argument("--out", type=Path, default=REPO_OBJECTS, help="target folder (default: models/objects)")
    args = ap.parse_args(argv)

    names = args.only or shapes.recipe_names()
    for name in names:
        shapes.get_recipe(name)  # fail early on a typo
    stale, built, t0 = [], 0, time.time()
    for name in tqdm(names, desc="objects", unit="obj"):
        recipe = shapes.get_recipe(name)
        mesh = shapes.build_mesh(name)
        if not is_stable_rest(mesh):
            raise SystemExit(f"{name}: identity is not a stable resting pose; fix the recipe")
        mesh_hash, meta, folder = content_hash(obj_bytes(mesh)), recipe_meta(recipe), args.out / name
        if up_to_date(folder, mesh_hash, meta) and not args.force:
            continue
        stale.append(name)
        if args.check:
            continue
        shutil.rmtree(folder, ignore_errors=True)
        final = store.write_object_dir(folder, mesh, meta, pieces=decompose)
        built += 1
        tqdm.write(f"{name:18s} {final['faces']:5d} faces  {final['convex']['pieces']:2d} pieces")
    if not args.check:
        known = set(shapes.recipe_names())
        for extra in sorted(p for p in args.out.iterdir() if p.is_dir() and p.name not in known and not p.name.startswith("__")):
            print(f"removing {extra} (no recipe)")
            shutil.rmtree(extra)
    size = sum(f.stat().st_size for f in args.out.rglob("*") if f.is_file())
    print(f"{len(names)} objects, {built} built in {time.time() - t0:.1f} s; {args.out} holds {size / 1e6:.2f} MB")
    if args.check and stale:
        print("stale:", ", ".join(stale))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
