"""CPU per control step of the DexRep observation in GraspEnv, against a straightforward peer.

The peer (`reference_features`) computes the same feature vector group by group from the
public per-feature functions of dexdrake/dexrep/features.py, sharing no work: the body pose
of every hand point read by name, the wrist and the grid anchor read again, a closest-point
query for the surface and another for local-geo. tests/test_dexrep.py holds the
FeatureExtractor to its bits.

Each episode (the grasp expert drives the hand; seeds 0, 1, ...) runs twice, interleaved: once
with GraspEnv's observation from its FeatureExtractor, once from the peer. Both see the same
states (the observation does not feed back into the physics), their observations must be
equal bit for bit, and the CPU time (time.process_time) of `GraspEnv.observation` inside
`step` is summed for each: what scripts/bench_rollout.py reports as "DexRep features".
Run: python scripts/bench_features.py [--hands allegro_z1,adroit] [--feature-set DexRep+Vel]
    [--object bottle_small] [--episodes 3] [--horizon 100]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from dexdrake.dexrep import features as F
from dexdrake.dexrep.feature_sets import FEATURE_SETS
from dexdrake.dexrep.geometry import ClosestPoints, ObjectGeometry


def reference_features(hand, plant, hand_instance, geometry: ObjectGeometry, feature_set: str, plant_context,
                       X_WO, surface_clip: float = F.SURFACE_CLIP) -> np.ndarray:
    """The fast-path feature vector of `feature_set`, computed group by group with no shared work."""
    X = F.as_matrix(X_WO)
    R, t = X[:3, :3], X[:3, 3]

    def pose(body: str) -> np.ndarray:
        return plant.EvalBodyPoseInWorld(plant_context, plant.GetBodyByName(body, hand_instance)).GetAsMatrix34()

    def hand_points() -> np.ndarray:  # one einsum for all: it rounds a row by its place in the batch
        poses = np.array([pose(p.body) for p in hand.dexrep_points])
        return np.einsum("pij,pj->pi", poses, [[*p.offset, 1.0] for p in hand.dexrep_points])

    def closest():
        return geometry.closest_points((hand_points() - t) @ R)

    joints = [plant.GetJointByName(j, hand_instance) for j in hand.policy_joints]
    parts = []
    for group in FEATURE_SETS[feature_set]:
        if group == "hand":
            q = np.array([j.GetOnePosition(plant_context) for j in joints])
            X_WH = np.vstack([pose(hand.wrist_body), [0.0, 0.0, 0.0, 1.0]])
            parts.append(F.hand_state(q, hand_points(), X_WH))
        elif group == "hand_vel":
            parts.append(np.array([j.GetOneVelocity(plant_context) for j in joints]))
        elif group == "hand2obj":
            parts.append((hand_points() - t).ravel())
        elif group == "pglo":
            parts += [geometry.global_feature, F.pose_6d(X)]
        elif group == "local_geo":
            parts.append(geometry.local_features[geometry.nearest_samples(closest().points)].ravel())
        elif group in ("surf", "occ_surf"):
            if group == "occ_surf":
                anchor = pose(hand.occupancy.body)
                X_WG = np.eye(4)
                X_WG[:3, :3] = anchor[:, :3]
                X_WG[:3, 3] = anchor @ [*hand.occupancy.offset, 1.0]
                parts.append(F.occupancy(X_WG, X, geometry, hand.occupancy.size, hand.occupancy.resolution))
            cp = closest()
            parts.append(F.surface_from_closest(ClosestPoints(cp.distance, cp.points, cp.normals @ R.T),
                                                surface_clip))
    return np.concatenate(parts, dtype=np.float64)


def measure(hand_name: str, feature_set: str, obj: str, episodes: int, horizon: int) -> dict[str, float]:
    """CPU ms per step of the observation, extractor and peer, over the same expert episodes."""
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.reactive_grasp import ReactiveGrasp

    env = GraspEnv(training_scenario(hand_name, obj), feature_set, horizon)
    extractor_observation = env.observation

    def peer_observation() -> np.ndarray:
        s = env.scene
        return reference_features(s.hand, s.plant, s.hand_instance, env.geometry, feature_set, env.plant_context,
                                  env.seen_object_pose())

    cpu = {"extractor": 0.0, "peer": 0.0}
    observed: dict[str, list[np.ndarray]] = {"extractor": [], "peer": []}

    def timed(name, fn):
        def observation() -> np.ndarray:
            start = time.process_time()
            out = fn()
            cpu[name] += time.process_time() - start
            observed[name].append(out)
            return out
        return observation

    steps = 0
    for episode in range(episodes):
        order = ("extractor", "peer") if episode % 2 == 0 else ("peer", "extractor")
        for name in order:
            observed[name].clear()
            env.observation = timed(name, extractor_observation if name == "extractor" else peer_observation)
            result = env.rollout(ReactiveGrasp, episode)
        for a, b in zip(*observed.values(), strict=True):
            if not np.array_equal(a, b):
                raise SystemExit(f"{hand_name}: the extractor's and the peer's observations differ "
                                 f"(max abs {np.max(np.abs(a - b)):.3g})")
        steps += len(observed["extractor"])
        del result
    return {name: 1e3 * seconds / steps for name, seconds in cpu.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hands", default="allegro_z1,adroit")
    parser.add_argument("--feature-set", default="DexRep+Vel")
    parser.add_argument("--object", default="bottle_small")
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--horizon", type=int, default=100)
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    for hand in args.hands.split(","):
        ms = measure(hand, args.feature_set, args.object, args.episodes, args.horizon)
        print(f"{hand} {args.feature_set} on {args.object}: observation {ms['extractor']:.3f} ms per step, "
              f"peer {ms['peer']:.3f} ms; peer / extractor {ms['peer'] / ms['extractor']:.2f}x (same bits)")
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
