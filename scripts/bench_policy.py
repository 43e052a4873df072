"""Benchmark the DexRepNet policy: batch-1 inference per control step and BC time per epoch.

Sizes are the shipped Adroit policy's (its recorded observation blocks and actions; fresh
weights). Baselines named in the output: the Scenario's control period, and the
paper's "about 6 minutes" for 150 BC epochs on one GPU.

Usage: python scripts/bench_policy.py [--steps 2000] [--samples 10000] [--epochs 2]
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np
import torch

from dexdrake.cli.demo import default_policy_path
from dexdrake.learn.bc import BCConfig, train_bc
from dexdrake.learn.demo_dataset import DemoDataset
from dexdrake.learn.policy import DexRepNetPolicy, load_policy
from dexdrake.systems.scenario import Scenario

PAPER_BC_SECONDS = 6 * 60  # 150 epochs, one GPU, paper's dataset


def bench_inference(policy: DexRepNetPolicy, steps: int) -> np.ndarray:
    """Per-call seconds of policy.act (deterministic mean) on one thread, batch 1."""
    rng = np.random.default_rng(0)
    obs = rng.standard_normal((steps, policy.config.obs_dim)).astype(np.float32)
    times = np.empty(steps)
    with torch.inference_mode():
        for i in range(50):  # warm-up
            policy.act(obs[i])
        for i in range(steps):
            t0 = time.perf_counter()
            policy.act(obs[i])
            times[i] = time.perf_counter() - t0
    return times


def bench_bc(policy: DexRepNetPolicy, samples: int, epochs: int) -> float:
    """Seconds per BC epoch (paper settings: Adam, batch 64, lr 1e-5) on synthetic data."""
    rng = np.random.default_rng(0)
    obs = rng.standard_normal((samples, policy.config.obs_dim)).astype(np.float32)
    act = np.tanh(obs[:, : policy.config.action_dim]).astype(np.float32)
    data = DemoDataset(obs, act)
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        train_bc(policy, data, out, BCConfig(epochs=epochs, checkpoint_every=0, progress=False))
        return (time.perf_counter() - t0) / epochs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--samples", type=int, default=10_000)
    parser.add_argument("--epochs", type=int, default=2)
    parser.add_argument("--bc-threads", type=int, nargs="+", default=sorted({1, torch.get_num_threads()}))
    args = parser.parse_args()

    torch.manual_seed(0)
    config = load_policy(default_policy_path())[0].config
    policy = DexRepNetPolicy(config).eval()
    n_params = sum(p.numel() for p in policy.parameters())
    print(f"policy ({config.feature_set}): blocks {dict(config.blocks)} -> {config.action_dim}, {n_params} parameters, "
          f"torch {torch.__version__}")
    period = Scenario().control_period

    torch.set_num_threads(1)
    times = bench_inference(policy, args.steps)
    mean_us, p50, p99 = times.mean() * 1e6, np.percentile(times, 50) * 1e6, np.percentile(times, 99) * 1e6
    print(f"inference (batch 1, 1 thread, {args.steps} steps): mean {mean_us:.1f} us, p50 {p50:.1f} us, p99 {p99:.1f} us")
    print(f"  vs the {1e3 * period:g} ms control period: {mean_us / (period * 1e6):.4f} of the period "
          f"(headroom x{period * 1e6 / mean_us:.0f})")

    per_epoch: dict[int, float] = {}
    for threads in args.bc_threads:
        torch.set_num_threads(threads)
        per_epoch[threads] = secs = bench_bc(policy.train(), args.samples, args.epochs)
        print(f"BC ({args.samples} samples, batch 64, {threads} thread(s), CPU): {secs:.2f} s/epoch, "
              f"150 epochs ~ {150 * secs / 60:.1f} min; vs paper's ~6 min on one GPU (their dataset size): "
              f"ratio {150 * secs / PAPER_BC_SECONDS:.2f}")
    if len(per_epoch) > 1:
        base = min(per_epoch)
        speedups = ", ".join(f"{n} threads x{per_epoch[base] / secs:.2f}" for n, secs in per_epoch.items())
        print(f"  speed vs {base} thread(s): {speedups}")

if __name__ == "__main__":
    main()
