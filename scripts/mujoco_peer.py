"""The speed peer of the simulation benchmarks: MuJoCo stepping the paper's Adroit relocate scene.

Measured in the same run as our own numbers (never stored), from the optional `bench` extra
(`mujoco`, `gymnasium-robotics`): gymnasium-robotics' `AdroitHandRelocate-v1`, the MJCF the
paper's DAPG/DexRepNet experiments use (plant dt 2 ms, 5 physics steps per env step). The
hand is driven by uniformly random actions, one per env step, so it moves and touches.
"""

from __future__ import annotations

import time
from dataclasses import dataclass


@dataclass(frozen=True)
class PeerRate:
    physics_steps_per_cpu_s: float  # mj_step calls per CPU-second
    sim_s_per_cpu_s: float  # simulated seconds per CPU-second
    env_steps_per_cpu_s: float  # gymnasium env.step calls (5 physics steps each) per CPU-second
    version: str


def measure_relocate(cpu_seconds: float = 3.0, seed: int = 0) -> PeerRate | None:
    """MuJoCo's rates on the relocate scene, or None when the `bench` extra is not installed."""
    try:
        import gymnasium as gym
        import gymnasium_robotics
        import mujoco
    except ImportError:
        return None
    gym.register_envs(gymnasium_robotics)
    env = gym.make("AdroitHandRelocate-v1")
    env.reset(seed=seed)
    env.action_space.seed(seed)
    model, data = env.unwrapped.model, env.unwrapped.data

    steps, start = 0, time.process_time()
    while time.process_time() - start < cpu_seconds / 2:
        data.ctrl[:] = env.action_space.sample()
        for _ in range(5):
            mujoco.mj_step(model, data)
        steps += 5
    physics = steps / (time.process_time() - start)

    env.reset(seed=seed)
    n, start = 0, time.process_time()
    while time.process_time() - start < cpu_seconds / 2:
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        n += 1
        if terminated or truncated:
            env.reset()
    env_rate = n / (time.process_time() - start)
    env.close()
    return PeerRate(physics, physics * model.opt.timestep, env_rate, f"mujoco {mujoco.__version__}")
