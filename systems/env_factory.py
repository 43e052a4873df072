"""GraspEnv factories shared by training, evaluation and the demo.

`GraspEnvFactory` is a picklable callable (a frozen dataclass), so worker processes of the
rollout samplers and of the evaluator can rebuild the same env.
"""

from __future__ import annotations

from dataclasses import dataclass

from dexdrake.errors import DexdrakeError
from dexdrake.perceived_pose import PerceptionModel
from dexdrake.task import TaskSpec


@dataclass(frozen=True)
class GraspEnvFactory:
    """Builds `GraspEnv` for `hand` with `feature_set` observations over `objects`."""

    hand: str
    feature_set: str | None
    objects: tuple[str, ...]
    horizon: int = 200
    object_from_seed: bool = False  # reset(seed) runs objects[seed % len(objects)] (balanced training batches)
    task: TaskSpec = TaskSpec()  # reward and success criterion
    perception: PerceptionModel = PerceptionModel()  # how the features see the object pose
    arm_action: str = "joints"  # how the actions command the arm (dexdrake/hands/action_map.py)

    def __post_init__(self) -> None:
        if not self.objects:
            raise DexdrakeError("GraspEnvFactory needs at least one object")
        if self.horizon < 1:
            raise DexdrakeError(f"horizon must be >= 1, got {self.horizon}")

    @property
    def scenario(self):
        """The sim Scenario the envs run (the defaults' plant step, control period and driver
        limits for `hand`, this factory's perception model); what training records in its
        checkpoints (`scenario_record`)."""
        return training_scenario(self.hand, self.objects[0], self.perception)

    def __call__(self):
        from dexdrake.systems.grasp_env import GraspEnv

        env = GraspEnv(self.scenario, feature_set=self.feature_set, horizon=self.horizon, task=self.task,
                       objects=list(self.objects), arm_action=self.arm_action)
        return ObjectFromSeed(env) if self.object_from_seed else env


def training_scenario(hand: str, object_name: str | None = None, perception: PerceptionModel = PerceptionModel()):
    """The sim Scenario of training, evaluation and the demo for `hand` and `object_name`
    (None: the default object) seeing the object through `perception` (default: the true
    pose): the Scenario defaults (systems/scenario.py) for the rest."""
    from dexdrake.systems.scenario import Scenario

    return Scenario(name="training", hand=hand, perception=perception,
                    **({} if object_name is None else {"object": object_name}))


class ObjectFromSeed:
    """A GraspEnv whose `reset(seed)` runs object seed % len(objects) (placement still from the seed)."""

    def __init__(self, env):
        self.env = env

    def reset(self, seed: int):
        return self.env.reset(seed, object_name=self.env.objects[seed % len(self.env.objects)])

    def __getattr__(self, name: str):
        return getattr(self.env, name)


def env_factory_for_policy(
    policy_config, objects: list[str], horizon: int, object_from_seed: bool = False, task: TaskSpec = TaskSpec(),
    perception: PerceptionModel = PerceptionModel(),
) -> GraspEnvFactory:
    """The factory matching a policy's recorded hand, feature set and arm action
    (`check_policy_fits`), its envs seeing the object through `perception`."""
    from dexdrake.learn.policy import check_policy_fits

    hand, feature_set = policy_config.hand, policy_config.feature_set
    check_policy_fits(policy_config, hand, feature_set, "the policy")
    return GraspEnvFactory(hand, feature_set, tuple(objects), horizon, object_from_seed, task, perception,
                           policy_config.arm_action)
