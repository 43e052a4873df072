"""Allegro v4, Z1, Allegro-on-Z1 and Allegro-on-virtual-arm models, their hand descriptions
and the Allegro bus units, checked against tables transcribed here from the specs
(specs/allegro_v4.md, specs/z1.md) with forward kinematics computed in numpy, not Drake."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from pydrake.geometry import (
    AddContactMaterial,
    Box,
    ProximityProperties,
    SceneGraph,
)
from pydrake.math import RigidTransform
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import (
    AddMultibodyPlantSceneGraph,
    CoulombFriction,
    DiscreteContactApproximation,
    MultibodyPlant,
)
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from dexdrake.errors import DexdrakeError
from dexdrake.hands import allegro_units as au
from dexdrake.hands.description import _read, load_hand
from dexdrake.paths import models_dir

# ------------------------------------------------------------------ spec tables
# specs/allegro_v4.md: joint -> (parent, xyz, rpy, axis, lower, upper)
X, Y, Z = (1, 0, 0), (0, 1, 0), (0, 0, 1)
HAND = {}
for f, (xyz, rpy) in enumerate([((0, 0.0435, -0.001542), (-0.0872665, 0, 0)),
                                 ((0, 0, 0.0007), (0, 0, 0)),
                                 ((0, -0.0435, -0.001542), (0.0872665, 0, 0))]):
    k = 4 * f
    HAND[f"joint_{k}.0"] = ("palm_link", xyz, rpy, Z, -0.47, 0.47)
    HAND[f"joint_{k + 1}.0"] = (f"link_{k}.0", (0, 0, 0.0164), (0, 0, 0), Y, -0.196, 1.61)
    HAND[f"joint_{k + 2}.0"] = (f"link_{k + 1}.0", (0, 0, 0.054), (0, 0, 0), Y, -0.174, 1.709)
    HAND[f"joint_{k + 3}.0"] = (f"link_{k + 2}.0", (0, 0, 0.0384), (0, 0, 0), Y, -0.227, 1.618)
HAND["joint_12.0"] = ("palm_link", (-0.0182, 0.019333, -0.045987), (0, -1.65806, -1.5708),
                      (-1, 0, 0), 0.263, 1.396)
HAND["joint_13.0"] = ("link_12.0", (-0.027, 0.005, 0.0399), (0, 0, 0), Z, -0.105, 1.163)
HAND["joint_14.0"] = ("link_13.0", (0, 0, 0.0177), (0, 0, 0), Y, -0.189, 1.644)
HAND["joint_15.0"] = ("link_14.0", (0, 0, 0.0514), (0, 0, 0), Y, -0.162, 1.719)
TIPS = {3: 0.0267, 7: 0.0267, 11: 0.0267, 15: 0.0423}

# specs/z1.md: joint -> (xyz, axis, lower, upper, effort)
Z1 = {
    "joint1": ((0, 0, 0.0585), Z, -2.6180, 2.6180, 30),
    "joint2": ((0, 0, 0.045), Y, 0, 2.9671, 60),
    "joint3": ((-0.35, 0, 0), Y, -2.8798, 0, 30),
    "joint4": ((0.218, 0, 0.057), Y, -1.5184, 1.5184, 30),
    "joint5": ((0.07, 0, 0), Z, -1.3439, 1.3439, 30),
    "joint6": ((0.0492, 0, 0), X, -2.7925, 2.7925, 30),
}
Z1_BASE = np.array([-0.45, 0, 0])
# Documented mount (scripts/build_allegro_models.py): palm_link in link06.
MOUNT_XYZ, MOUNT_RPY = np.array([0.051 + 0.095, 0, 0]), (0, math.pi / 2, 0)
GRASP_CENTRE = np.array([0.055, 0, -0.03])

MODELS = {  # file -> (revolute+prismatic joints, actuators)
    "allegro/allegro_right.urdf": (16, 16),
    "z1/z1.urdf": (6, 6),
    "allegro/allegro_z1.urdf": (22, 22),
    "allegro/allegro_arm.urdf": (22, 22),
}


# ------------------------------------------------------------------ numpy kinematics
def rot_axis(axis, angle: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def rpy(r: float, p: float, y: float) -> np.ndarray:
    """URDF convention: R = Rz(y) Ry(p) Rx(r)."""
    return rot_axis(Z, y) @ rot_axis(Y, p) @ rot_axis(X, r)


def tf(R: np.ndarray, p) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def hand_fk(q: dict[str, float]) -> dict[str, np.ndarray]:
    """Poses of every hand link (and tip) in palm_link from the spec table."""
    poses = {"palm_link": np.eye(4)}
    for name, (parent, xyz, r, axis, _, _) in HAND.items():
        child = "link_" + name.removeprefix("joint_")
        poses[child] = poses[parent] @ tf(rpy(*r), xyz) @ tf(rot_axis(axis, q.get(name, 0)), 0)
    for k, dz in TIPS.items():
        poses[f"link_{k}.0_tip"] = poses[f"link_{k}.0"] @ tf(np.eye(3), (0, 0, dz))
    return poses


def z1_flange(q: dict[str, float]) -> np.ndarray:
    """World pose of link06 from the spec table, base at Z1_BASE."""
    T = tf(np.eye(3), Z1_BASE)
    for name, (xyz, axis, *_) in Z1.items():
        T = T @ tf(np.eye(3), xyz) @ tf(rot_axis(axis, q.get(name, 0)), 0)
    return T


# ------------------------------------------------------------------ Drake helpers
_SCENE_GRAPHS = []  # keep each plant's SceneGraph alive as long as the plant


def load(rel: str):
    """A finalised continuous plant (with geometry registered) holding model `rel`."""
    plant, scene_graph = MultibodyPlant(0.0), SceneGraph()
    _SCENE_GRAPHS.append(scene_graph)
    plant.RegisterAsSourceForSceneGraph(scene_graph)
    (instance,) = Parser(plant).AddModels(str(models_dir() / rel))
    plant.Finalize()
    return plant, instance


def set_joints(plant, context, q: dict[str, float]) -> None:
    positions = plant.GetPositions(context)
    for name, value in q.items():
        positions[plant.GetJointByName(name).position_start()] = value
    plant.SetPositions(context, positions)


FLEXED = {f"joint_{k}.0": v for k, v in zip(range(16), 3 * [0.3, 1.2, 1.0, 0.8]
                                             + [1.3, 0.6, 0.7, 0.9])}
FLEXED.update({"joint_0.0": -0.2, "joint_8.0": 0.25})
Z1_POSE = {"joint1": 0.4, "joint2": 1.2, "joint3": -1.1, "joint4": 0.3, "joint5": -0.5,
           "joint6": 0.9}


# ------------------------------------------------------------------ models
@pytest.mark.parametrize("rel", sorted(MODELS))
def test_model_parses_with_expected_dofs_and_actuators(rel):
    plant, instance = load(rel)
    dofs = [plant.get_joint(j) for j in plant.GetJointIndices(instance)
            if plant.get_joint(j).num_velocities() == 1]
    assert (len(dofs), plant.num_actuators(instance)) == MODELS[rel]
    for a in plant.GetJointActuatorIndices(instance):
        gains = plant.get_joint_actuator(a).get_controller_gains()
        assert gains.p > 0 and gains.d > 0


def test_models_are_regenerated_identically(tmp_path, load_script):
    """The committed model files are exactly what the generator writes."""
    module = load_script("build_allegro_models")
    for written in module.write_models(tmp_path):
        rel = written.relative_to(tmp_path)
        assert written.read_text() == (models_dir() / rel).read_text(), rel


@pytest.mark.parametrize("rel", ["allegro/allegro_right.urdf", "allegro/allegro_z1.urdf",
                                 "allegro/allegro_arm.urdf"])
def test_hand_joint_limits_match_spec_and_the_drive_the_drivers_give(rel):
    """Joint limits as the spec; each finger actuator's effort is its driver PWM limit in N*m
    and its reflected inertia and damping are the HIL emulator's (a hand no stronger or
    lighter in simulation than in HIL)."""
    from dexdrake.hardware.allegro_emulator import EmulatorConfig

    plant, _ = load(rel)
    context = plant.CreateDefaultContext()
    inertia = au.NM_PER_PWM / EmulatorConfig.accel_per_pwm
    for name, (*_, lo, hi) in HAND.items():
        joint = plant.GetJointByName(name)
        assert joint.position_lower_limits()[0] == lo and joint.position_upper_limits()[0] == hi
        np.testing.assert_array_equal(joint.velocity_upper_limits(), [7.0])
        actuator = plant.GetJointActuatorByName(f"{name}_act")
        bus = int(name.split("_")[1].split(".")[0])
        assert actuator.effort_limit() == pytest.approx(au.PWM_LIMITS[bus] * au.NM_PER_PWM)
        assert actuator.calc_reflected_inertia(context) == pytest.approx(inertia)
        assert joint.default_damping() == pytest.approx(inertia * EmulatorConfig.damping)


@pytest.mark.parametrize("rel", ["z1/z1.urdf", "allegro/allegro_z1.urdf"])
def test_z1_joint_limits_match_spec(rel):
    plant, _ = load(rel)
    for name, (_, _, lo, hi, effort) in Z1.items():
        joint = plant.GetJointByName(name)
        assert joint.position_lower_limits()[0] == lo and joint.position_upper_limits()[0] == hi
        np.testing.assert_allclose(joint.velocity_upper_limits(), [math.pi])
        assert plant.GetJointActuatorByName(f"{name}_act").effort_limit() == effort


@pytest.mark.parametrize("q", [{}, FLEXED], ids=["zeros", "flexed"])
def test_hand_forward_kinematics_matches_spec(q):
    plant, _ = load("allegro/allegro_right.urdf")
    context = plant.CreateDefaultContext()
    set_joints(plant, context, q)
    expected = hand_fk(q)
    palm = plant.GetFrameByName("palm_link")
    for link, T in expected.items():
        X = plant.CalcRelativeTransform(context, palm, plant.GetFrameByName(link))
        np.testing.assert_allclose(X.GetAsMatrix4(), T, atol=1e-9, err_msg=link)
    if not q:  # sanity of the table itself: middle tip straight up the +z axis
        np.testing.assert_allclose(expected["link_7.0_tip"][:3, 3],
                                   [0, 0, 0.0007 + 0.0164 + 0.054 + 0.0384 + 0.0267])


@pytest.mark.parametrize("q", [{}, Z1_POSE], ids=["zeros", "pose"])
def test_z1_flange_forward_kinematics_matches_spec(q):
    plant, _ = load("z1/z1.urdf")
    context = plant.CreateDefaultContext()
    set_joints(plant, context, q)
    X = plant.GetFrameByName("link06").CalcPoseInWorld(context)
    np.testing.assert_allclose(X.GetAsMatrix4(), z1_flange(q), atol=1e-9)
    if not q:  # folded home pose: flange ahead of and above the base
        np.testing.assert_allclose(X.translation(),
                                   Z1_BASE + [-0.35 + 0.218 + 0.07 + 0.0492, 0,
                                              0.0585 + 0.045 + 0.057], atol=1e-12)


def test_allegro_z1_tips_follow_flange_and_mount():
    plant, _ = load("allegro/allegro_z1.urdf")
    context = plant.CreateDefaultContext()
    q = {**Z1_POSE, **FLEXED}
    set_joints(plant, context, q)
    X_WP = z1_flange(q) @ tf(rpy(*MOUNT_RPY), MOUNT_XYZ)
    for link, T in hand_fk(q).items():
        X = plant.GetFrameByName(link).CalcPoseInWorld(context)
        np.testing.assert_allclose(X.GetAsMatrix4(), X_WP @ T, atol=1e-9, err_msg=link)


def test_virtual_arm_pose_and_joints():
    plant, _ = load("allegro/allegro_arm.urdf")
    context = plant.CreateDefaultContext()
    palm = plant.GetFrameByName("palm_link")
    X = palm.CalcPoseInWorld(context)
    # q = 0: palm faces down, fingers along +x, grasp centre 0.25 m above the origin.
    np.testing.assert_allclose(X.rotation().matrix() @ [1, 0, 0], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(X.rotation().matrix() @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(X @ GRASP_CENTRE, [0, 0, 0.25], atol=1e-12)
    set_joints(plant, context, {"ARTx": 0.1, "ARTy": -0.05, "ARTz": -0.2, "ARRy": 0.5})
    X2 = palm.CalcPoseInWorld(context)
    wrist = X.translation() - 0.095 * (X.rotation().matrix() @ [0, 0, 1])
    moved = wrist + [0.1, -0.05, -0.2]
    expected = moved + rot_axis(Y, 0.5) @ (X.translation() - wrist)
    np.testing.assert_allclose(X2.translation(), expected, atol=1e-12)
    assert {plant.get_joint(j).name() for j in plant.GetJointIndices()} >= {
        "ARTx", "ARTy", "ARTz", "ARRx", "ARRy", "ARRz"}


# ------------------------------------------------------------------ hand descriptions
@pytest.mark.parametrize("name,arm", [("allegro", ["ARTx", "ARTy", "ARTz", "ARRx", "ARRy",
                                                   "ARRz"]),
                                      ("allegro_z1", [f"joint{i}" for i in range(1, 7)])])
def test_hand_descriptions_load_and_name_existing_frames(name, arm):
    hand = load_hand(name)
    bus = [f"joint_{k}.0" for k in range(16)]
    assert list(hand.policy_joints) == arm + bus and list(hand.arm_joints) == arm
    assert list(hand.hardware_joints) == bus and len(bus) == au.NUM_JOINTS
    np.testing.assert_array_equal(hand.hardware_permutation(), np.arange(6, 22))
    plant, instance = load(hand.model)
    for body in [hand.wrist_body, hand.palm.body, hand.occupancy.body,
                 *(p.body for p in hand.fingertips), *(p.body for p in hand.dexrep_points)]:
        assert plant.HasBodyNamed(body, instance), body
    assert [p.body for p in hand.fingertips] == [f"link_{k}.0_tip" for k in (3, 7, 11, 15)]
    assert len(hand.dexrep_points) == 20
    assert sorted(p.body for p in hand.dexrep_points) == sorted(
        [f"link_{k}.0" for k in range(16)] + [p.body for p in hand.fingertips])
    np.testing.assert_allclose(np.linalg.norm(hand.palm.normal), 1.0)
    lo, hi = hand.joint_limits()
    np.testing.assert_array_equal(lo[6:], [HAND[j][4] for j in bus])
    np.testing.assert_array_equal(hi[6:], [HAND[j][5] for j in bus])
    # The pre-grasp is inside the limits as written (no clamping needed).
    q = np.array([hand.pregrasp.get(j, 0.0) for j in hand.policy_joints])
    np.testing.assert_array_equal(hand.pregrasp_vector(), q)
    assert hand.pregrasp["joint_12.0"] > 1.2  # thumb rotated to oppose


def test_allegro_descriptions_write_the_hand_once():
    """The hand part lives in one shared file; each description adds only its arm."""
    shared = yaml.safe_load((models_dir() / "allegro" / "allegro_v4_hand.yaml").read_text())
    arms = {"allegro": "ARTz", "allegro_z1": "joint2"}
    for name, arm_joint in arms.items():
        own = yaml.safe_load((models_dir() / "allegro" / f"{name}.hand.yaml").read_text())
        assert own["include"] == "allegro_v4_hand.yaml"
        assert set(own) & set(shared) <= {"pregrasp", "grasp_script", "grasp_expert"}  # only merged entries
        for merged in ("grasp_script", "grasp_expert"):  # each key written once
            assert not set(own.get(merged, {})) & set(shared[merged])
        assert not set(own["pregrasp"]) & set(shared["pregrasp"])
        hand = load_hand(name)
        assert hand.pregrasp == {**shared["pregrasp"], **own["pregrasp"]} and arm_joint in hand.pregrasp
        assert [p.body for p in hand.fingertips] == [p["body"] for p in shared["fingertips"]]


def test_an_included_part_is_laid_under_the_description(tmp_path):
    (tmp_path / "part.yaml").write_text("wrist_body: w\npalm: {body: p, normal: [1, 0, 0]}\n"
                                        "pregrasp: {a: 1, b: 2}\n")
    (tmp_path / "h.hand.yaml").write_text("include: part.yaml\nname: h\npalm: {body: q}\n"
                                          "pregrasp: {b: 3, c: 4}\n")
    assert _read(tmp_path / "h.hand.yaml") == {
        "wrist_body": "w", "name": "h", "palm": {"body": "q", "normal": [1, 0, 0]},
        "pregrasp": {"a": 1, "b": 3, "c": 4}}


@pytest.mark.parametrize("name", ["allegro", "allegro_z1"])
def test_pregrasp_puts_palm_down_above_the_table(name):
    hand = load_hand(name)
    plant, _ = load(hand.model)
    context = plant.CreateDefaultContext()
    set_joints(plant, context, hand.pregrasp)
    X = plant.GetFrameByName(hand.palm.body).CalcPoseInWorld(context)
    np.testing.assert_allclose(X.rotation().matrix() @ hand.palm.normal, [0, 0, -1], atol=0.01)
    np.testing.assert_allclose(X @ np.array(hand.palm.centre), [0, 0, 0.2], atol=0.005)
    thumb = X @ hand_fk(hand.pregrasp)["link_15.0_tip"][:3, 3]
    assert thumb[2] > 0.1  # the opposed thumb stays clear of the table
    if name == "allegro_z1":
        np.testing.assert_allclose(X.GetAsMatrix4(), z1_flange(hand.pregrasp)
                                   @ tf(rpy(*MOUNT_RPY), MOUNT_XYZ), atol=1e-9)


def test_hand_pd_tracks_a_step_at_2ms_with_sap():
    """The hand's PD (Drake gains in the model) is stable and converges at dt = 2 ms."""
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlantSceneGraph(builder, 0.002)
    plant.set_discrete_contact_approximation(DiscreteContactApproximation.kSap)
    (instance,) = Parser(plant).AddModels(str(models_dir() / "allegro/allegro_arm.urdf"))
    plant.mutable_gravity_field().set_gravity_vector([0, 0, 0])
    plant.Finalize()
    hand = load_hand("allegro")
    target = hand.pregrasp_vector() + np.r_[np.zeros(6), 0.3 * (np.arange(16) % 4 != 0)]
    diagram = builder.Build()
    sim = Simulator(diagram)
    context = plant.GetMyMutableContextFromRoot(sim.get_mutable_context())
    plant.get_desired_state_input_port(instance).FixValue(context, np.r_[target, np.zeros(22)])
    plant.get_actuation_input_port(instance).FixValue(context, np.zeros(22))
    sim.AdvanceTo(1.0)
    q = plant.GetPositions(context, instance)
    assert np.all(np.isfinite(q))
    np.testing.assert_allclose(q, target, atol=2e-3)


def test_hand_holds_and_lifts_half_kilo_box_with_friction_one():
    """Closing the hand (model PD gains) on a 0.5 kg, 6 cm box at the grasp centre holds
    it against gravity while the (gravity-compensated) arm lifts it 0.1 m."""
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlantSceneGraph(builder, 0.002)
    plant.set_discrete_contact_approximation(DiscreteContactApproximation.kSap)
    hand = load_hand("allegro")
    (instance,) = Parser(plant).AddModels(str(hand.model_path))
    plant.set_gravity_enabled(instance, False)
    box = plant.AddRigidBody("box", plant.AddModelInstance("object"),
                             SpatialInertia.SolidBoxWithMass(0.5, 0.06, 0.06, 0.06))
    props = ProximityProperties()
    AddContactMaterial(friction=CoulombFriction(1.0, 1.0), properties=props)
    plant.RegisterCollisionGeometry(box, RigidTransform(), Box(0.06, 0.06, 0.06), "box", props)
    plant.Finalize()
    sim = Simulator(builder.Build())
    context = plant.GetMyMutableContextFromRoot(sim.get_mutable_context())
    q = hand.pregrasp_vector()
    plant.SetPositions(context, instance, q)
    X_WP = plant.GetFrameByName(hand.palm.body).CalcPoseInWorld(context)
    start = X_WP @ np.array(hand.palm.centre)
    plant.SetFreeBodyPose(context, box, RigidTransform(start))
    closed = q.copy()
    closed[6:] = [0, 1.0, 1.2, 1.0] * 3 + [1.396, 1.0, 1.2, 1.2]
    desired = plant.get_desired_state_input_port(instance)
    desired.FixValue(context, np.r_[closed, np.zeros(22)])
    plant.get_actuation_input_port(instance).FixValue(context, np.zeros(22))
    sim.AdvanceTo(1.0)
    held = plant.EvalBodyPoseInWorld(context, box).translation()
    assert abs(held[2] - start[2]) < 0.01  # not dropped while closing
    closed[2] += 0.1  # ARTz: lift
    desired.FixValue(context, np.r_[closed, np.zeros(22)])
    sim.AdvanceTo(2.0)
    lifted = plant.EvalBodyPoseInWorld(context, box).translation()
    np.testing.assert_allclose(lifted - held, [0, 0, 0.1], atol=0.005)


# ------------------------------------------------------------------ bus units
def test_position_counts_round_trip_and_spec_frame():
    assert au.RAD_PER_COUNT == pytest.approx(8.876e-5, rel=1e-3)
    q = np.linspace(-1.7, 1.7, 16)
    np.testing.assert_allclose(au.counts_to_rad(au.rad_to_counts(q)), q,
                               atol=au.RAD_PER_COUNT / 2)
    counts = np.array([-566, 0, 1, 32767], dtype=np.int16)
    np.testing.assert_array_equal(au.rad_to_counts(au.counts_to_rad(counts)), counts)
    # `080 [8] CA FD ..`: index j0 = 0xFDCA = -566 counts, -0.05024 rad (the frame itself
    # is decoded by the CAN codec, tests/test_allegro_can.py).
    assert au.counts_to_rad(np.array([-566]))[0] == pytest.approx(-0.05024, abs=5e-6)
    with pytest.raises(DexdrakeError):
        au.rad_to_counts([4.0])


def test_pwm_limits_in_bus_order():
    np.testing.assert_array_equal(au.PWM_LIMITS[:4], [375, 675, 450, 285])
    np.testing.assert_array_equal(au.PWM_LIMITS[12:], [525, 405, 270, 270])


def test_vendor_gains_in_bus_order():
    np.testing.assert_array_equal(au.KP_VENDOR, 3 * [500, 800, 900, 500] + [1000, 700, 600,
                                                                               600])
    np.testing.assert_array_equal(au.KD_VENDOR, 3 * [25, 50, 55, 40] + [50, 50, 50, 40])
    assert au.KP_VENDOR.shape == au.KD_VENDOR.shape == au.PWM_LIMITS.shape == (16,)
