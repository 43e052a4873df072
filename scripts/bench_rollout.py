"""Rollout and training throughput of the DexRep Adroit grasp env (prints numbers and ratios).

    python scripts/bench_rollout.py [--object mug] [--rollouts 4] [--horizon 50] [--bc-samples 8000]

Measures: env steps per second of the process sampler with 1 and 2 workers (baseline: 1
worker; the ratio is the parallel speed-up), policy inference time per step (batch 1, one
torch thread; ratio to the env step), and behaviour-cloning time per epoch on a synthetic
dataset of DexRep size (baseline: the paper's 150 epochs in about 6 minutes on one GPU, i.e.
2.4 s per epoch, dataset size unstated). The machine's load average is printed with them.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np
import torch

PAPER_BC_EPOCH_S = 6 * 60 / 150


def bench_sampler(factory, policy, workers: int, rollouts: int, seed0: int) -> float:
    """Env steps per second of `rollouts` stochastic rollouts on `workers` processes (after warm-up)."""
    from dexdrake.learn.samplers import ProcessSampler

    with ProcessSampler(factory, workers) as sampler:
        sampler.sample(policy, list(range(seed0, seed0 + workers)))  # builds every worker's env
        start = time.perf_counter()
        trajs = sampler.sample(policy, list(range(seed0 + 100, seed0 + 100 + rollouts)))
        wall = time.perf_counter() - start
    return sum(len(t) for t in trajs) / wall


def bench_inference(policy, obs: np.ndarray, n: int = 500) -> float:
    """Seconds per `policy.act` call (batch 1)."""
    torch.set_num_threads(1)
    for _ in range(20):
        policy.act(obs)
    start = time.perf_counter()
    for _ in range(n):
        policy.act(obs)
    return (time.perf_counter() - start) / n


def bench_bc_epoch(config, samples: int, epochs: int = 2) -> float:
    """Seconds per BC epoch (batch 64, one torch thread) on random data of the policy's sizes."""
    from dexdrake.learn.bc import BCConfig, train_bc
    from dexdrake.learn.demo_dataset import DemoDataset
    from dexdrake.learn.policy import DexRepNetPolicy

    rng = np.random.default_rng(0)
    data = DemoDataset(rng.normal(size=(samples, config.obs_dim)).astype(np.float32),
                       rng.uniform(-1, 1, size=(samples, config.action_dim)).astype(np.float32))
    policy = DexRepNetPolicy(config)
    with tempfile.TemporaryDirectory() as tmp:
        result = train_bc(policy, data, tmp, BCConfig(epochs=epochs, val_fraction=0.0, checkpoint_every=0,
                                                      progress=False))
        seconds = [float(r) for r in _column(result.log_csv, "seconds")]
    return float(np.mean(seconds))


def _column(path, name):
    from dexdrake.learn.curves import read_csv

    return [row[name] for row in read_csv(path)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--object", default="mug")
    parser.add_argument("--rollouts", type=int, default=4)
    parser.add_argument("--horizon", type=int, default=50)
    parser.add_argument("--bc-samples", type=int, default=8000)
    args = parser.parse_args()

    from dexdrake.eval.envs import GraspEnvFactory
    from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig

    torch.set_num_threads(1)
    torch.manual_seed(0)
    factory = GraspEnvFactory("adroit", "DexRep", (args.object,), args.horizon)
    env = factory()
    config = PolicyConfig.from_blocks(env.observation_blocks, env.action_dim, feature_set="DexRep", hand="adroit",
                                      init_log_std=-1.0)
    policy = DexRepNetPolicy(config).eval()
    obs = env.reset(0).astype(np.float32)
    print(f"load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    start = time.perf_counter()
    for _ in range(args.horizon):
        env.step(np.zeros(env.action_dim))
    step_s = (time.perf_counter() - start) / args.horizon
    print(f"in-process env step (DexRep features incl.): {1e3 * step_s:.1f} ms -> {1 / step_s:.1f} steps/s")
    rates = {w: bench_sampler(factory, policy, w, args.rollouts, 1000 * w) for w in (1, 2)}
    for w, r in rates.items():
        print(f"process sampler, {w} worker(s): {r:.1f} env steps/s ({args.rollouts} rollouts x {args.horizon} steps)")
    print(f"speed-up 2 workers vs 1 worker (baseline): {rates[2] / rates[1]:.2f}x")
    inf = bench_inference(policy, obs)
    print(f"policy inference: {1e3 * inf:.2f} ms per step = {inf / step_s:.1%} of one env step (baseline)")
    epoch = bench_bc_epoch(config, args.bc_samples)
    print(f"BC epoch ({args.bc_samples} samples of {config.obs_dim}-d, batch 64, 1 thread): {epoch:.2f} s; "
          f"{epoch / PAPER_BC_EPOCH_S:.2f}x the paper's {PAPER_BC_EPOCH_S:.1f} s per epoch on a GPU (baseline)")
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
