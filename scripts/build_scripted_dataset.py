"""Build a BC dataset from successful scripted grasps (raw states first, then features).

    python scripts/build_scripted_dataset.py record --objects train --seeds 2 --first-seed 1000 \
        --out runs/scripted_raw.npz [--workers 2] [--horizon 100] [--timing fast|early_lift] \
        [--noise 0.05 --noise-seed 0]
    python scripts/build_scripted_dataset.py featurise --raw runs/scripted_raw.npz \
        --feature-set DexRep --out runs/scripted_dexrep.npz

    python scripts/build_scripted_dataset.py merge --inputs a.npz b.npz --out all.npz

`record` needs no PointNet encoder (no features); `featurise` turns the kept (successful)
episodes into any feature set's observations, so ablations reuse one recording. With
`--noise STD` the recording executes the expert action plus OU noise (STD in normalised
action units) and records the clean expert action (DART-style; default off).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import shlex
import sys
from dataclasses import asdict
from pathlib import Path

from tqdm import tqdm


def _record(job: tuple[str, str, list[int], int, str, float, int]):
    from dexdrake.systems.scripted_data import record_object, timing_named

    hand, name, seeds, horizon, timing, noise, noise_seed = job
    return record_object(hand, name, seeds, horizon, timing_named(timing), noise=noise, noise_seed=noise_seed)


def cmd_record(args: argparse.Namespace) -> None:
    from dexdrake.errors import DexdrakeError
    from dexdrake.eval.action_noise import DEFAULT_RHO
    from dexdrake.eval.seeds import check_training_seeds
    from dexdrake.objects.library import resolve_objects
    from dexdrake.systems.scripted_data import concat, save_raw, timing_named

    if args.noise < 0:
        raise SystemExit(f"--noise must be >= 0, got {args.noise}")
    timing = timing_named(args.timing)
    _, names = resolve_objects(args.objects)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    try:
        check_training_seeds(seeds, "episode seeds (--first-seed ...)")
    except DexdrakeError as e:
        raise SystemExit(f"build_scripted_dataset: error: {e}") from None
    jobs = [(args.hand, n, seeds, args.horizon, args.timing, args.noise, args.noise_seed) for n in names]
    with mp.get_context("spawn").Pool(args.workers) as pool:
        parts = list(tqdm(pool.imap(_record, jobs), total=len(jobs), desc="record", unit="object"))
    raw = concat(parts)
    meta = {"script": asdict(timing), "timing": args.timing, "seeds": seeds, "horizon": args.horizon,
            "noise": {"std": args.noise, "seed": args.noise_seed, "rho": DEFAULT_RHO, "process": "OU (AR(1)) on executed actions"}
            if args.noise > 0 else None,
            "command": shlex.join(["python", *sys.argv]), "overall_success": float(raw.success.mean())}
    save_raw(args.out, raw, meta)
    print(f"{int(raw.success.sum())}/{len(raw.success)} episodes succeeded; wrote {args.out}")
    for n in names:
        ok = [bool(s) for o, s in zip(raw.objects, raw.success) if o == n]
        print(f"  {n:<18} {sum(ok)}/{len(ok)}")


def cmd_featurise(args: argparse.Namespace) -> None:
    from dexdrake.learn.demo_dataset import save_demo_dataset
    from dexdrake.systems.scripted_data import dataset_metadata, featurise, load_raw

    recorded, meta = load_raw(args.raw)
    kept = recorded.select_successful()
    if not len(kept.objects):
        raise SystemExit(f"{args.raw} holds no successful episode")
    obs, blocks = featurise(kept, args.feature_set, progress=True)
    metadata = dataset_metadata(recorded, kept, meta, args.feature_set, blocks)
    metadata["featurise_command"] = shlex.join(["python", *sys.argv])
    save_demo_dataset(args.out, obs, kept.actions, kept.episode_starts, metadata)
    print(f"wrote {len(obs)} samples of {len(kept.objects)} episodes ({obs.shape[1]}-d {args.feature_set}) to {args.out}")


def cmd_merge(args: argparse.Namespace) -> None:
    from dexdrake.systems.scripted_data import concat, load_raw, save_raw

    loaded = [load_raw(p) for p in args.inputs]
    raw = concat([r for r, _ in loaded])
    meta = {"merged_from": [{"path": str(p), **{k: m.get(k) for k in ("command", "seeds", "script", "timing", "horizon", "noise")}}
                            for p, (_, m) in zip(args.inputs, loaded)],
            "script": loaded[0][1].get("script"), "command": shlex.join(["python", *sys.argv]),
            "seeds": sorted({s for _, m in loaded for s in m.get("seeds", [])}),
            "overall_success": float(raw.success.mean())}
    save_raw(args.out, raw, meta)
    print(f"merged {len(raw.objects)} episodes ({int(raw.success.sum())} successful) into {args.out}")


def main() -> None:
    from dexdrake.systems.scripted_data import TIMINGS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    rec = sub.add_parser("record")
    rec.add_argument("--hand", default="adroit")
    rec.add_argument("--objects", default="train")
    rec.add_argument("--seeds", type=int, default=2)
    rec.add_argument("--first-seed", type=int, default=1000)
    rec.add_argument("--horizon", type=int, default=100)
    rec.add_argument("--workers", type=int, default=2)
    rec.add_argument("--timing", default="fast", choices=sorted(TIMINGS),
                     help="script phase timing (dexdrake.systems.scripted_data.TIMINGS)")
    rec.add_argument("--noise", type=float, default=0.0, help="OU noise std on executed actions (0: off)")
    rec.add_argument("--noise-seed", type=int, default=0)
    rec.add_argument("--out", type=Path, required=True)
    rec.set_defaults(func=cmd_record)
    fea = sub.add_parser("featurise")
    fea.add_argument("--raw", type=Path, required=True)
    fea.add_argument("--feature-set", default="DexRep")
    fea.add_argument("--out", type=Path, required=True)
    fea.set_defaults(func=cmd_featurise)
    mer = sub.add_parser("merge")
    mer.add_argument("--inputs", type=Path, nargs="+", required=True)
    mer.add_argument("--out", type=Path, required=True)
    mer.set_defaults(func=cmd_merge)
    args = parser.parse_args()
    args.func(args)


if __name__ == "__main__":
    main()
