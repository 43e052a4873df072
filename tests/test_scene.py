"""The grasp scene, the env, the scripted grasp, rerun logging and the `sim` CLI."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw

from dexdrake.cli import main as cli_main
from rrd_content import logged_rows
from dexdrake.systems.grasp_env import GraspEnv
from dexdrake.systems.env_factory import training_scenario
from dexdrake.systems.scene import ObjectPlacement, build_grasp_scene
from dexdrake.systems.scripted_grasp import ScriptedGrasp, closed_pose


@pytest.fixture(scope="module")
def sphere_env():
    return GraspEnv(training_scenario("adroit", "sphere_medium"), horizon=150)


def test_scene_ports_and_sizes():
    scene = build_grasp_scene(training_scenario("adroit", "box_cube"))
    d = scene.diagram
    assert d.GetInputPort("command").size() == 30
    assert d.GetOutputPort("hand_state").size() == 60
    assert d.GetOutputPort("object_pose").size() == 7
    assert scene.plant.time_step() == pytest.approx(0.005)


def test_placement_follows_paper_ranges():
    rng = np.random.default_rng(0)
    samples = [ObjectPlacement.sample(rng) for _ in range(500)]
    xs, ys, yaws = (np.array([getattr(s, k) for s in samples]) for k in ("x", "y", "yaw"))
    # Each coordinate stays in its range and spreads over all of it (every tenth of it is hit).
    for values, lo, hi in [(xs, -0.05, 0.05), (ys, -0.05, 0.0), (yaws, -np.pi, np.pi)]:
        assert values.min() >= lo and values.max() <= hi
        counts, _ = np.histogram(values, bins=10, range=(lo, hi))
        assert counts.min() >= 25, counts


def test_reset_places_object_at_rest_on_table(sphere_env):
    env = sphere_env
    env.reset(3)
    p0 = env.object_position()
    assert p0[2] == pytest.approx(env.scene.object_info.rest_height)
    # Holding the pre-grasp pose for a while: object stays put, hand stays at its set-points.
    q0 = env.scene.hand.pregrasp_vector()
    for _ in range(10):
        obs, reward, done, info = env.step_positions(q0)
    assert np.all(np.isfinite(obs))
    assert np.linalg.norm(env.object_position() - p0) < 1e-3
    assert np.abs(env.scene.hand_positions(env.plant_context) - q0).max() < 1e-2
    assert info["terms"].r_g == 0 and not info["success"]


def test_a_seed_places_an_object_alike_whatever_the_envs_objects(sphere_env):
    # `dexdrake demo --object X --seed N` (a one-object env) must replay the evaluation's
    # episode N of X (an env over all objects): the placement may not depend on the count.
    many = GraspEnv(training_scenario("adroit", "sphere_medium"), horizon=150,
                    objects=["box_cube", "sphere_medium", "apple"])
    for seed in (1, 7, 1901):
        sphere_env.reset(seed)
        many.reset(seed, object_name="sphere_medium")
        np.testing.assert_allclose(many.object_pose().GetAsMatrix4(),
                                   sphere_env.object_pose().GetAsMatrix4(), atol=1e-12)


def test_hand_state_port_matches_env_state(sphere_env):
    env = sphere_env
    env.reset(0)
    port = env.diagram.GetOutputPort("hand_state").Eval(env.context)
    np.testing.assert_allclose(port, env.hand_state())
    pose = env.diagram.GetOutputPort("object_pose").Eval(env.context)
    np.testing.assert_allclose(pose[:3], env.object_position())


def test_env_steps_the_one_diagram_and_observes_its_features_port():
    """GraspEnv feeds the built diagram's "command" input and reads its "features" output
    (DexRepSystem on the hand state and object pose), the same values as the extractor on
    the plant's own state."""
    env = GraspEnv(training_scenario("adroit", "sphere_medium"), feature_set="DexRep", horizon=5)
    env.reset(3)
    env.step(np.linspace(-0.3, 0.3, env.action_dim))
    assert env.diagram.GetInputPort("command") is not None and env.built.controller is None
    direct = env.built.dexrep.extractor(env.plant_context, env.scene.object_pose(env.plant_context))
    np.testing.assert_allclose(env.observation(), direct, atol=1e-9)


def test_normalised_actions_map_onto_joint_ranges(sphere_env):
    env = sphere_env
    env.reset(0)
    env.step(np.ones(env.action_dim))
    lo, hi = env.scene.hand.joint_limits()
    np.testing.assert_allclose(env.q_command, hi)
    assert env.command_guard.counts == {"non_finite": 0, "clipped": 0}


def test_bad_actions_hold_or_clip_and_are_counted_in_the_env(sphere_env):
    env = sphere_env
    env.reset(0)
    lo, hi = env.scene.hand.joint_limits()
    a = np.linspace(-0.5, 0.5, env.action_dim)
    env.step(a)
    held = env.q_command.copy()
    bad = a.copy()
    bad[3] = np.nan
    env.step(bad)  # non-finite: the last command is held
    np.testing.assert_array_equal(env.q_command, held)
    env.step(np.full(env.action_dim + 1, 0.1))  # wrong size: held too
    np.testing.assert_array_equal(env.q_command, held)
    big = a.copy()
    big[0], big[-1] = 3.0, -2.0
    env.step(big)  # out of range: clipped to the joint limits
    assert env.q_command[0] == hi[0] and env.q_command[-1] == lo[-1]
    np.testing.assert_allclose(env.q_command[1:-1], (lo + hi)[1:-1] / 2 + a[1:-1] * (hi - lo)[1:-1] / 2)
    assert env.command_guard.counts == {"non_finite": 2, "clipped": 1}
    env.reset(1)
    assert env.command_guard.counts == {"non_finite": 0, "clipped": 0}


def test_fingertip_distances_shrink_when_hand_closes_on_object(sphere_env):
    env = sphere_env
    env.reset(0)
    far = env.fingertip_distances()
    assert np.all(far > 0.1) and np.all(np.isfinite(far))
    plan = ScriptedGrasp(env)  # its grasp pose for the arm, the fingers open then closed
    q_open, q_closed = plan.q_open.copy(), plan.q_closed.copy()
    q_open[: plan.n_arm] = q_closed[: plan.n_arm] = plan.q_grasp
    for _ in range(20):
        env.step_positions(q_open)
    around = env.fingertip_distances()
    for _ in range(20):
        env.step_positions(q_closed)
    closed = env.fingertip_distances()
    assert np.all(around > 0.015) and np.all(around < far)
    assert np.sum(closed < 0.01) >= 3 and closed.sum() < 0.75 * around.sum(), (around, closed)


def test_closed_pose_moves_finger_joints_toward_their_limits():
    from dexdrake.hands.description import load_hand

    hand = load_hand("adroit")
    q_open, q_closed = hand.pregrasp_vector(), closed_pose(hand)
    _, hi = hand.joint_limits()
    i = hand.policy_joints.index("FFJ1")
    assert q_closed[i] == pytest.approx(hi[i])
    arm = slice(0, len(hand.arm_joints))
    np.testing.assert_allclose(q_closed[arm], q_open[arm])


def test_scripted_grasp_lifts_the_sphere(sphere_env):
    summary = sphere_env.rollout(ScriptedGrasp, seed=0)
    assert summary.success, summary
    assert summary.max_lift > 0.1


def _planned_grasp(env, seed: int, yaw: float) -> np.ndarray:
    env.reset(seed)
    pose = env.scene.plant.GetFreeBodyPose(env.plant_context, env.scene.object_body)
    env.scene.plant.SetFreeBodyPose(env.plant_context, env.scene.object_body,
                                    RigidTransform(RollPitchYaw(0, 0, yaw), pose.translation()))
    return ScriptedGrasp(env).q_grasp


def test_round_objects_are_grasped_at_the_start_yaw_whatever_their_own(sphere_env):
    # A sphere's yaw cannot be seen, so the plan must not depend on it; a bar's plan turns with it.
    np.testing.assert_allclose(_planned_grasp(sphere_env, 0, 0.0), _planned_grasp(sphere_env, 0, 0.6), atol=1e-6)
    widths = sphere_env.scene.object_info.footprint_widths()
    assert widths.max() - widths.min() < 0.01
    bar = GraspEnv(training_scenario("adroit", "box_bar"), horizon=5)
    assert np.abs(_planned_grasp(bar, 0, 0.0) - _planned_grasp(bar, 0, 0.6)).max() > 0.1


def test_a_diverged_simulation_ends_the_episode_as_a_failed_fault(tmp_path, sphere_env):
    from pydrake.multibody.math import SpatialVelocity

    from dexdrake.episode import run_episode
    from dexdrake.systems.rerun_logger import RerunLogger
    from rrd_content import text_logs

    env = sphere_env
    rrd = tmp_path / "diverged.rrd"
    logger = RerunLogger(rrd, "sim")
    hooks = logger.hooks(env)

    def diverge() -> None:  # a non-finite object velocity: SceneGraph refuses the next pose
        hooks["on_reset"]()
        env.scene.plant.SetFreeBodySpatialVelocity(env.plant_context, env.scene.object_body,
                                                   SpatialVelocity(np.zeros(3), np.array([np.nan, 0.0, 0.0])))

    result = run_episode(env, lambda obs: np.zeros(env.action_dim), 0, on_reset=diverge, on_step=hooks["on_step"])
    logger.close()
    assert not result.success and result.steps == 1
    assert result.fault.startswith("simulation diverged at step 1 (seed 0): SceneGraph encountered a non-finite")
    assert text_logs(rrd, "/faults/log") == [("CRITICAL", result.fault)]
    env.reset(0)  # the next episode runs normally
    _, reward, done, info = env.step(np.zeros(env.action_dim))
    assert np.isfinite(reward) and "fault" not in info and np.isfinite(env.object_position()).all()


def test_rerun_recording_is_written(tmp_path, sphere_env):
    from dexdrake.systems.rerun_logger import RerunLogger

    path = tmp_path / "ep.rrd"
    env = GraspEnv(training_scenario("adroit", "box_cube"), horizon=5)
    logger = RerunLogger(path, "sim")
    env.rollout(ScriptedGrasp, seed=0, logger=logger)
    logger.close()
    rows = logged_rows(path)
    # The scene once (table and hand static, the object's mesh at the reset), then every
    # step: the object, joints, reward terms, task state.
    assert rows["/world/table"] == 0 and rows["/world/object/mesh"] == 1 and "/world/hand/palm" in rows
    for entity in ("/reward/total", "/reward/r_d", "/task/lift", "/task/success"):
        assert rows[entity] == 5, entity
    assert rows["/world/object"] == 6 and rows["/world/fingertips"] == 6
    joints = [e for e in rows if e.startswith("/joints/") and e.endswith("/q")]
    assert len(joints) == 30 and all(rows[e] == 6 for e in joints)


def test_cli_unknown_names_list_valid_ones(capsys):
    assert cli_main(["sim", "--object", "no_such_thing"]) == 2
    err = capsys.readouterr().err
    assert "unknown object 'no_such_thing'" in err and "sphere_medium" in err
    assert cli_main(["sim", "--hand", "shadow"]) == 2
    assert "adroit" in capsys.readouterr().err


def test_cli_models_check_lists_every_hand(capsys):
    assert cli_main(["models", "check"]) == 0
    out = capsys.readouterr().out
    assert "adroit" in out and "allegro_z1" in out
    assert any(line.split()[0] == "adroit" and line.split()[2] == "30" for line in out.splitlines()[1:])
