"""The map between normalised actions and joint set-points (dexdrake/hands/action_map.py):
joint ranges, and the palm pose solved by the arm's inverse kinematics, in the training env
and in the deployed policy system alike."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from dexdrake.errors import DexdrakeError
from dexdrake.hands.action_map import ActionMap
from dexdrake.hands.description import _palm_pose_action, load_hand


@pytest.fixture(scope="module")
def allegro_z1():
    return load_hand("allegro_z1")


def _near_pregrasp(hand, rng, spread=0.15):
    lo, hi = hand.joint_limits()
    return np.clip(hand.pregrasp_vector() + rng.normal(0.0, spread, len(lo)), lo, hi)


def test_joint_actions_span_each_joints_range():
    hand = load_hand("adroit")
    lo, hi = hand.joint_limits()
    actions = ActionMap(hand)
    q = np.random.default_rng(0).uniform(lo, hi)
    assert np.allclose(actions.command(actions.normalise(q), q * 0), q)
    assert np.allclose(actions.command(-np.ones(len(lo)), q), lo, rtol=0, atol=1e-12)
    beyond = actions.command(np.full(len(lo), 3.0), q)  # the command guard clips it (and counts)
    assert np.allclose(beyond, (hi + lo) / 2 + 3.0 * (hi - lo) / 2)


def test_palm_pose_actions_are_the_palm_pose_solved_back_to_the_same_joints(allegro_z1):
    """normalise -> command returns the set-points from a measured arm nearby; the arm's
    actions move the grasp centre over the description's box and turn the palm."""
    actions = ActionMap(allegro_z1, "palm_pose")
    n, box = len(allegro_z1.arm_joints), allegro_z1.palm_pose_action
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = _near_pregrasp(allegro_z1, rng)
        measured = q + rng.normal(0.0, 0.01, len(q))
        assert np.allclose(actions.command(actions.normalise(q), measured), q, atol=1e-4)
    a = np.zeros(len(q))
    a[:3] = [0.5, -0.5, 0.2]
    centre, R = actions.ik.palm_pose(actions.command(a, allegro_z1.pregrasp_vector())[:n])
    lower, upper = np.array(box.lower), np.array(box.upper)
    assert np.allclose(centre, (upper + lower) / 2 + a[:3] * (upper - lower) / 2, atol=1e-4)
    a[3:6] = [0.0, 0.0, 0.5]  # a turn of 0.5 * rotation about the pre-grasp palm's z axis
    turned = actions.ik.palm_pose(actions.command(a, allegro_z1.pregrasp_vector())[:n])[1]
    angle = np.arccos(np.clip((np.trace(R.T @ turned) - 1) / 2, -1, 1))
    assert angle == pytest.approx(0.5 * box.rotation, abs=1e-3)
    assert np.allclose(actions.normalise(actions.command(a, allegro_z1.pregrasp_vector()))[:6], a[:6], atol=1e-4)


def test_a_non_finite_palm_action_is_held_and_a_hand_without_the_box_is_refused(allegro_z1):
    actions = ActionMap(allegro_z1, "palm_pose")
    a = np.zeros(allegro_z1.num_actuators)
    a[2] = np.nan
    q = actions.command(a, allegro_z1.pregrasp_vector())
    assert np.isnan(q[:6]).all() and np.isfinite(q[6:]).all()  # the command guard holds the arm
    with pytest.raises(DexdrakeError, match="has no palm_pose arm action"):
        ActionMap(load_hand("adroit"), "palm_pose")
    with pytest.raises(DexdrakeError, match="unknown arm action 'cartesian'"):
        ActionMap(allegro_z1, "cartesian")
    with pytest.raises(DexdrakeError, match="lower < upper"):
        _palm_pose_action({"name": "h", "palm_pose_action": {"lower": [0, 0, 0], "upper": [1, 1, 0], "rotation": 1}})


def test_the_env_and_the_policy_system_map_an_action_alike(allegro_z1, tmp_path):
    """One palm-pose action: GraspEnv.step sends the set-points ActionMap.command gives from
    the plant's arm, and PolicySystem's "command" output is the same map of its action."""
    import torch

    from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.policy_system import PolicySystem

    env = GraspEnv(training_scenario("allegro_z1"), feature_set=None, horizon=5, arm_action="palm_pose")
    env.reset(3)
    q_measured = env.scene.hand_positions(env.plant_context)
    a = np.clip(env.normalise(q_measured) + 0.05, -1, 1)
    env.step(a)
    expected = env.actions.command(a, q_measured)
    assert np.allclose(env.q_command, expected, atol=1e-12)

    n = allegro_z1.num_actuators
    policy = DexRepNetPolicy(PolicyConfig.from_blocks({"hand": 4}, n, hand="allegro_z1", arm_action="palm_pose"))
    with torch.no_grad():
        policy.mlp[-1].weight.zero_()
        policy.mlp[-1].bias.copy_(torch.as_tensor(a, dtype=torch.float32))
    builder = DiagramBuilder()
    system = builder.AddSystem(PolicySystem(policy, 0.02, actions=env.actions))
    obs = builder.AddSystem(ConstantVectorSource(np.zeros(4)))
    hand_state = builder.AddSystem(ConstantVectorSource(np.r_[q_measured, np.zeros(n)]))
    builder.Connect(obs.get_output_port(), system.GetInputPort("observation"))
    builder.Connect(hand_state.get_output_port(), system.GetInputPort("hand_state"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    system.hold(system.GetMyMutableContextFromRoot(simulator.get_mutable_context()), q_measured)
    command = system.GetOutputPort("command")
    assert np.array_equal(command.Eval(system.GetMyContextFromRoot(simulator.get_context())), q_measured)
    simulator.AdvanceTo(0.01)
    got = command.Eval(system.GetMyContextFromRoot(simulator.get_context()))
    assert np.allclose(got, env.actions.command(policy.act(np.zeros(4))[0], q_measured), atol=1e-9)
    assert np.allclose(got, expected, atol=1e-5)  # the float32 network's action: the env's to rounding


def test_a_residual_arm_needs_joint_actions(allegro_z1, tmp_path):
    from dexdrake.learn.dagger import DaggerConfig, train_dagger
    from dexdrake.learn.policy import PolicyConfig, arm_action_map
    from dexdrake.systems.env_factory import GraspEnvFactory
    from dexdrake.systems.reactive_grasp import ReactiveGrasp

    config = replace(DaggerConfig(), hand="allegro_z1", residual_arm=True, arm_action="palm_pose")
    with pytest.raises(DexdrakeError, match="--residual-arm needs --arm-action joints"):
        train_dagger(["sphere_small"], tmp_path / "d", GraspEnvFactory, ReactiveGrasp, config)
    assert not (tmp_path / "d").exists()
    with pytest.raises(DexdrakeError, match="leads the arm's joints"):
        arm_action_map(PolicyConfig.from_blocks({"hand": 4}, 22, hand="allegro_z1", arm_action="palm_pose"))


def test_palm_step_actions_move_the_palm_from_where_it_is_measured(allegro_z1):
    """normalise(q, measured) -> command(., measured) returns q; an action of 0 holds the measured
    palm; an action moves the grasp centre by action * step and turns the palm by action * step_rotation."""
    actions = ActionMap(allegro_z1, "palm_step")
    n, box = len(allegro_z1.arm_joints), allegro_z1.palm_pose_action
    rng = np.random.default_rng(2)
    for _ in range(20):
        measured = _near_pregrasp(allegro_z1, rng)
        q = measured + np.concatenate([rng.normal(0.0, 0.03, n), np.zeros(len(measured) - n)])
        a = actions.normalise(q, measured)
        assert np.all(np.abs(a[:n]) < 1)
        assert np.allclose(actions.command(a, measured)[:n], q[:n], atol=5e-4)
        assert np.allclose(actions.normalise(measured, measured)[:n], 0.0, atol=1e-9)
        assert np.allclose(actions.command(np.zeros(len(q)), measured)[:n], measured[:n], atol=1e-4)
    measured = allegro_z1.pregrasp_vector()
    centre, R = actions.ik.palm_pose(measured[:n])
    a = np.zeros(len(measured))
    a[:3], a[5] = [0.4, -0.6, 0.2], 0.8
    moved, turned = actions.ik.palm_pose(actions.command(a, measured)[:n])
    assert np.allclose(moved, centre + a[:3] * box.step, atol=1e-4)
    angle = np.arccos(np.clip((np.trace(R.T @ turned) - 1) / 2, -1, 1))
    assert angle == pytest.approx(0.8 * box.step_rotation, abs=1e-3)
    with pytest.raises(ValueError, match="q_measured"):
        actions.normalise(measured)


def test_palm_step_needs_a_step_in_the_description(allegro_z1):
    no_step = replace(allegro_z1, palm_pose_action=replace(allegro_z1.palm_pose_action, step=0.0, step_rotation=0.0))
    with pytest.raises(DexdrakeError, match="palm_step"):
        ActionMap(no_step, "palm_step")
    with pytest.raises(DexdrakeError, match="step"):
        _palm_pose_action({"name": "h", "palm_pose_action": {"lower": [0, 0, 0], "upper": [1, 1, 1], "rotation": 1,
                                                             "step": 0.05}})
