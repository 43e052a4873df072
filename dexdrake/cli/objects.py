"""`dexdrake objects ...` command-line commands (wired into dexdrake/cli/__init__.py).

The library (trimesh, scipy) is imported inside the commands so `dexdrake --help` stays quick.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from dexdrake import argtypes
from dexdrake.cli.flags import command_line, option_names

if TYPE_CHECKING:
    from dexdrake.objects.library import ObjectInfo

SPLITS = ("train", "unseen", "validation", "near", "user", "augmented")  # as dexdrake.objects.library.SPLITS
UP_AXES = ("x", "y", "z", "-x", "-y", "-z")  # as dexdrake.objects.importer.UP_AXES
MAX_COPIES, MAX_SHAPES = 50, 999  # as dexdrake.objects.augment.MAX_COPIES, MAX_SHAPES


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add `objects list`, `import`, `remove`, `augment` and `novelty` to a subparsers action."""
    parser = subparsers.add_parser("objects", help="list, import or augment grasp objects; how new the held-out ones are")
    sub = parser.add_subparsers(dest="objects_command", required=True)

    p_list = sub.add_parser("list", help="table of library objects")
    p_list.add_argument("--split", choices=SPLITS, help="only this split")
    p_list.set_defaults(func=cmd_list)

    p_imp = sub.add_parser("import", help="import a mesh file (OBJ/STL/PLY/GLB) as a user object")
    p_imp.add_argument("path", type=Path, help="mesh file")
    p_imp.add_argument("--name", required=True, help="object name (a-z, 0-9, _ and -)")
    p_imp.add_argument("--scale", type=argtypes.positive, default=1.0, help="factor to metres, e.g. 0.001 for mm")
    p_imp.add_argument("--category", default="user", help="category label (default: user)")
    p_imp.add_argument("--overwrite", action="store_true", help="replace an existing user object")
    p_imp.add_argument("--up-axis", choices=UP_AXES, help="the file's up direction (default: y "
                       "for .glb/.gltf, whose convention is y up; z otherwise)")
    p_imp.set_defaults(func=cmd_import)

    p_rm = sub.add_parser("remove", help="delete an imported (user) object")
    p_rm.add_argument("name", help="user object name")
    p_rm.set_defaults(func=cmd_remove)

    p_aug = sub.add_parser("augment", help="scaled copies of the training objects and procedural shapes, to train on "
                           "(split 'augmented')")
    _add_augmented(p_aug, 2, 0)
    p_aug.set_defaults(func=cmd_augment)

    p_nov = sub.add_parser("novelty", help="how new the held-out objects are: each one's nearest training or "
                           "augmented object (markdown)",
                           description="Each unseen, validation and near object's nearest reference (the training "
                                       "objects, their scaled copies and the procedural shapes of `objects augment "
                                       "--copies C --shapes S`, built in memory) by mean surface Chamfer distance, "
                                       "best over yaw, against a threshold: the median training object's distance to "
                                       "its nearest training neighbour. Prints and writes a markdown table naming "
                                       "the command.")
    _add_augmented(p_nov, 4, 100, "the augmented split to measure against: ")
    p_nov.add_argument("--out", type=argtypes.output_file(".md"),
                       help="the table to write (default: models/objects/novelty.md)")
    p_nov.set_defaults(func=cmd_novelty, recorded_options=option_names(p_nov))
    return parser


def _add_augmented(parser: argparse.ArgumentParser, copies: int, shapes: int, what: str = "") -> None:
    """--copies and --shapes: the augmented split (dexdrake.objects.augment)."""
    parser.add_argument("--copies", type=argtypes.int_at_least(1, MAX_COPIES), default=copies,
                        help=f"{what}copies per training object (default {copies}, at most {MAX_COPIES})")
    parser.add_argument("--shapes", type=argtypes.int_at_least(0, MAX_SHAPES), default=shapes,
                        help=f"{what}procedural shapes (superquadrics and compounds of them; default {shapes}, "
                             f"at most {MAX_SHAPES})")


def _known_pieces(info: "ObjectInfo") -> int | None:
    """Number of convex pieces if already computed (shipped or cached), without running CoACD."""
    from dexdrake.objects import store
    from dexdrake.objects.convex import piece_files, pieces_key
    from dexdrake.paths import cache_dir

    meta = store.read_meta(info.mesh_path.parent)
    if "convex" in meta:
        return int(meta["convex"]["pieces"])
    files = piece_files(cache_dir() / "convex" / pieces_key(info.content_hash))
    return len(files) or None


def format_table(infos: list["ObjectInfo"]) -> str:
    """Fixed-width table: name, category, split, extents (cm), convex pieces."""
    rows = [("name", "category", "split", "extents cm (x y z)", "pieces")]
    for i in infos:
        pieces = _known_pieces(i)
        ext = " x ".join(f"{e * 100:.1f}" for e in i.extents)
        rows.append((i.name, i.category, i.split, ext, "-" if pieces is None else str(pieces)))
    widths = [max(len(r[k]) for r in rows) for k in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def cmd_list(args: argparse.Namespace) -> int:
    """Print the object table."""
    from dexdrake.objects.library import list_objects

    infos = list_objects(args.split)
    print(format_table(infos))
    print(f"{len(infos)} objects")
    return 0


def cmd_import(args: argparse.Namespace) -> int:
    """Import a mesh; print the result and every repair made (refusals: DexdrakeError)."""
    from dexdrake.objects import store
    from dexdrake.objects.library import import_mesh

    info = import_mesh(args.path, args.name, category=args.category, scale=args.scale,
                       overwrite=args.overwrite, up_axis=args.up_axis)
    pieces = info.convex_pieces()
    for line in store.read_meta(info.mesh_path.parent)["import"]["repairs"]:
        print(f"  {line}")
    print(format_table([info]))
    print(f"imported {info.name} -> {info.mesh_path} ({len(pieces)} convex pieces)")
    return 0


def cmd_remove(args: argparse.Namespace) -> int:
    """Delete a user object."""
    from dexdrake.objects.library import remove_user_object

    remove_user_object(args.name)
    print(f"removed user object {args.name}")
    return 0


def cmd_augment(args: argparse.Namespace) -> int:
    """Make the augmented split (dexdrake.objects.augment); print where and how many."""
    from dexdrake.objects import store
    from dexdrake.objects.augment import SCALE_RANGE, build_augmented

    names = build_augmented(args.copies, args.shapes)
    print(f"{len(names) - args.shapes} scaled copies (per-axis factors in {SCALE_RANGE[0]}-{SCALE_RANGE[1]}) and "
          f"{args.shapes} procedural shapes in {store.augmented_root()}; train on them with `--objects train+augmented`")
    return 0


def cmd_novelty(args: argparse.Namespace) -> int:
    """Write and print the held-out objects' novelty table (dexdrake.objects.similarity.novelty_table)."""
    from dexdrake.objects.meshfile import write_atomic
    from dexdrake.objects.similarity import novelty_table
    from dexdrake.outputs import check_writable
    from dexdrake.paths import models_dir

    out = args.out or check_writable(models_dir() / "objects" / "novelty.md", folder=False)
    text = novelty_table(args.copies, args.shapes, command_line(["objects", "novelty"], args, args.recorded_options))
    write_atomic(out, text.encode())
    print(text + f"wrote {out}")
    return 0
