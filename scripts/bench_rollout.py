"""Throughput of labelled grasp experience: rates, a per-step breakdown and MuJoCo's in the same run.

    python scripts/bench_rollout.py [--objects mug,can_soda,box_cube,bottle_wine] [--episodes-per-object 2]
        [--horizon 100] [--envs 1,8] [--repeats 2] [--bc-samples 8000] [--workers 1,2]

Everything runs the real code path of DAgger collection (`dexdrake.learn.dagger.labelled_lockstep`:
Drake physics, DexRep features, the task's reward and the expert's label, K envs
in lockstep with one policy call per step for the K observations):
- start-up: importing the stack (what the sampler's forkserver imports once for all workers,
  and the rest) and building the env for one object, in a fresh process;
- expert-driven collection (the expert acts and labels) and policy-driven collection (the
  shipped Adroit DexRep policy acts, the expert labels) at each K of `--envs`, on the same
  episodes (`--episodes-per-object` seeds per object): labelled steps and simulated seconds per
  CPU-second of this process, and MuJoCo's multiple;
- the breakdown of one labelled step, each part against its budget: plant advance (split, on sampled steps, into contact
  work = the advance minus the same advance with the object out of reach, and the rest;
  contact detection = SceneGraph's point-pair query times the plant steps per control
  period), DexRep features, reward (fingertip distances and terms), expert label, policy
  inference (per env), env reset (per step), and Python overhead (the rest);
- DAPG sampling (`samplers.rollout_lockstep`: the policy samples its actions, no expert) at
  each K: env steps per CPU-second;
- before and after in the same run: the reward's fingertip query of its own against the
  distances read from the features' query, and batch-1 torch inference (`no_grad`) against
  `act_batch` at K = 8 per env;
- MuJoCo stepping the paper's Adroit relocate scene (optional `bench` extra, see
  `mujoco_peer.py`) and our rate as a multiple of it;
- DAgger collection with 1 and 2 workers, local processes and Ray (`bench_scaling.py`:
  labelled steps per wall and per worker CPU-second, parallel efficiency), policy inference
  and a behaviour-cloning epoch.
Rates are per CPU-second (time.process_time): on a shared machine wall time is inflated by
other processes, and CPU time too, less so (shared caches and cores); so every configuration
runs `--repeats` times, the configurations interleaved, and the fastest run of each is
printed. The load average is printed before and after.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from dexdrake import argtypes  # noqa: E402

STARTUP_SNIPPET = """
import time, importlib
t0 = time.process_time()
from dexdrake.learn.samplers import PRELOAD
for name in PRELOAD:
    importlib.import_module(name)
t1 = time.process_time()
from dexdrake.systems.env_factory import GraspEnvFactory
import dexdrake.systems.grasp_env
t2 = time.process_time()
env = GraspEnvFactory("adroit", "DexRep", ({obj!r},), 10)()
env.reset(0)
print(t1 - t0, t2 - t1, time.process_time() - t2)
"""
BUDGET_MS = {"DexRep features": 0.4, "reward": 0.1, "expert label": 0.5, "policy inference": 0.15}


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
        q = np.clip(q_command, *env.scene.hand.joint_limits())
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
        (GraspEnv, "fingertip_distances", sections.wrap("reward", GraspEnv.fingertip_distances)),
        (grasp_env, "reward_terms", sections.wrap("reward", grasp_env.reward_terms)),
        (GraspEnv, "reset", sections.wrap("env reset + expert plan", GraspEnv.reset)),
        (ReactiveGrasp, "__init__", sections.wrap("env reset + expert plan", ReactiveGrasp.__init__)),
        (ReactiveGrasp, "__call__", sections.wrap("expert label", ReactiveGrasp.__call__)),
        (DexRepNetPolicy, "act_batch", sections.wrap("policy inference", DexRepNetPolicy.act_batch)),
    ]
    saved = [(obj, name, getattr(obj, name)) for obj, name, _ in patches]
    for obj, name, value in patches:
        setattr(obj, name, value)

    def undo():
        for obj, name, value in saved:
            setattr(obj, name, value)

    return split, undo


def collect(envs, jobs: list[tuple[str, int]], policy) -> tuple[int, float]:
    """(labelled steps, CPU seconds) of DAgger episodes `jobs` (object, seed), len(envs) at a
    time in lockstep: the expert acts if `policy` is None."""
    from dexdrake.learn.dagger import labelled_lockstep
    from dexdrake.systems.reactive_grasp import ReactiveGrasp

    steps, start, k = 0, time.process_time(), len(envs)
    for i in range(0, len(jobs), k):
        group = jobs[i:i + k]
        steps += sum(len(d.labels) for d in labelled_lockstep(envs[:len(group)], group, policy, 0.0, ReactiveGrasp))
    return steps, time.process_time() - start


def breakdown(jobs, k: int, policy, factory) -> tuple[dict[str, float], int, float, dict]:
    sections = Sections()
    split, undo = instrument(sections)
    try:
        envs = [factory() for _ in range(k)]
        for env in envs:  # build every scene before timing (start-up is measured apart)
            for name in dict.fromkeys(name for name, _ in jobs):
                env.reset(0, object_name=name)
        sections.total.clear()
        steps, cpu = collect(envs, jobs, policy)
    finally:
        undo()
    return dict(sections.total), steps, cpu - split["sampling"], split


def dapg_sampling(jobs, k: int, policy, factory) -> tuple[int, float]:
    """(env steps, CPU seconds) of DAPG's stochastic rollouts of the seeds of `jobs`, k at a
    time in lockstep (envs built and every object's scene made before timing)."""
    from dexdrake.learn.samplers import rollout_lockstep

    envs = [factory() for _ in range(k)]
    for env in envs:
        for name in dict.fromkeys(name for name, _ in jobs):
            env.reset(0, object_name=name)
    seeds = [seed * len(jobs) + i for i, (_, seed) in enumerate(jobs)]  # distinct; the object is drawn from the seed
    steps, start = 0, time.process_time()
    for i in range(0, len(seeds), k):
        steps += sum(len(t.rewards) for t in rollout_lockstep(envs[:len(seeds[i:i + k])], policy, seeds[i:i + k]))
    return steps, time.process_time() - start


def print_breakdown(title: str, parts: dict[str, float], steps: int, cpu: float, split: dict) -> None:
    print(f"\n{title}: {steps} labelled steps in {cpu:.2f} CPU-s -> {1e3 * cpu / steps:.2f} ms per labelled step")
    rows = dict(parts)
    rows["python overhead + rest"] = cpu - sum(parts.values())
    for name, seconds in rows.items():
        budget = f"  (budget {BUDGET_MS[name]:g} ms)" if name in BUDGET_MS else ""
        print(f"  {name:<32}{1e3 * seconds / steps:>8.3f} ms  {seconds / cpu:>6.1%}{budget}")
    if split["full"] > 0:
        advance = parts.get("plant advance", 0.0) / steps
        contact = max(split["full"] - split["free"], 0.0) / split["full"]
        print(f"    of the plant advance (sampled): contact work (advance minus the same advance without the "
              f"object) {1e3 * contact * advance:.3f} ms, dynamics + PD + the rest {1e3 * (1 - contact) * advance:.3f} ms; "
              f"contact detection (SceneGraph point pairs) {1e3 * split['detect'] / split['full'] * advance:.3f} ms")


def startup_cpu_s(obj: str) -> tuple[float, float, float]:
    """CPU seconds, in a fresh process, of (importing what the forkserver preloads for every
    worker, importing the rest of the env's stack, building a DexRep env and resetting it)."""
    out = subprocess.run([sys.executable, "-c", STARTUP_SNIPPET.format(obj=obj)], capture_output=True, text=True,
                         check=True)
    preload, rest, build = map(float, out.stdout.strip().splitlines()[-1].split())
    return preload, rest, build


def per_call_ms(fn, n: int, repeats: int = 3) -> float:
    """The fastest of `repeats` means of n calls of fn(), in CPU ms."""
    best = float("inf")
    for _ in range(repeats):
        start = time.process_time()
        for _ in range(n):
            fn()
        best = min(best, (time.process_time() - start) / n)
    return 1e3 * best


def before_after(policy, factory, objects: list[str]) -> None:
    """The old and new implementations of the reward's fingertip distances and of policy
    inference, timed side by side in this process."""
    env = factory()
    obs = env.reset(1000, object_name=objects[0])
    for _ in range(40):  # the hand near the object
        obs = env.step(policy.act(obs)[0])[0]
    env.observation()

    def own_query():
        env._tips_at = None  # forget the distances read from the features' query
        return env.fingertip_distances()

    print("\nbefore -> after, same process (fastest of 3 means, CPU ms):")
    print(f"  reward's fingertip distances: own closest-point query {per_call_ms(own_query, 300):.3f} -> read from "
          f"the features' query {per_call_ms(env.fingertip_distances, 300):.3f}")
    o32 = np.asarray(obs, dtype=np.float32)
    batch = np.stack([o32] * 8)

    def old_act():
        with torch.no_grad():
            return policy(torch.as_tensor(o32).unsqueeze(0))[0].numpy()

    old = per_call_ms(old_act, 300)
    one = per_call_ms(lambda: policy.act(o32), 300)
    eight = per_call_ms(lambda: policy.act_batch(batch, [None] * 8), 100) / 8
    print(f"  policy inference per env: batch 1 no_grad forward {old:.3f} -> act_batch K=1 {one:.3f}, "
          f"K=8 {eight:.3f} (budget {BUDGET_MS['policy inference']:g})")


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
    parser.add_argument("--episodes-per-object", type=argtypes.episodes, default=2,
                        help=argtypes.episodes_per_object_help("seeds 1000..1000+N-1"))
    parser.add_argument("--horizon", type=argtypes.steps, default=100, help=argtypes.horizon_help())
    parser.add_argument("--envs", default="1,8", help="envs in lockstep (K) to measure")
    parser.add_argument("--repeats", type=int, default=2, help="runs of each configuration (the fastest is kept)")
    parser.add_argument("--bc-samples", type=int, default=8000)
    parser.add_argument("--workers", default="1,2", help="worker counts for the scaling table ('' to skip)")
    args = parser.parse_args()
    objects = args.objects.split(",")
    ks = [int(k) for k in args.envs.split(",")]

    import mujoco_peer

    torch.set_num_threads(1)
    policy, factory = shipped_policy_env(objects, args.horizon)
    dt, period = factory.scenario.time_step, factory.scenario.control_period
    jobs = [(name, 1000 + k) for k in range(args.episodes_per_object) for name in objects]
    print(f"plant step {1e3 * dt:g} ms, control period {1e3 * period:g} ms; objects {objects}; horizon {args.horizon}; "
          f"{len(jobs)} episodes per measurement")
    print(f"load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")

    preload, rest, build = startup_cpu_s(objects[0])
    print(f"start-up (fresh process): {preload + rest + build:.1f} CPU-s = imports the forkserver preloads once for "
          f"all workers {preload:.1f} + other imports {rest:.1f} + one DexRep env built and reset {build:.2f}")
    runs: dict[tuple[str, int], tuple] = {}
    for _ in range(args.repeats):
        for k in ks:
            for driver, pol in (("expert-driven", None), ("policy-driven", policy)):
                run = breakdown(jobs, k, pol, factory)  # (parts, steps, cpu, split)
                if (driver, k) not in runs or run[2] / run[1] < runs[driver, k][2] / runs[driver, k][1]:
                    runs[driver, k] = run
    results = {}
    for (driver, k), (parts, steps, cpu, split) in runs.items():
        results[driver, k] = steps / cpu
        print_breakdown(f"{driver} DAgger collection, K={k} (fastest of {args.repeats})", parts, steps, cpu, split)

    sampling: dict[int, float] = {}
    for _ in range(args.repeats):
        for k in ks:
            steps, cpu = dapg_sampling(jobs, k, policy, factory)
            sampling[k] = max(sampling.get(k, 0.0), steps / cpu)
    print("\nDAPG sampling (stochastic policy rollouts, no expert; fastest of "
          f"{args.repeats}): " + ", ".join(f"K={k} {rate:.0f} env steps per CPU-s ({1e3 / rate:.2f} ms per step)"
                                           for k, rate in sampling.items()))
    before_after(policy, factory, objects)
    peer = mujoco_peer.measure_relocate()
    print()
    for (driver, k), rate in results.items():
        sim_rate = rate * period
        line = (f"{driver}, K={k}: {rate:.0f} labelled steps per CPU-s ({1e3 / rate:.2f} ms per step) = "
                f"{sim_rate:.2f} simulated s per CPU-s")
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
        episodes = max(args.episodes_per_object, 1) * len(objects) * max(counts)
        print(f"\nDAgger collection (expert-driven) with {args.workers} workers, local processes and Ray:")
        print_scaling(measure_scaling(objects, episodes, args.horizon, ("process", "ray"), counts),
                      f"python scripts/bench_scaling.py --objects {','.join(objects)} --episodes {episodes} "
                      f"--horizon {args.horizon} --backends process,ray --workers {args.workers}")

    epoch = bench_bc_epoch(policy.config, args.bc_samples)
    print(f"\nBC epoch ({args.bc_samples} samples of {policy.config.obs_dim}-d, batch 64, 1 thread): {epoch:.2f} s")
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
