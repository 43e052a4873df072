"""The grasp plan shared by the scripted grasp and the expert (ReactiveGrasp), the expert's label
as a function of the state, and the cost of its lift label (a few Jacobian steps, not an IK solve)."""

import json

import numpy as np
import pytest
from pydrake.math import RigidTransform, RotationMatrix

from dexdrake.systems.grasp_env import GraspEnv
from dexdrake.systems.reactive_grasp import ReactiveGrasp
from dexdrake.systems.env_factory import training_scenario
from dexdrake.systems.scene import ObjectPlacement
from dexdrake.systems.scripted_grasp import ScriptedGrasp, plan_grasp


@pytest.fixture(scope="module")
def can_env():
    return GraspEnv(training_scenario("adroit", "can_soda"), horizon=150)


def test_plan_is_geometry_only_and_tall_objects_are_grasped_deeper(can_env):
    can_env.reset(0)
    grasp = ScriptedGrasp(can_env)
    plan, script, info = grasp.plan, grasp.script, can_env.scene.object_info
    X_obj = can_env.scene.object_pose(can_env.plant_context)
    top = X_obj.translation()[2] + info.extents[2] / 2
    # the can (12 cm) is tall: its grasp centre is tall_palm_depth below its top, offset along the fingers
    assert plan.grasp[2] == pytest.approx(top - script.tall_palm_depth, abs=1e-9)
    np.testing.assert_allclose(np.linalg.norm((plan.grasp - X_obj.translation())[:2]), abs(script.reach), atol=1e-9)
    assert np.allclose(plan.lift - plan.grasp, [0, 0, script.lift]) and plan.above[2] == pytest.approx(top + script.hover)
    again = plan_grasp(script, info, X_obj, grasp.ik.palm_pose(grasp.q_open[: grasp.n_arm])[1])
    np.testing.assert_array_equal(again.grasp, plan.grasp)  # a function of the object's shape and pose
    np.testing.assert_allclose(grasp.ik.palm_pose(grasp.q_grasp)[0], plan.grasp, atol=1e-3)


def test_lift_label_is_a_few_jacobian_steps_that_match_the_full_ik(can_env):
    can_env.reset(1)
    expert = ReactiveGrasp(can_env)
    assert expert.lift_height == pytest.approx(expert.plan.grasp[2] + expert.script.lift)  # planned at rest
    q_arm = expert.q_grasp + np.array([0.01, 0.01, 0.02, 0.05, -0.05, 0.03])  # off the plan, tilted
    p, R = expert.ik.palm_pose(q_arm)
    target = np.array([p[0], p[1], expert.lift_height])
    full = expert.ik.solve(target, q_arm, R)
    label = expert._lift(q_arm, np.array([0.02, -0.03, 0.1]), True)  # the object over the placement range
    np.testing.assert_allclose(expert.ik.palm_pose(label)[0], target, atol=1e-3)  # straight up, to the lift height
    np.testing.assert_allclose(expert.ik.palm_pose(label)[1], R, atol=1e-2)  # the palm keeps its rotation
    np.testing.assert_allclose(label, full, atol=5e-3)
    # an object carried 3 cm past the range's +x edge and 2 cm past its +y edge is carried back
    outside = np.array([ObjectPlacement.X_RANGE[1] + 0.03, ObjectPlacement.Y_RANGE[1] + 0.02, 0.1])
    label = expert._lift(q_arm, outside, True)
    np.testing.assert_allclose(expert.ik.palm_pose(label)[0], target - [0.03, 0.02, 0.0], atol=1e-3)
    np.testing.assert_allclose(expert.ik.palm_pose(label)[1], R, atol=1e-2)
    # ... but only once it is off the table: until then straight up (a sideways pull would loosen the grasp)
    np.testing.assert_allclose(expert.ik.palm_pose(expert._lift(q_arm, outside, False))[0], target, atol=1e-3)


def test_allegro_z1_expert_reaches_along_a_straight_line_of_the_grasp_centre():
    """On the Z1 the funnel's target is reached by steps of the grasp centre along the straight line
    to it, `approach_step` long, the palm turning at most `approach_turn` toward the plan's rotation
    (a joint-space path bows sideways)."""
    env = GraspEnv(training_scenario("allegro_z1", "box_bar"), horizon=100)
    env.reset(3)
    expert = ReactiveGrasp(env)
    r = expert.rules
    assert r.approach_step > 0
    q_arm = env.hand_state()[: expert.n_arm]
    p, R = expert.ik.palm_pose(q_arm)
    full_turn = RotationMatrix(expert.R_grasp @ R.T).ToAngleAxis().angle()
    assert full_turn > r.approach_turn  # box_bar's palm turns across its short axis
    for point in (expert.above_point, expert.grasp_point, p + [0.0, 0.0, -0.02]):
        label = expert._toward(q_arm, point)
        p_next, R_next = expert.ik.palm_pose(label)
        d = point - p
        np.testing.assert_allclose(p_next, p + d * min(1.0, r.approach_step / np.linalg.norm(d)), atol=2e-3)
        assert RotationMatrix(R_next @ R.T).ToAngleAxis().angle() == pytest.approx(r.approach_turn, abs=0.01)
        assert RotationMatrix(expert.R_grasp @ R_next.T).ToAngleAxis().angle() == pytest.approx(
            full_turn - r.approach_turn, abs=0.01)  # toward the plan's rotation


def test_nearest_start_is_never_farther_from_the_start_than_the_object():
    rng = np.random.default_rng(0)
    for _ in range(200):
        start = ObjectPlacement.sample(rng)
        xy = np.array([start.x, start.y]) + rng.normal(0, 0.08, 2)
        near = ObjectPlacement.nearest_start(xy)
        assert np.linalg.norm(near - [start.x, start.y]) <= np.linalg.norm(xy - [start.x, start.y]) + 1e-12
        assert ObjectPlacement.X_RANGE[0] <= near[0] <= ObjectPlacement.X_RANGE[1]
        assert ObjectPlacement.Y_RANGE[0] <= near[1] <= ObjectPlacement.Y_RANGE[1]


def test_expert_label_is_a_function_of_the_state_not_of_the_episode_past(can_env):
    """Along an expert-driven grasp whose object is pushed before the grasp, an expert made
    afresh at each state (knowing only the object's start height) labels it as the running
    one does: a policy can clone only what the state determines."""
    can_env.reset(2)
    running = ReactiveGrasp(can_env)
    plant, ctx, body = can_env.scene.plant, can_env.plant_context, can_env.scene.object_body
    arm_gaps, phases = [], []
    for step in range(90):
        if step == 8:  # the object pushed 1.5 cm aside and turned while the hand descends
            X = plant.GetFreeBodyPose(ctx, body)
            plant.SetFreeBodyPose(ctx, body, RigidTransform(RotationMatrix.MakeZRotation(0.3) @ X.rotation(),
                                                            X.translation() + [0.015, -0.01, 0.0]))
        label = can_env.normalise(running(can_env))
        fresh = ReactiveGrasp(can_env)
        fresh.p_start = running.p_start
        arm_gaps.append(np.max(np.abs(can_env.normalise(fresh(can_env)) - label)[: running.n_arm]))
        phases.append(running.phase)
        can_env.step(np.clip(label, -1, 1))
    assert {"descend", "close", "lift"} <= set(phases)
    # Measured: 7 of 90 steps (while the fingers close, the squeeze lifts the can a few mm and
    # the running expert's plan, frozen once they closed, lags a fresh one by 0.02-0.04).
    assert np.sum(np.array(arm_gaps) > 0.02) <= 7, np.round(arm_gaps, 3)


def test_fingers_that_started_closing_keep_closing_near_the_grasp_and_open_beyond(can_env):
    can_env.reset(0)
    expert = ReactiveGrasp(can_env)
    r, plant, ctx = expert.rules, can_env.scene.plant, can_env.plant_context
    assert r.above_xy < r.keep_xy
    fingers = expert.q_open + 0.4 * (expert.q_closed - expert.q_open)  # started, past `closed`
    X = plant.GetFreeBodyPose(ctx, can_env.scene.object_body)  # the can out of the fingers' way (not held)
    plant.SetFreeBodyPose(ctx, can_env.scene.object_body, RigidTransform(X.rotation(), X.translation() + [0, 0.4, 0]))
    phases = {}
    for aside in (r.above_xy + 0.005, r.keep_xy - 0.005, r.keep_xy + 0.01):
        target = expert.grasp_point + [aside, 0.0, 0.02]  # within the blocked height above the grasp point
        q = plant.GetPositions(ctx)
        q[can_env.scene.q_index] = np.r_[expert.ik.solve(target, expert.q_grasp, expert.R_grasp), fingers[expert.n_arm:]]
        plant.SetPositions(ctx, q)
        plant.SetVelocities(ctx, np.zeros(plant.num_velocities()))
        label = expert(can_env)
        phases[aside] = expert.phase
        closing = expert.closure(label) == pytest.approx(1.0)
        assert closing == (expert.phase == "close")
    assert list(phases.values()) == ["close", "close", "open"], phases


def test_a_hand_blocked_above_the_grasp_closes_though_its_arm_jitters(can_env):
    # A cloned policy's arm blocked 2 cm above the grasp point jitters at ~0.17 (m/s or rad/s):
    # the label says close there, and descend while the arm still moves fast.
    can_env.reset(0)
    expert = ReactiveGrasp(can_env)
    r, plant, ctx = expert.rules, can_env.scene.plant, can_env.plant_context
    q = plant.GetPositions(ctx)
    q[can_env.scene.q_index] = np.r_[expert.ik.solve(expert.grasp_point + [0.0, 0.0, 0.02], expert.q_grasp, expert.R_grasp),
                                     expert.q_open[expert.n_arm :]]
    plant.SetPositions(ctx, q)
    phases = []
    for speed in (0.1, 2 * r.stopped_speed):
        v = np.zeros(plant.num_velocities())
        v[can_env.scene.v_index[0]] = speed  # ARTx
        plant.SetVelocities(ctx, v)
        expert(can_env)
        phases.append(expert.phase)
    assert phases == ["close", "descend"]


def test_an_object_resting_higher_away_from_the_fingers_is_not_lifted_for_the_allegro():
    # Dropped onto its side a box rests higher than it started; the Allegro's rules count it
    # lifted only near a fingertip, so its expert re-grasps instead of lifting an empty hand
    # and steering it after the object (which ran away from it).
    from dataclasses import replace

    env = GraspEnv(training_scenario("allegro_z1", "box_cube"), horizon=5)
    env.reset(0)
    expert = ReactiveGrasp(env)
    by_height = ReactiveGrasp(env, rules=replace(expert.rules, in_hand=float("inf")))  # the height alone
    plant, ctx = env.scene.plant, env.plant_context
    X = plant.GetFreeBodyPose(ctx, env.scene.object_body)
    plant.SetFreeBodyPose(ctx, env.scene.object_body, RigidTransform(X.rotation(), X.translation() + [0.0, 0.0, 0.02]))
    q = plant.GetPositions(ctx)
    q[env.scene.q_index] = expert.q_open + 0.4 * (expert.q_closed - expert.q_open)  # fingers half closed, in the air
    plant.SetPositions(ctx, q)
    assert env.fingertip_distances().min() > expert.rules.in_hand == 0.03
    expert(env)
    assert expert.phase != "lift"
    by_height(env)
    assert by_height.phase == "lift"


def test_ik_steps_keep_joints_on_their_limits_and_still_reach(can_env):
    # A grasp low on the table needs ARTy on its lower limit and the palm tilted: a step that
    # ignored the limit would turn the palm back and leave the grasp centre high.
    can_env.reset(0)
    grasp = ScriptedGrasp(can_env)
    low = grasp.plan.grasp - np.array([0.0, 0.0, grasp.plan.grasp[2] - 0.03])
    q_low = grasp.ik.solve(low, grasp.q_grasp, grasp.R_grasp)
    assert q_low[1] == pytest.approx(grasp.lo[1], abs=1e-6)  # ARTy on its lower limit
    shifted = low + np.array([0.01, -0.01, 0.0])
    q = grasp.ik.step(shifted, grasp.R_grasp, q_low, 3)
    assert grasp.lo[1] <= q[1] <= grasp.hi[1]
    np.testing.assert_allclose(grasp.ik.palm_pose(q)[0], shifted, atol=2e-3)


def test_ik_jacobian_is_the_residual_derivative_and_solves_reach(can_env):
    can_env.reset(0)
    grasp = ScriptedGrasp(can_env)
    ik, rng = grasp.ik, np.random.default_rng(0)
    for _ in range(5):  # at random arm positions inside the limits, against central differences
        q = rng.uniform(ik.lo, ik.hi) * 0.8 + 0.1 * (ik.lo + ik.hi)
        args = (grasp.plan.grasp, grasp.R_grasp, 0.05, grasp.q_grasp)
        h, eye = 1e-6, np.eye(ik.n_arm)
        numeric = np.stack([(ik.residual(q + h * e, *args) - ik.residual(q - h * e, *args)) / (2 * h) for e in eye], 1)
        np.testing.assert_allclose(ik.residual_jacobian(q, *args), numeric, atol=1e-6)
    q = ik.solve(grasp.plan.grasp, grasp.q_above, grasp.R_grasp)
    np.testing.assert_allclose(ik.palm_pose(q)[0], grasp.plan.grasp, atol=1e-4)


def test_ik_palm_pose_follows_every_change_of_the_arm_positions(can_env):
    """The IK keeps its context's kinematics while the arm positions are unchanged; a new
    position, or a caller's array changed in place, is evaluated afresh."""
    from dexdrake.hands.arm_ik import ArmIK

    can_env.reset(0)
    ik, fresh = ScriptedGrasp(can_env).ik, lambda q: ArmIK(can_env.scene).palm_pose(q)
    rng = np.random.default_rng(1)
    q1, q2 = (rng.uniform(ik.lo, ik.hi) for _ in range(2))
    for q in (q1, q1, q2, q1):
        for a, b in zip(ik.palm_pose(q), fresh(q)):
            np.testing.assert_array_equal(a, b)
    q = q1.copy()
    ik.palm_pose(q2)
    ik.palm_pose(q)
    q[0] = q2[0]  # the caller's array changed in place
    np.testing.assert_array_equal(ik.palm_pose(q)[0], fresh(q)[0])


def test_named_grasp_pose_sets_its_joints_and_leaves_the_closing_rule_to_the_others():
    from dexdrake.errors import DexdrakeError
    from dexdrake.hands.description import load_hand
    from dexdrake.systems.scripted_grasp import closed_pose

    hand = load_hand("adroit")
    plain, oppose = closed_pose(hand, 0.8), closed_pose(hand, 0.8, "oppose")
    named = hand.grasp_poses["oppose"]
    lo, hi = hand.joint_limits()
    for i, joint in enumerate(hand.policy_joints):
        if joint in named:  # clamped into the joint's limits
            assert oppose[i] == pytest.approx(np.clip(named[joint], lo[i], hi[i])) and oppose[i] != pytest.approx(plain[i])
        else:
            assert oppose[i] == plain[i]
    i = hand.policy_joints.index("FFJ2")  # a closing joint goes 80 % of the way to its limit
    assert plain[i] == pytest.approx(hand.pregrasp_vector()[i] + 0.8 * (hi[i] - hand.pregrasp_vector()[i]))
    with pytest.raises(DexdrakeError, match="no grasp pose 'pinch'"):
        closed_pose(hand, 1.0, "pinch")


def test_a_hand_pre_shaped_for_the_grasp_approaches_in_that_pose_and_closes_the_rest(can_env):
    from dataclasses import replace

    from dexdrake.systems.scripted_grasp import script_for

    can_env.reset(0)
    hand = can_env.scene.hand
    expert = ReactiveGrasp(can_env, replace(script_for(hand), closed_pose="oppose", open_pose="oppose"))
    named, pregrasp = hand.grasp_poses["oppose"], hand.pregrasp_vector()
    for i, joint in enumerate(hand.policy_joints):
        if joint in named:  # already in the grasp pose before the descent: no part of the closing
            assert expert.q_open[i] == expert.q_closed[i] != pregrasp[i]
        else:
            assert expert.q_open[i] == pregrasp[i]
    assert expert.closure(expert.q_open) == 0.0 and expert.closure(expert.q_closed) == pytest.approx(1.0)
    label = expert(can_env)  # at the start the hand is told to take the pose while it approaches
    assert expert.phase == "approach"
    np.testing.assert_array_equal(label[expert.n_arm :], expert.q_open[expert.n_arm :])


def test_grasp_pose_naming_an_unknown_joint_is_refused():
    from dexdrake.errors import DexdrakeError
    from dexdrake.hands.description import _grasp_poses

    with pytest.raises(DexdrakeError, match=r"unknown joints \['XXJ9'\]"):
        _grasp_poses({"name": "h", "grasp_poses": {"p": {"XXJ9": 1.0}}}, ("THJ0",))


def test_expert_takes_the_variant_chosen_for_its_object(can_env, tmp_path, monkeypatch):
    import json

    from dexdrake.objects.augment import build_augmented

    from dexdrake.systems import reactive_grasp

    table = {"variants": {"power": {}, "oppose_70": {"closed_pose": "oppose", "closure": 0.7}},
             "objects": {"can_soda": {"variant": "oppose_70"}}}
    (tmp_path / "t.json").write_text(json.dumps(table))
    monkeypatch.setattr(reactive_grasp, "expert_grasps_path", lambda hand: tmp_path / "t.json")
    reactive_grasp._expert_grasps.cache_clear()
    try:
        can_env.reset(0)
        expert = ReactiveGrasp(can_env)
        assert (expert.script.closed_pose, expert.script.closure) == ("oppose", 0.7)
        hand = can_env.scene.hand
        assert reactive_grasp.expert_script(hand, "box_cube") == reactive_grasp.script_for(hand)  # no entry: default
        monkeypatch.setenv("DEXDRAKE_DATA", str(tmp_path / "data"))
        (copy,) = build_augmented(1, 0, ["can_soda"])  # a scaled copy is grasped as the object it copies
        copy_env = GraspEnv(training_scenario("adroit", copy), horizon=5)
        copy_env.reset(0)
        assert (ReactiveGrasp(copy_env).script.closed_pose, ReactiveGrasp(copy_env).script.closure) == ("oppose", 0.7)
    finally:
        reactive_grasp._expert_grasps.cache_clear()


@pytest.mark.parametrize("hand_name", ["adroit", "allegro_z1"])
def test_shipped_expert_grasp_table_covers_every_training_object_with_its_best_variant(hand_name):
    from dexdrake.eval.expert import HANDICAPS, hand_variants
    from dexdrake.hands.description import load_hand
    from dexdrake.objects.library import list_objects
    from dexdrake.systems import reactive_grasp

    reactive_grasp._expert_grasps.cache_clear()
    table = reactive_grasp._expert_grasps(hand_name)
    assert table["command"].startswith("dexdrake expert choose")
    assert not set(table["seeds"]) & set(range(10))  # the expert table's seeds 0..9 stay unseen by the choice
    assert {o.name for o in list_objects("train")} == set(table["objects"])
    hand = load_hand(hand_name)
    assert list(table["variants"]) == hand_variants(hand)
    score = {v: -HANDICAPS.get(v, 0) for v in table["variants"]}
    for name, entry in table["objects"].items():
        counts = entry["successes"]
        assert set(counts) == set(table["variants"])
        assert counts[entry["variant"]] + score[entry["variant"]] == max(counts[v] + score[v] for v in counts)
        reactive_grasp.expert_script(hand, name)  # a valid GraspScript (unknown fields would raise)


def test_variant_choice_stops_trying_a_variant_that_cannot_win_and_chooses_as_trying_all():
    from dexdrake.eval.expert import best_variant

    rng = np.random.default_rng(0)
    variants, seeds = ["a", "b", "c", "d"], [10, 11, 12, 13]
    for _ in range(200):
        table = {(v, s): bool(rng.random() < p) for v, p in zip(variants, rng.random(4)) for s in seeds}
        calls = []
        best, tried = best_variant(variants, seeds, lambda v, s: calls.append((v, s)) or table[v, s])
        counts = {v: sum(table[v, s] for s in seeds) for v in variants}
        assert best == max(variants, key=lambda v: (counts[v], -variants.index(v)))  # as if all were tried
        assert all(tried[v] == [table[v, s] for s in seeds[: len(tried[v])]] for v in variants)
        assert len(calls) == sum(map(len, tried.values()))
    best, tried = best_variant(variants, seeds, lambda v, s: True)  # the default wins on every seed
    assert best == "a" and [len(tried[v]) for v in variants] == [4, 0, 0, 0]
    for _ in range(200):  # with handicaps: the highest successes less handicap, still as if all were tried
        table = {(v, s): bool(rng.random() < p) for v, p in zip(variants, rng.random(4)) for s in seeds}
        handicaps = {v: int(h) for v, h in zip(variants, rng.integers(0, 3, 4))}
        best, tried = best_variant(variants, seeds, lambda v, s: table[v, s], handicaps)
        score = {v: sum(table[v, s] for s in seeds) - handicaps[v] for v in variants}
        assert best == max(variants, key=lambda v: (score[v], -variants.index(v)))
    table = {("a", s): s < 12 for s in seeds} | {("b", s): s < 13 for s in seeds}  # b wins by one: not enough
    assert best_variant(["a", "b"], seeds, lambda v, s: table[v, s], {"b": 1})[0] == "a"
    assert best_variant(["a", "b"], seeds, lambda v, s: table[v, s], {})[0] == "b"


def test_reach_from_the_far_edge_and_across_the_fingers_shift_the_grasp_centre(can_env):
    from dataclasses import replace

    can_env.reset(0)
    grasp = ScriptedGrasp(can_env)
    info, R_start = can_env.scene.object_info, grasp.R_pregrasp
    X_obj = can_env.scene.object_pose(can_env.plant_context)
    base = plan_grasp(grasp.script, info, X_obj, R_start)
    fingers = (base.grasp - X_obj.translation())[:2]  # the default reach is along the fingers
    fingers = np.r_[np.sign(grasp.script.reach) * fingers / np.linalg.norm(fingers), 0.0]
    across = np.cross([0.0, 0.0, 1.0], fingers)
    # the can is round (6.6 cm across): from its far edge the shift counts 3.3 cm farther along the fingers
    edge = plan_grasp(replace(grasp.script, reach_edge=1.0), info, X_obj, R_start)
    np.testing.assert_allclose(edge.grasp - base.grasp, 0.033 * fingers, atol=1e-3)
    side = plan_grasp(replace(grasp.script, side=-0.02), info, X_obj, R_start)
    np.testing.assert_allclose(side.grasp - base.grasp, -0.02 * across, atol=1e-9)
    np.testing.assert_allclose(side.above - side.grasp, base.above - base.grasp, atol=1e-9)


def test_a_grasp_may_hold_only_on_touch_instead_of_the_hands_closure_rule(can_env):
    from dataclasses import replace

    can_env.reset(0)
    expert = ReactiveGrasp(can_env)
    assert expert.closed_hold == expert.rules.closed_hold
    assert ReactiveGrasp(can_env, replace(expert.script, closed_hold=1.1)).closed_hold == 1.1


def test_allegro_pinch_poses_point_the_fingertips_down_and_close_them_toward_the_thumb():
    from dexdrake.hands.description import load_hand
    from dexdrake.systems.scripted_grasp import closed_pose, open_pose

    hand = load_hand("allegro_z1")
    q_open, q_closed = open_pose(hand, "pinch_open"), closed_pose(hand, 1.0, "pinch")
    j = {name: i for i, name in enumerate(hand.policy_joints)}
    for finger in ("joint_1.0", "joint_5.0"):  # index and middle MCP: bent down, then further toward the palm
        assert 0.9 < q_open[j[finger]] < q_closed[j[finger]]
    for ring in ("joint_9.0", "joint_10.0", "joint_11.0"):  # the ring finger stays stretched out of the way
        assert q_open[j[ring]] == q_closed[j[ring]] == 0.0
    assert q_closed[j["joint_14.0"]] > q_open[j["joint_14.0"]]  # the thumb pushes toward the fingertips
    firm = closed_pose(hand, 1.0, "pinch_firm")  # the index and middle PIP and the thumb further closed
    assert all(firm[j[k]] > q_closed[j[k]] for k in ("joint_2.0", "joint_6.0", "joint_14.0"))


@pytest.mark.parametrize("controller", ["expert", "scripted"])
def test_expert_table_writes_the_markdown_and_csv_it_prints(tmp_path, capsys, controller):
    import csv

    from dexdrake.cli import main

    out = tmp_path / "table.md"
    argv = ["expert", "table", "--objects", "sphere_small", "--controller", controller, "--episodes-per-object", "2",
            "--seed", "3", "--horizon", "4", "--workers", "1", "--backend", "sequential", "--out", str(out)]
    assert main(argv) == 0
    text = out.read_text()
    assert text in capsys.readouterr().out
    assert "`dexdrake expert table --hand adroit --objects sphere_small --workers 1 --backend sequential" in text
    assert f"--controller {controller} --episodes-per-object 2 --seed 3 --horizon 4 --out {out}`" in text
    assert "Seeds 3..4 per object" in text and "| sphere_small | sphere | " in text
    rows = list(csv.DictReader(out.with_suffix(".csv").open()))
    assert [(r["kind"], r["name"], r["category"], r["episodes"]) for r in rows] == [
        ("object", "sphere_small", "sphere", "2"), ("category", "", "sphere", "2")]
    assert float(rows[0]["ms_per_call"]) > 0 and rows[0]["successes"] == rows[1]["successes"]


def test_expert_choose_writes_the_grasp_table_and_re_chooses_objects_on_other_seeds(tmp_path, capsys):
    from dexdrake.cli import main
    from dexdrake.eval.expert import hand_variants
    from dexdrake.hands.description import load_hand

    out = tmp_path / "grasps.json"
    base = ["expert", "choose", "--episodes-per-object", "1", "--horizon", "3", "--backend", "sequential",
            "--out", str(out)]
    assert main([*base, "--objects", "sphere_small"]) == 0
    table = json.loads(out.read_text())
    variants = hand_variants(load_hand("adroit"))
    assert (table["hand"], table["seeds"], table["horizon"], list(table["variants"])) == ("adroit", [100], 3, variants)
    assert table["command"].startswith("dexdrake expert choose --hand adroit --objects sphere_small")
    entry = table["objects"]["sphere_small"]
    assert entry["variant"] in variants and set(entry["successes"]) == set(variants)
    assert capsys.readouterr().out.rstrip().endswith(f"wrote {out}")
    assert main([*base, "--objects", "can_soda", "--seed", "9"]) == 2  # the seeds `expert table` reports on
    assert "seeds 9..9 overlap 0..9, the seeds `expert table` reports on" in capsys.readouterr().err
    assert main([*base, "--objects", "can_soda", "--seed", "107"]) == 0  # another seed block than the table's
    again = json.loads(out.read_text())
    assert list(again["objects"]) == ["sphere_small", "can_soda"] and again["command"] == table["command"]
    assert again["seeds"] == [100] and again["objects"]["sphere_small"] == entry
    assert again["objects"]["can_soda"]["seeds"] == [107]
    assert f"--seed 107 --horizon 3 --out {out}" in again["objects"]["can_soda"]["command"]


def test_max_yaw_clips_the_palms_turn_toward_the_short_axis():
    """An elongated object lying across the fingers: the grasp turns the palm a quarter turn,
    or at most `max_yaw` about the vertical."""
    from dataclasses import replace

    from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix

    from dexdrake.objects.library import get_object
    from dexdrake.systems.scripted_grasp import GraspScript

    info = get_object("box_bar")
    R_start = RotationMatrix(RollPitchYaw(np.pi, 0.0, 0.0)).matrix()  # palm down, fingers along world z
    long_axis = 0 if info.extents[0] >= info.extents[1] else 1

    def turn(script, yaw_obj):
        X_obj = RigidTransform(RotationMatrix.MakeZRotation(yaw_obj), [0.0, 0.0, info.rest_height])
        plan = plan_grasp(script, info, X_obj, R_start)
        return RotationMatrix(R_start.T @ plan.R).ToAngleAxis().angle()

    free = [turn(GraspScript(), y + (np.pi / 2 if long_axis else 0.0)) for y in (0.2, 1.3)]
    clipped = [turn(GraspScript(max_yaw=1.0), y + (np.pi / 2 if long_axis else 0.0)) for y in (0.2, 1.3)]
    assert clipped[0] == pytest.approx(free[0], abs=1e-9) and free[0] < 1.0  # within the limit: unchanged
    assert free[1] > 1.0 and clipped[1] == pytest.approx(1.0, abs=1e-9)
    assert turn(replace(GraspScript(), max_yaw=0.0), 1.3) == pytest.approx(0.0, abs=1e-9)


def test_allegro_z1_fingers_pre_close_near_the_grasp_and_the_grasp_stays_put_while_they_close():
    # Its drivers follow finger set-points at 3 rad/s: the label closes the fingers `preclose`
    # already in the last `preclose_height` of the descent, and once the close rule holds the
    # grasp no longer follows an object the palm nudges (`follow_closing`).
    from dataclasses import replace

    env = GraspEnv(training_scenario("allegro_z1", "can_soda"), horizon=5)
    env.reset(0)
    expert = ReactiveGrasp(env)
    r, plant, ctx = expert.rules, env.scene.plant, env.plant_context
    assert not r.follow_closing and 0 < r.preclose < 1 and r.blocked_height < r.preclose_height

    def hand_at(height: float) -> None:
        q = plant.GetPositions(ctx)
        arm = expert.ik.solve(expert.grasp_point + [0.0, 0.0, height], expert.q_grasp, expert.R_grasp)
        q[env.scene.q_index] = np.r_[arm, expert.q_open[expert.n_arm:]]
        plant.SetPositions(ctx, q)
        plant.SetVelocities(ctx, np.zeros(plant.num_velocities()))

    for height, closure in ((r.preclose_height + 0.03, 0.0), (r.preclose_height - 0.02, r.preclose)):
        hand_at(height)
        label = expert(env)
        assert expert.phase == "descend" and expert.closure(label) == pytest.approx(closure, abs=1e-9)
    following = ReactiveGrasp(env, rules=replace(r, follow_closing=True))
    grasp = expert.grasp_point.copy()
    assert np.array_equal(following.grasp_point, grasp)
    hand_at(0.0)  # at the grasp point: close; the can then pushed 1 cm aside
    X = plant.GetFreeBodyPose(ctx, env.scene.object_body)
    plant.SetFreeBodyPose(ctx, env.scene.object_body, RigidTransform(X.rotation(), X.translation() + [0.01, 0.0, 0.0]))
    for controller in (expert, following):
        controller(env)
        assert controller.phase == "close"
    assert np.array_equal(expert.grasp_point, grasp) and np.linalg.norm(following.grasp_point - grasp) > 0.005


def _allegro_lifting_a_touched_box(script: dict | None = None, rules: dict | None = None
                                   ) -> tuple[GraspEnv, ReactiveGrasp, ReactiveGrasp]:
    """The Allegro-on-Z1's env with box_cube raised 5 cm into the open hand, every fingertip on
    it, and two experts planned at rest: the hand's, and one with `script` and `rules` overrides."""
    from dataclasses import replace

    env = GraspEnv(training_scenario("allegro_z1", "box_cube"), horizon=5)
    env.reset(0)
    expert = ReactiveGrasp(env)
    other = ReactiveGrasp(env, replace(expert.script, **(script or {})), replace(expert.rules, **(rules or {})))
    plant, ctx = env.scene.plant, env.plant_context
    X = plant.GetFreeBodyPose(ctx, env.scene.object_body)
    plant.SetFreeBodyPose(ctx, env.scene.object_body, RigidTransform(X.rotation(), X.translation() + [0.0, 0.0, 0.05]))
    q = plant.GetPositions(ctx)
    q[env.scene.q_index] = expert.q_open  # fingers open, the hand above the grasp point
    plant.SetPositions(ctx, q)
    env.fingertip_distances = lambda: np.zeros(len(expert.hand.fingertips))  # every fingertip on the object
    return env, expert, other


def test_allegro_z1_keeps_lifting_a_touched_object_that_spreads_its_fingers_open():
    # A wide object in the hand pushes the fingers back below `started`; lifted and touched by the
    # thumb and a finger, it is still lifted (`lift_touching`), not carried down by the funnel.
    env, expert, by_closure = _allegro_lifting_a_touched_box(rules={"lift_touching": False})
    assert expert.rules.lift_touching and expert.closure(env.hand_state()[: env.action_dim]) < expert.rules.started
    expert(env)
    by_closure(env)
    assert (expert.phase, by_closure.phase) == ("lift", "descend")


def test_a_grasp_variant_may_lift_slower_than_the_hands_rule():
    env, expert, slow = _allegro_lifting_a_touched_box(script={"lift_lead": 0.02})
    q_arm = env.hand_state()[: expert.n_arm]
    leads = []  # the arm set-point's largest lead on a joint (normalised)
    for controller in (expert, slow):
        out = controller(env)
        assert controller.phase == "lift"
        step = env.normalise(out)[: expert.n_arm] - env.normalise(np.r_[q_arm, out[expert.n_arm:]])[: expert.n_arm]
        leads.append(np.abs(step).max())
    assert leads[1] == pytest.approx(0.02, rel=1e-6) and 0.02 < leads[0] <= expert.rules.lift_lead + 1e-9


def test_expert_table_counts_the_episodes_a_fault_ended():
    from dexdrake.episode import EpisodeResult
    from dexdrake.eval.expert import ControllerEpisode, ControllerTable

    trip = "driver fault at step 11 (seed 7): overspeed: joint_15.0 at 11.56 rad/s (the driver trips above 10.50 rad/s)"
    table = ControllerTable(["box_cube"], 0, 2, 100, {"box_cube": "box"})
    table.episodes["box_cube"] = [ControllerEpisode(EpisodeResult("box_cube", 0, True, 0.2, 100, 1.0), 0.1, 100),
                                  ControllerEpisode(EpisodeResult("box_cube", 1, False, 0.0, 11, 0.0, fault=trip), 0.1, 11)]
    text = table.markdown("Expert", [])
    assert "- 1 of 2 episodes ended on a fault, each a failure: 1 driver fault (overspeed)" in text
    assert "| box_cube | box | 1/2 | 50 % |" in text
