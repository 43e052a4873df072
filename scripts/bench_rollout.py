"""Throughput of labelled grasp experience: rates, a per-step breakdown and MuJoCo's in the same run.

    python scripts/bench_rollout.py [--objects mug,can_soda,box_cube,bottle_wine] [--episodes 1]
        [--horizon 100] [--bc-samples 8000] [--workers 1,2]

Everything runs the real code path of DAgger collection (`dexdrake.learn.dagger.labelled_episode`:
Drake physics, DexRep features, the task's reward and the state-driven expert's label):
- start-up: importing the stack and building the env for one object, in a fresh process;
- expert-driven collection (the expert acts and labels) and policy-driven collection (the
  shipped Adroit DexRep policy acts, the expert labels): labelled steps and simulated
  seconds per CPU-second of this process;
- the breakdown of one labelled step: plant advance (split, on sampled steps, into contact
  work = the advance minus the same advance with the object out of reach, and the rest;
  contact detection = SceneGraph's point-pair query times the plant steps per control
  period), DexRep features, reward (fingertip distances), expert label, policy inference,
  env reset (per step), and Python overhead (the rest);
- MuJoCo stepping the paper's Adroit relocate scene (optional `bench` extra, see
  `mujoco_peer.py`) and our rate as a multiple of it;
- DAgger collection with 1 and 2 workers, local processes and Ray (`bench_scaling.py`:
  labelled steps per wall and per worker CPU-second, parallel efficiency), policy inference
  and a behaviour-cloning epoch.
Rates are per CPU-second (time.process_time): on a shared machine wall time is inflated by
other processes; the load average is printed before and after.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import replace

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

STARTUP_SNIPPET = """
import time
t0 = time.process_time()
from dexdrake.systems.env_factory import GraspEnvFactory
env = GraspEnvFactory("adroit", "DexRep", ({obj!r},), 10)()
env.reset(0)
print(time.process_time() - t0)
"""


class Sections:
    """CPU time per named section; nested sections are subtracted from their parent."""

    def __init__(self) -> None:
        self.total: dict[str, float] = defaultdict(float)
        self._stack: list[list] = []

    def wrap(self, name: str, fn):
        def timed(*args, **kwargs):
            self._stack.append([name, time.process_time(), 0.0])
            try:
                return fn(*args, **kwargs)
            finally:
                _, start, children = self._stack.pop()
                spent = time.process_time() - start
                self.total[name] += spent - children
                if self._stack:
                    self._stack[-1][2] += spent
        return timed

    def add(self, name: str, seconds: float) -> None:
        self.total[name] += seconds
        if self._stack:
            self._stack[-1][2] += seconds


def instrument(sections: Sections, sample_every: int = 5):
    """Patch the env, expert and policy classes so their work is timed by `sections`; every
    `sample_every`-th plant advance is also re-run on a copy without the object to split off
    the contact work. Returns (the sampled split's sums, a function that undoes the patches)."""
    from pydrake.math import RigidTransform
    from pydrake.systems.analysis import Simulator

    from dexdrake.learn.policy import DexRepNetPolicy
    from dexdrake.systems import grasp_env
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.reactive_grasp import ReactiveGrasp

    split = {"n": 0, "full": 0.0, "free": 0.0, "detect": 0.0, "sampling": 0.0}
    original_step = GraspEnv.step_positions

    def step_positions(env, q_command):
        split["n"] += 1
        if split["n"] % sample_every == 0:
            start = time.process_time()
            _sample_contact_split(env, q_command, split)
            split["sampling"] += time.process_time() - start  # the benchmark's own work, not counted
        return original_step(env, q_command)

    class TimedSimulator(Simulator):
        def AdvanceTo(self, t):  # noqa: N802 (Drake's name)
            start = time.process_time()
            out = super().AdvanceTo(t)
            sections.add("plant advance", time.process_time() - start)
            return out

    def _sample_contact_split(env, q_command, acc):
        diagram, t = env.diagram, env.context.get_time() + env.scenario.control_period
        q = np.clip(q_command, env._mid - env._half, env._mid + env._half)
        runs = {}
        for key, far in (("full", False), ("free", True)):
            ctx = env.context.Clone()
            diagram.GetInputPort("command").FixValue(ctx, q)
            if far:
                plant_ctx = env.scene.plant.GetMyMutableContextFromRoot(ctx)
                env.scene.plant.SetFreeBodyPose(plant_ctx, env.scene.object_body, RigidTransform([5.0, 5.0, 5.0]))
            sim = Simulator(diagram, ctx)
            start = time.process_time()
            sim.AdvanceTo(t)
            runs[key] = time.process_time() - start
        query = env.scene.diagram.GetOutputPort("query_object").Eval(env.scene.diagram.GetMyContextFromRoot(env.context))
        start = time.process_time()
        query.ComputePointPairPenetration()
        steps = round(env.scenario.control_period / env.scenario.time_step)
        acc["detect"] += (time.process_time() - start) * steps
        acc["full"] += runs["full"]
        acc["free"] += runs["free"]

    patches = [
        (grasp_env, "Simulator", TimedSimulator),
        (GraspEnv, "step_positions", step_positions),
        (GraspEnv, "observation", sections.wrap("DexRep features", GraspEnv.observation)),
        (GraspEnv, "fingertip_distances", sections.wrap("reward (fingertip distances)", GraspEnv.fingertip_distances)),
        (GraspEnv, "reset", sections.wrap("env reset + expert plan", GraspEnv.reset)),
        (ReactiveGrasp, "__init__", sections.wrap("env reset + expert plan", ReactiveGrasp.__init__)),
        (ReactiveGrasp, "__call__", sections.wrap("expert label", ReactiveGrasp.__call__)),
        (DexRepNetPolicy, "act", sections.wrap("policy inference", DexRepNetPolicy.act)),
    ]
    saved = [(obj, name, getattr(obj, name)) for obj, name, _ in patches]
    for obj, name, value in patches:
        setattr(obj, name, value)

    def undo():
        for obj, name, value in saved:
            setattr(obj, name, value)

    return split, undo


def collect(env, objects, episodes: int, policy, seed0: int) -> tuple[int, float]:
    """(labelled steps, CPU seconds) of DAgger episodes: the expert acts if `policy` is None."""
    from dexdrake.learn.dagger import labelled_episode
    from dexdrake.systems.reactive_grasp import ReactiveGrasp

    steps, start = 0, time.process_time()
    for k in range(episodes):
        for name in objects:
            steps += len(labelled_episode(env, name, seed0 + k, policy, 0.0, ReactiveGrasp).labels)
    return steps, time.process_time() - start


def breakdown(objects, episodes: int, policy, factory, seed0: int) -> tuple[dict[str, float], int, float, dict]:
    sections = Sections()
    split, undo = instrument(sections)
    try:
        env = factory()
        for name in objects:  # build every scene before timing (start-up is measured apart)
            env.reset(0, object_name=name)
        sections.total.clear()
        steps, cpu = collect(env, objects, episodes, policy, seed0)
    finally:
        undo()
    return dict(sections.total), steps, cpu - split["sampling"], split


def print_breakdown(title: str, parts: dict[str, float], steps: int, cpu: float, split: dict) -> None:
    print(f"\n{title}: {steps} labelled steps in {cpu:.2f} CPU-s -> {1e3 * cpu / steps:.2f} ms per labelled step")
    rows = dict(parts)
    rows["python overhead + rest"] = cpu - sum(parts.values())
    for name, seconds in rows.items():
        print(f"  {name:<32}{1e3 * seconds / steps:>8.3f} ms  {seconds / cpu:>6.1%}")
    if split["full"] > 0:
        advance = parts.get("plant advance", 0.0) / steps
        contact = max(split["full"] - split["free"], 0.0) / split["full"]
        print(f"    of the plant advance (sampled): contact work (advance minus the same advance without the "
              f"object) {1e3 * contact * advance:.3f} ms, dynamics + PD + the rest {1e3 * (1 - contact) * advance:.3f} ms; "
              f"contact detection (SceneGraph point pairs) {1e3 * split['detect'] / split['full'] * advance:.3f} ms")


def startup_cpu_s(obj: str) -> float:
    """CPU seconds (including imports) to build a DexRep env and reset it, in a fresh process."""
    out = subprocess.run([sys.executable, "-c", STARTUP_SNIPPET.format(obj=obj)], capture_output=True, text=True,
                         check=True)
    return float(out.stdout.strip().splitlines()[-1])


def bench_bc_epoch(config, samples: int, epochs: int = 2) -> float:
    """Seconds per BC epoch (batch 64, one torch thread) on random data of the policy's sizes."""
    from dexdrake.learn.bc import BCConfig, train_bc
    from dexdrake.learn.curves import read_csv
    from dexdrake.learn.demo_dataset import DemoDataset
    from dexdrake.learn.policy import DexRepNetPolicy

    rng = np.random.default_rng(0)
    data = DemoDataset(rng.normal(size=(samples, config.obs_dim)).astype(np.float32),
                       rng.uniform(-1, 1, size=(samples, config.action_dim)).astype(np.float32))
    with tempfile.TemporaryDirectory() as tmp:
        result = train_bc(DexRepNetPolicy(config), data, tmp,
                          BCConfig(epochs=epochs, val_fraction=0.0, checkpoint_every=0, progress=False))
        return float(np.mean([float(r["seconds"]) for r in read_csv(result.log_csv)]))


def shipped_policy_env(objects: list[str], horizon: int):
    """(the shipped Adroit policy, the env factory of its hand and feature set over `objects`)."""
    from dexdrake.cli.demo import default_policy_path
    from dexdrake.learn.policy import load_policy
    from dexdrake.systems.env_factory import env_factory_for_policy

    policy = load_policy(default_policy_path())[0]
    return policy, env_factory_for_policy(policy.config, objects, horizon)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", default="mug,can_soda,box_cube,bottle_wine")
    parser.add_argument("--episodes", type=int, default=1, help="expert episodes per object")
    parser.add_argument("--horizon", type=int, default=100)
    parser.add_argument("--bc-samples", type=int, default=8000)
    parser.add_argument("--workers", default="1,2", help="worker counts for the scaling table ('' to skip)")
    args = parser.parse_args()
    objects = args.objects.split(",")

    import mujoco_peer

    torch.set_num_threads(1)
    policy, factory = shipped_policy_env(objects, args.horizon)
    dt, period = factory.scenario.time_step, factory.scenario.control_period
    print(f"plant step {1e3 * dt:g} ms, control period {1e3 * period:g} ms; objects {objects}; horizon {args.horizon}")
    print(f"load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")

    print(f"start-up (fresh process: imports, one DexRep env built and reset): {startup_cpu_s(objects[0]):.1f} CPU-s")
    results = {}
    for driver, pol in (("expert-driven", None), ("policy-driven", policy)):
        parts, steps, cpu, split = breakdown(objects, args.episodes, pol, factory, 1000)
        results[driver] = steps / cpu
        print_breakdown(f"{driver} DAgger collection", parts, steps, cpu, split)

    peer = mujoco_peer.measure_relocate()
    print()
    for driver, rate in results.items():
        sim_rate = rate * period
        line = f"{driver}: {rate:.0f} labelled steps per CPU-s = {sim_rate:.2f} simulated s per CPU-s"
        if peer is not None:
            line += f" = {sim_rate / peer.sim_s_per_cpu_s:.3f}x MuJoCo"
        print(line)
    if peer is None:
        print("MuJoCo peer: not measured (install the optional extra: pip install -e '.[bench]')")
    else:
        print(f"MuJoCo peer ({peer.version}, Adroit relocate, dt 2 ms, random actions): "
              f"{peer.physics_steps_per_cpu_s:.0f} physics steps per CPU-s = {peer.sim_s_per_cpu_s:.1f} simulated s "
              f"per CPU-s; {peer.env_steps_per_cpu_s:.0f} gymnasium env steps per CPU-s (no features, no labels)")

    if args.workers:
        from bench_scaling import measure_scaling, print_scaling

        counts = tuple(int(w) for w in args.workers.split(","))
        episodes = max(args.episodes, 1) * len(objects) * max(counts)
        print(f"\nDAgger collection (expert-driven) with {args.workers} workers, local processes and Ray:")
        print_scaling(measure_scaling(objects, episodes, args.horizon, ("process", "ray"), counts),
                      f"python scripts/bench_scaling.py --objects {','.join(objects)} --episodes {episodes} "
                      f"--horizon {args.horizon} --backends process,ray --workers {args.workers}")

    obs = factory().reset(0).astype(np.float32)
    start, n = time.process_time(), 300
    for _ in range(n):
        policy.act(obs)
    inference = (time.process_time() - start) / n
    print(f"\npolicy inference (batch 1, one thread): {1e3 * inference:.2f} ms per step")
    epoch = bench_bc_epoch(policy.config, args.bc_samples)
    print(f"BC epoch ({args.bc_samples} samples of {policy.config.obs_dim}-d, batch 64, 1 thread): {epoch:.2f} s")
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
