"""CPU per GraspEnv step with the observation read from the diagram's "features" port
(DexRepSystem: hand kinematics on its private plant context) against the same extractor on
the plant's own context (kinematics already evaluated by the reward), which GraspEnv uses.

Both envs step the same actions in the same process, interleaved step by step, and must
observe the same features (to 1e-9: the port passes the object pose as a quaternion); the ratio is per CPU-second (time.process_time).
Run: python scripts/bench_features_port.py [--object mug] [--episodes 4] [--horizon 100]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--object", default="mug")
    parser.add_argument("--episodes", type=int, default=4, help="episodes of the one object (seeds 0..N-1)")
    parser.add_argument("--horizon", type=int, default=100)
    args = parser.parse_args()

    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.env_factory import training_scenario

    port_env, env = (GraspEnv(training_scenario("adroit", args.object), "DexRep", args.horizon) for _ in range(2))
    port = port_env.diagram.GetOutputPort("features")
    port_env.observation = lambda: port.Eval(port_env.context)
    cpu = {"features port": 0.0, "extractor on the plant context": 0.0}
    print(f"load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    for episode in range(args.episodes):
        port_env.reset(episode)
        env.reset(episode)
        rng = np.random.default_rng(episode)
        for _ in range(args.horizon):
            action = rng.uniform(-0.3, 0.3, env.action_dim)
            for name, e in (("features port", port_env), ("extractor on the plant context", env)):
                start = time.process_time()
                e.step(action)
                cpu[name] += time.process_time() - start
            if not np.allclose(port_env.observation(), env.observation(), rtol=0, atol=1e-9):
                raise SystemExit("the two observations differ")
    steps = args.episodes * args.horizon
    for name, seconds in cpu.items():
        print(f"{name:<32}{1e3 * seconds / steps:7.3f} ms per step")
    ratio = cpu["features port"] / cpu["extractor on the plant context"]
    print(f"features port / extractor on the plant context: {ratio:.3f}")
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
