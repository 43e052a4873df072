"""The grasp plan shared by the scripted grasp and the state-driven expert, and the cost of
an expert label (a few Jacobian steps, not an IK solve)."""

import numpy as np
import pytest

from dexdrake.systems.grasp_env import GraspEnv
from dexdrake.systems.reactive_grasp import ReactiveGrasp
from dexdrake.systems.scene import SceneConfig
from dexdrake.systems.scripted_grasp import ScriptedGrasp, plan_grasp


@pytest.fixture(scope="module")
def can_env():
    return GraspEnv(SceneConfig(object="can_soda"), horizon=150)


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
    again = plan_grasp(script, info, X_obj, grasp._palm_pose(grasp.q_open[: grasp.n_arm])[1])
    np.testing.assert_array_equal(again.grasp, plan.grasp)  # a function of the object's shape and pose
    np.testing.assert_allclose(grasp._palm_pose(grasp.q_grasp)[0], plan.grasp, atol=1e-3)


def test_lift_label_is_a_few_jacobian_steps_that_match_the_full_ik(can_env):
    can_env.reset(1)
    expert = ReactiveGrasp(can_env)
    q_arm = expert.q_grasp + np.array([0.01, 0.01, 0.02, 0.05, -0.05, 0.03])  # off the plan, tilted
    p = expert._palm_pose(q_arm)[0]
    target = np.array([p[0], p[1], expert.grasp_point[2] + expert.script.lift])
    full = expert.solve_arm(target, expert.R_grasp, q_arm)
    label = expert._straight_up(q_arm)
    np.testing.assert_allclose(expert._palm_pose(label)[0], target, atol=1e-3)  # straight up, to the lift height
    np.testing.assert_allclose(label, full, atol=5e-3)


def test_ik_steps_keep_joints_on_their_limits_and_still_reach(can_env):
    # A grasp low on the table needs ARTy on its lower limit and the palm tilted: a step that
    # ignored the limit would turn the palm back and leave the grasp centre high.
    can_env.reset(0)
    grasp = ScriptedGrasp(can_env)
    low = grasp.plan.grasp - np.array([0.0, 0.0, grasp.plan.grasp[2] - 0.03])
    q_low = grasp.solve_arm(low, grasp.R_grasp, grasp.q_grasp)
    assert q_low[1] == pytest.approx(grasp.lo[1], abs=1e-6)  # ARTy on its lower limit
    shifted = low + np.array([0.01, -0.01, 0.0])
    q = grasp.step_arm(shifted, grasp.R_grasp, q_low, 3)
    assert grasp.lo[1] <= q[1] <= grasp.hi[1]
    np.testing.assert_allclose(grasp._palm_pose(q)[0], shifted, atol=2e-3)
