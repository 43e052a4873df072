"""Build the shipped default policy: scripted demos -> DexRep dataset -> BC -> eval -> models/weights.

    python scripts/build_default_policy.py [--work runs/default_policy] [--epochs 40] [--lr 1e-4]
        [--seeds 2] [--seen-episodes 2] [--unseen-episodes 5] [--workers 2]
        [--timing fast|early_lift] [--noise 0.05 --noise-seed 0]

Each stage is a real command (printed and recorded in the manifest) and is skipped when its
output already exists in --work. The result: models/weights/adroit_dexrep_policy.pt (the best
BC checkpoint, fp32), adroit_dexrep_policy.json (commands, seeds, dataset metadata, feature
set, compute, metrics) and eval_seen.md / eval_unseen.md. Model selection uses the BC
validation split of the training demos only; the unseen objects are evaluated once.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DISPLAY = {sys.executable: "python", str(Path(sys.executable).with_name("dexdrake")): "dexdrake"}
DATA_SOURCE = ("successful scripted grasps (systems/scripted_grasp.py ScriptedGrasp, phase timing "
               "dexdrake.eval.scripted_data.TIMINGS[{timing!r}]) on training objects{noise}; not the human-demo replay")


def run(cmd: list[str], done: Path, log: list[dict]) -> None:
    """Run `cmd` unless `done` exists; record the command and its wall time."""
    text = shlex.join([DISPLAY.get(w, w) for w in cmd])
    if done.exists():
        print(f"[skip, {done} exists] {text}")
        log.append({"command": text, "skipped": True})
        return
    print(f"[run] {text}", flush=True)
    start = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT)
    log.append({"command": text, "wall_s": round(time.perf_counter() - start, 1)})


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def main() -> None:
    from dexdrake.eval.scripted_data import TIMINGS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("runs/default_policy"))
    parser.add_argument("--epochs", type=int, default=40)
    parser.add_argument("--lr", type=float, default=1e-4)
    parser.add_argument("--seeds", type=int, default=2, help="scripted episodes per training object")
    parser.add_argument("--first-seed", type=int, default=1000, help="first demo seed (eval uses 0..)")
    parser.add_argument("--seen-episodes", type=int, default=2)
    parser.add_argument("--unseen-episodes", type=int, default=5)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--timing", default="fast", choices=sorted(TIMINGS),
                        help="script phase timing (dexdrake.eval.scripted_data.TIMINGS)")
    parser.add_argument("--noise", type=float, default=0.0,
                        help="DART-style OU noise std on executed demo actions (normalised units; 0: off)")
    parser.add_argument("--noise-seed", type=int, default=0)
    args = parser.parse_args()

    py, dexdrake = sys.executable, str(Path(sys.executable).with_name("dexdrake"))
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    raw, data, bc = work / "scripted_raw.npz", work / "scripted_dexrep.npz", work / "bc"
    log: list[dict] = []
    start = time.perf_counter()
    run([py, "scripts/build_scripted_dataset.py", "record", "--objects", "train", "--seeds", str(args.seeds),
         "--first-seed", str(args.first_seed), "--workers", str(args.workers), "--timing", args.timing,
         "--noise", str(args.noise), "--noise-seed", str(args.noise_seed), "--out", str(raw)], raw, log)
    run([py, "scripts/build_scripted_dataset.py", "featurise", "--raw", str(raw), "--feature-set", "DexRep",
         "--out", str(data)], data, log)
    run([dexdrake, "train", "bc", "--data", str(data), "--out", str(bc), "--epochs", str(args.epochs), "--lr",
         str(args.lr), "--batch", "64", "--seed", "0"], bc / "bc_last.pt", log)
    policy = bc / "bc_best.pt"
    for label, episodes in (("unseen", args.unseen_episodes), ("seen", args.seen_episodes)):
        run([dexdrake, "eval", "--policy", str(policy), "--objects", label, "--episodes", str(episodes), "--seed", "0",
             "--workers", str(args.workers), "--out", str(work / "eval")], work / "eval" / f"eval_{label}.json", log)

    weights = ROOT / "models" / "weights"
    target = weights / "adroit_dexrep_policy.pt"
    shutil.copyfile(policy, target)
    metrics = {}
    for label in ("seen", "unseen"):
        report = json.loads((work / "eval" / f"eval_{label}.json").read_text())
        metrics[label] = {k: report[k] for k in ("average_pct", "per_object", "episodes_per_object", "seed", "horizon",
                                                  "command", "wall_s", "workers")}
        text = (work / "eval" / f"eval_{label}.md").read_text().replace(str(policy), "models/weights/adroit_dexrep_policy.pt"
                                                                         f" (copied from {policy})")
        (weights / f"eval_{label}.md").write_text(text)

    import torch

    from dexdrake.dexrep.pointnet import default_encoder_path
    from dexdrake.learn.demo_dataset import load_demo_dataset
    from dexdrake.learn.policy import load_policy

    net, meta = load_policy(target)
    dataset_meta = load_demo_dataset(data).metadata
    encoder = default_encoder_path()
    noise_text = (f", executed with OU action noise std {args.noise} (seed {args.noise_seed}) and labelled with the "
                  "clean expert action (DART-style)") if args.noise > 0 else ""
    manifest = {
        "policy": "models/weights/adroit_dexrep_policy.pt",
        "sha256": sha256(target),
        "hand": net.config.hand,
        "feature_set": net.config.feature_set,
        "observation_blocks": dict(net.config.blocks),
        "parameters": sum(p.numel() for p in net.parameters()),
        "pointnet_encoder": {"path": "models/weights/pointnet_encoder.pt", "sha256": sha256(encoder)},
        "training": {
            "stages": "behaviour cloning only (no DAPG)",
            "bc": meta.get("bc_config"),
            "selected_epoch": meta.get("epoch"),
            "val_loss": meta.get("val_loss"),
            "paper_bc": "150 epochs, batch 64, lr 1e-5; then 500 DAPG iterations",
        },
        "dataset": {"source": DATA_SOURCE.format(timing=args.timing, noise=noise_text), "path": str(data),
                    "metadata": {k: v for k, v in dataset_meta.items()}},
        "commands": log + [{"command": shlex.join(["python", *sys.argv])}],
        "compute": {"cpu_cores": os.cpu_count(), "gpu": None, "torch_threads": 1, "platform": platform.platform(),
                    "load_average_at_end": round(os.getloadavg()[0], 1), "note": "2 CPU cores shared with other jobs",
                    "pipeline_wall_s_this_run": round(time.perf_counter() - start, 1), "torch": torch.__version__},
        "metrics": metrics,
    }
    (weights / "adroit_dexrep_policy.json").write_text(json.dumps(manifest, indent=1) + "\n")
    print(f"wrote {target} ({target.stat().st_size / 1e6:.2f} MB), its manifest and eval tables; "
          f"seen {metrics['seen']['average_pct']:.1f} %, unseen {metrics['unseen']['average_pct']:.1f} %")


if __name__ == "__main__":
    main()
