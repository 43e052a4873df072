"""The Adroit-style hand models: parsing, limits, kinematics vs the spec, PD servo, filters,
hand descriptions. Spec numbers are re-transcribed here from specs/adroit.md so the checks
are independent of scripts/build_adroit_model.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pydrake.geometry import Box
from pydrake.math import RigidTransform
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import (
    AddMultibodyPlant,
    CoulombFriction,
    MultibodyPlant,
    MultibodyPlantConfig,
)
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import ExternallyAppliedSpatialForce
from pydrake.multibody.tree import JointActuatorIndex, SpatialInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from dexdrake.hands.description import load_hand
from dexdrake.paths import models_dir

REPO = Path(__file__).resolve().parents[1]
MODELS = {"adroit": 30, "adroit_4f": 25, "adroit_3f": 21, "adroit_2f": 17}
FINGERS = {
    "adroit": "ff mf rf lf th",
    "adroit_4f": "ff mf rf th",
    "adroit_3f": "ff mf th",
    "adroit_2f": "ff th",
}

# --- spec tables (specs/adroit.md) --------------------------------------------------------
SPEC_LIMITS = {
    "ARTx": (-0.25, 0.25), "ARTy": (0.0, 0.2), "ARTz": (-0.3, 0.5),
    "ARRx": (-0.75, 0.75), "ARRy": (-0.75, 0.75), "ARRz": (-0.75, 0.75),
    "WRJ1": (-0.524, 0.175), "WRJ0": (-0.785, 0.611),
    "LFJ4": (0.0, 0.698),
    "THJ4": (-1.047, 1.047), "THJ3": (0.0, 1.309), "THJ2": (-0.262, 0.262),
    "THJ1": (-0.524, 0.524), "THJ0": (-1.571, 0.0),
}
for _f in "FF MF RF LF".split():
    SPEC_LIMITS[f"{_f}J3"] = (-0.436, 0.436)
    for _i in range(3):
        SPEC_LIMITS[f"{_f}J{_i}"] = (0.0, 1.571)

X, Y, Z = np.eye(3)
KNUCKLES = {"ff": (0.033, 0, 0.095), "mf": (0.011, 0, 0.099), "rf": (-0.011, 0, 0.095)}


def rot(axis, angle: float) -> np.ndarray:
    """Rodrigues rotation matrix about a (normalised) axis."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def quat(w, x, y, z) -> np.ndarray:
    w, x, y, z = np.array([w, x, y, z]) / np.linalg.norm([w, x, y, z])
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


class Pose:
    """A (R, p) pair composed child-after-parent, numpy only."""

    def __init__(self, R=np.eye(3), p=(0, 0, 0)):
        self.R, self.p = np.asarray(R, float), np.asarray(p, float)

    def then(self, p=(0, 0, 0), R=np.eye(3)) -> Pose:
        return Pose(self.R @ R, self.p + self.R @ np.asarray(p, float))

    def point(self, p) -> np.ndarray:
        return self.p + self.R @ np.asarray(p, float)


def spec_sites(q: dict[str, float], fingers: str = "ff mf rf lf th") -> dict[str, np.ndarray]:
    """World positions of the S_* sites from the spec's body offsets and joint axes."""
    g = q.get
    fore = Pose(quat(0.0006, -0.0006, 0.7068, 0.7074), (0, -0.7, 0.2))
    fore = Pose(fore.R, fore.point((g("ARTx", 0), g("ARTy", 0), g("ARTz", 0))))
    fore = fore.then(R=rot(X, g("ARRx", 0)) @ rot(Y, g("ARRy", 0)) @ rot(Z, g("ARRz", 0)))
    wrist = fore.then((0, 0, 0.396), rot(Y, g("WRJ1", 0)))
    palm = wrist.then((0, 0, 0.034), rot(X, g("WRJ0", 0)))
    sites = {"S_grasp": palm.point((0.007, -0.05, 0.07))}

    def digit(base: Pose, f: str) -> np.ndarray:
        F = f.upper()
        prox = base.then(R=rot(Y, g(f"{F}J3", 0)) @ rot(X, g(f"{F}J2", 0)))
        mid = prox.then((0, 0, 0.045), rot(X, g(f"{F}J1", 0)))
        dist = mid.then((0, 0, 0.025), rot(X, g(f"{F}J0", 0)))
        return dist.point((0, 0, 0.026))

    for f in fingers.split():
        if f in KNUCKLES:
            sites[f"S_{f}tip"] = digit(palm.then(KNUCKLES[f]), f)
        elif f == "lf":
            meta = palm.then((-0.017, 0, 0.044), rot((0.571, 0, 0.821), g("LFJ4", 0)))
            sites["S_lftip"] = digit(meta.then((-0.017, 0, 0.044)), f)
        else:
            base = palm.then((0.034, -0.009, 0.029), quat(0.924, 0, 0.3825, 0))
            prox = base.then(R=rot(-Z, g("THJ4", 0)) @ rot(X, g("THJ3", 0)))
            mid = prox.then((0, 0, 0.038), rot(X, g("THJ2", 0)) @ rot(Y, g("THJ1", 0)))
            dist = mid.then((0, 0, 0.032), rot(Y, g("THJ0", 0)))
            sites["S_thtip"] = dist.point((0, 0, 0.0275))
    return sites


FLEXED = {j: hi for j, (lo, hi) in SPEC_LIMITS.items() if j[:2] in ("FF", "MF", "RF", "LF")}
FLEXED.update({"THJ4": 1.047, "THJ3": 1.309, "THJ0": -1.571})
ARM_WRIST_POSE = {
    "ARTx": 0.1, "ARTy": 0.15, "ARTz": -0.2, "ARRx": 0.3, "ARRy": -0.4, "ARRz": 0.5,
    "WRJ1": -0.3, "WRJ0": 0.4, "FFJ3": 0.2, "FFJ2": 0.5, "MFJ1": 0.7, "RFJ3": -0.3,
    "LFJ4": 0.5, "LFJ3": 0.1, "LFJ0": 0.9, "THJ4": -0.6, "THJ3": 0.8, "THJ2": 0.2,
    "THJ1": -0.4, "THJ0": -0.5,
}


def model_path(name: str) -> str:
    return str(models_dir() / "adroit" / f"{name}.sdf")


def plant_for(name: str) -> MultibodyPlant:
    plant = MultibodyPlant(0.0)
    Parser(plant).AddModels(model_path(name))
    plant.Finalize()
    return plant


def set_q(plant: MultibodyPlant, context, q: dict[str, float]) -> None:
    for j, v in q.items():
        if plant.HasJointNamed(j):
            joint = plant.GetJointByName(j)
            (joint.set_translation if j.startswith("ART") else joint.set_angle)(context, v)


# --- tests --------------------------------------------------------------------------------
@pytest.mark.parametrize("name", MODELS)
def test_model_parses_with_expected_dofs_and_actuators(name):
    plant = plant_for(name)
    n = MODELS[name]
    assert plant.num_positions() == n and plant.num_velocities() == n
    assert plant.num_actuators() == n
    actuated = [plant.get_joint_actuator(JointActuatorIndex(i)).joint().name() for i in range(n)]
    assert actuated == list(load_hand(name).policy_joints)
    for i in range(n):
        act = plant.get_joint_actuator(JointActuatorIndex(i))
        assert act.has_controller() and act.get_controller_gains().p > 0
        assert 0 < act.effort_limit() < np.inf
        assert act.default_reflected_inertia() > 0


@pytest.mark.parametrize("name", MODELS)
def test_joint_limits_equal_spec(name):
    plant = plant_for(name)
    joints = load_hand(name).policy_joints
    assert set(joints) <= set(SPEC_LIMITS)
    for j in joints:
        joint = plant.GetJointByName(j)
        assert (joint.position_lower_limits()[0], joint.position_upper_limits()[0]) == \
            pytest.approx(SPEC_LIMITS[j], abs=1e-12), j
    lo, hi = load_hand(name).joint_limits()
    assert np.allclose(lo, [SPEC_LIMITS[j][0] for j in joints])
    assert np.allclose(hi, [SPEC_LIMITS[j][1] for j in joints])


@pytest.mark.parametrize("name", MODELS)
@pytest.mark.parametrize("config", [{}, FLEXED, ARM_WRIST_POSE], ids=["zero", "flexed", "pose"])
def test_fingertip_kinematics_match_spec(name, config):
    plant = plant_for(name)
    context = plant.CreateDefaultContext()
    set_q(plant, context, config)
    expected = spec_sites(config, FINGERS[name])
    assert len(expected) == len(FINGERS[name].split()) + 1
    for site, p in expected.items():
        got = plant.GetFrameByName(site).CalcPoseInWorld(context).translation()
        np.testing.assert_allclose(got, p, atol=1e-9, err_msg=site)


def test_zero_pose_palm_faces_down_and_fingers_point_along_y():
    plant = plant_for("adroit")
    context = plant.CreateDefaultContext()
    palm = plant.GetBodyByName("palm").EvalPoseInWorld(context)
    assert palm.rotation().multiply(np.array([0, -1, 0]))[2] < -0.99
    assert palm.rotation().multiply(np.array([0, 0, 1]))[1] > 0.99


def simulate_step(name: str, dt: float, q_d: dict[str, float], duration: float):
    """Simulate the PD-servoed robot (SAP, gravity off on it) toward q_d; return (q, v)."""
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(
        MultibodyPlantConfig(time_step=dt, discrete_contact_approximation="sap"), builder)
    (instance,) = Parser(plant).AddModels(model_path(name))
    plant.set_gravity_enabled(instance, False)
    plant.Finalize()
    joints = load_hand(name).policy_joints
    desired = np.zeros(2 * len(joints))
    for j, v in q_d.items():
        desired[joints.index(j)] = v
    source = builder.AddSystem(ConstantVectorSource(desired))
    builder.Connect(source.get_output_port(), plant.get_desired_state_input_port(instance))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.AdvanceTo(duration)
    ctx = plant.GetMyContextFromRoot(simulator.get_context())
    q = np.array([plant.GetJointByName(j).GetOnePosition(ctx) for j in joints])
    v = np.array([plant.GetJointByName(j).GetOneVelocity(ctx) for j in joints])
    return q, v, desired[: len(joints)]


@pytest.mark.parametrize("dt", [0.002, 0.001])
def test_pd_servo_tracks_finger_and_arm_steps(dt):
    step = {"FFJ2": 1.0, "THJ3": 0.8, "WRJ0": 0.3, "ARTz": 0.2, "ARRx": 0.4, "ARTx": -0.1}
    q, v, q_d = simulate_step("adroit", dt, step, duration=0.6)
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(v))
    np.testing.assert_allclose(q, q_d, atol=5e-3)
    assert np.abs(v).max() < 0.05


GRASP_CLOSE = {
    **{f"{f}J{i}": v for f in ("FF", "MF", "RF", "LF") for i, v in ((2, 1.0), (1, 1.0), (0, 0.8))},
    "THJ4": 0.6, "THJ3": 1.2, "THJ0": -0.3,
}


def test_fingers_hold_half_kilogram_box_with_friction_one():
    """Close the hand round a 5 cm, 0.5 kg box under the palm (palm facing down), holding
    the box up with an external force while the fingers close, then let gravity act."""
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(
        MultibodyPlantConfig(time_step=0.002, discrete_contact_approximation="sap"), builder)
    (instance,) = Parser(plant).AddModels(model_path("adroit"))
    plant.set_gravity_enabled(instance, False)
    mass, edge = 0.5, 0.05
    box = plant.AddRigidBody("box", plant.AddModelInstance("box"),
                             SpatialInertia.SolidBoxWithMass(mass, edge, edge, edge))
    plant.RegisterCollisionGeometry(box, RigidTransform(), Box(edge, edge, edge), "box",
                                    CoulombFriction(1.0, 1.0))
    plant.Finalize()
    joints = load_hand("adroit").policy_joints
    desired = np.zeros(2 * len(joints))
    for j, v in GRASP_CLOSE.items():
        desired[joints.index(j)] = v
    source = builder.AddSystem(ConstantVectorSource(desired))
    builder.Connect(source.get_output_port(), plant.get_desired_state_input_port(instance))
    simulator = Simulator(builder.Build())
    ctx = plant.GetMyMutableContextFromRoot(simulator.get_mutable_context())
    X_WP = plant.GetBodyByName("palm").EvalPoseInWorld(ctx)
    plant.SetFreeBodyPose(ctx, box, RigidTransform(X_WP.rotation(),
                                                   X_WP.multiply([0.008, -0.038, 0.075])))
    lift = ExternallyAppliedSpatialForce()
    lift.body_index = box.index()
    lift.F_Bq_W = SpatialForce(np.zeros(3), np.array([0.0, 0.0, mass * 9.81]))
    forces = plant.get_applied_spatial_force_input_port()
    forces.FixValue(ctx, [lift])
    simulator.AdvanceTo(0.4)
    forces.FixValue(ctx, [])
    released = box.EvalPoseInWorld(ctx).translation().copy()
    simulator.AdvanceTo(1.0)
    settled = box.EvalPoseInWorld(ctx).translation().copy()
    simulator.AdvanceTo(1.6)
    final = box.EvalPoseInWorld(ctx).translation()
    assert np.all(np.isfinite(final))
    assert np.linalg.norm(settled - released) < 0.04  # settles into the finger cage
    assert np.linalg.norm(final - settled) < 0.002  # and is then held still
    assert np.linalg.norm(box.EvalSpatialVelocityInWorld(ctx).translational()) < 0.01


def contact_pairs(q: dict[str, float], box_at: np.ndarray | None = None) -> set[tuple]:
    """Names of the geometry pairs in contact for the full hand at q (plus an optional
    10 cm box welded to the world at `box_at`)."""
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(
        MultibodyPlantConfig(time_step=0.002, discrete_contact_approximation="sap"), builder)
    Parser(plant).AddModels(model_path("adroit"))
    if box_at is not None:
        plant.RegisterCollisionGeometry(
            plant.world_body(), RigidTransform(box_at), Box(0.1, 0.1, 0.1), "box",
            CoulombFriction(1.0, 1.0))
    plant.Finalize()
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    set_q(plant, plant.GetMyMutableContextFromRoot(context), q)
    query = scene_graph.get_query_output_port().Eval(scene_graph.GetMyContextFromRoot(context))
    inspector = scene_graph.model_inspector()
    return {tuple(sorted((inspector.GetName(p.id_A), inspector.GetName(p.id_B))))
            for p in query.ComputePointPairPenetration()}


def test_robot_self_collision_filtered_but_objects_collide():
    assert contact_pairs({}) == set()
    assert contact_pairs(FLEXED) == set()
    plant = plant_for("adroit")
    grasp = plant.GetFrameByName("S_grasp").CalcPoseInWorld(plant.CreateDefaultContext())
    pairs = contact_pairs({}, box_at=grasp.translation())
    assert any("palm" in a + b for a, b in pairs), pairs


@pytest.mark.parametrize("name", MODELS)
def test_hand_description_matches_model(name):
    hand = load_hand(name)
    plant = plant_for(name)
    context = plant.CreateDefaultContext()
    assert hand.model_path.is_file()
    assert hand.arm_joints == hand.policy_joints[:6]
    assert hand.hardware_joints is None
    for body in {hand.wrist_body, hand.palm.body, hand.occupancy.body}:
        assert plant.HasBodyNamed(body)
    assert hand.palm.normal == (0, -1, 0)
    grasp = plant.GetFrameByName("S_grasp").CalcPose(context, plant.GetFrameByName("palm"))
    np.testing.assert_allclose(grasp.translation(), hand.palm.centre, atol=1e-12)
    n_fingers = len(FINGERS[name].split())
    assert [t.name for t in hand.fingertips][-1] == "thtip"
    assert len(hand.fingertips) == n_fingers
    for tip in hand.fingertips:
        site = plant.GetFrameByName(f"S_{tip.name}")
        assert site.body().name() == tip.body
        np.testing.assert_allclose(
            site.GetFixedPoseInBodyFrame().translation(), tip.offset, atol=1e-12)
    expected_points = {"adroit": 22, "adroit_4f": 17, "adroit_3f": 13, "adroit_2f": 9}[name]
    assert len(hand.dexrep_points) == expected_points
    assert len({p.name for p in hand.dexrep_points}) == expected_points
    for p in hand.dexrep_points:
        assert plant.HasBodyNamed(p.body), p.body
    lo, hi = hand.joint_limits()
    pre = hand.pregrasp_vector()
    assert np.all(pre >= lo) and np.all(pre <= hi)
    assert set(hand.pregrasp) <= set(hand.policy_joints)


def test_occupancy_grid_sits_in_front_of_palm_for_every_variant():
    centres = []
    for name in MODELS:
        hand = load_hand(name)
        plant = plant_for(name)
        ctx = plant.CreateDefaultContext()
        palm = plant.GetBodyByName("palm").body_frame()
        anchor = plant.GetBodyByName(hand.occupancy.body).body_frame()
        centre = anchor.CalcPose(ctx, palm).multiply(np.array(hand.occupancy.offset))
        centres.append(centre)
        half = hand.occupancy.size / 2
        assert np.all(np.abs(np.array(hand.palm.centre) - centre) < half)  # grasp centre inside
        assert centre[1] < -0.05  # on the palm side (palm normal is -y)
    np.testing.assert_allclose(centres, [centres[0]] * len(centres), atol=1e-12)


def test_pregrasp_thumb_opposes_fingers():
    hand = load_hand("adroit")
    plant = plant_for("adroit")
    ctx = plant.CreateDefaultContext()
    set_q(plant, ctx, dict(zip(hand.policy_joints, hand.pregrasp_vector())))
    palm = plant.GetBodyByName("palm").body_frame()
    th = plant.GetFrameByName("S_thtip").CalcPose(ctx, palm).translation()
    ff = plant.GetFrameByName("S_fftip").CalcPose(ctx, palm).translation()
    assert th[1] < -0.04  # thumb tip in front of the palm
    assert ff[1] < -0.01  # index slightly flexed toward the palm side
    assert np.linalg.norm(th - ff) < 0.12


def test_committed_models_match_generator(load_script):
    gen = load_script("build_adroit_model")
    for name, fingers in gen.VARIANTS.items():
        assert gen.build_sdf(name, fingers) == (REPO / f"models/adroit/{name}.sdf").read_text()
        assert gen.build_hand_yaml(name, fingers) == \
            (REPO / f"models/adroit/{name}.hand.yaml").read_text()
    with pytest.raises(ValueError, match="unknown fingers"):
        gen.bodies_for(("ff", "xx"))
