"""CasADi forward kinematics and the retargeter."""

import numpy as np
import pytest

from dexdrake.demos.format import DemoMeta, HumanDemo
from dexdrake.hands.description import BodyPoint, HandDescription, OccupancyAnchor, Palm
from dexdrake.retarget.config import HUMAN_BASE, HUMAN_TIP
from dexdrake.errors import DexdrakeError
from dexdrake.retarget.kinematics import extract_tree, fk_function, symbolic_points
from dexdrake.retarget.retargeter import Retargeter

ARM = ["ARTx", "ARTy", "ARTz", "ARRx", "ARRy", "ARRz"]
FINGERS = {"thumb": ("0.02 0.03 0.02", "0.4 0 0.3", "1 0 0"),
           "index": ("0.02 0.0 0.09", "0 0 0", "0 1 0"),
           "middle": ("0.0 -0.02 0.09", "0.1 0 0", "0 1 0")}


def _link(name):
    return (f'<link name="{name}"><inertial><mass value="0.01"/>'
            '<inertia ixx="1e-5" iyy="1e-5" izz="1e-5" ixy="0" ixz="0" iyz="0"/></inertial></link>')


def _joint(name, kind, parent, child, xyz="0 0 0", rpy="0 0 0", axis="1 0 0", lim=(-1, 1)):
    limit = f'<limit lower="{lim[0]}" upper="{lim[1]}" effort="10" velocity="1"/>' \
        if kind != "fixed" else ""
    ax = f'<axis xyz="{axis}"/>' if kind != "fixed" else ""
    return (f'<joint name="{name}" type="{kind}"><parent link="{parent}"/>'
            f'<child link="{child}"/><origin xyz="{xyz}" rpy="{rpy}"/>{ax}{limit}</joint>')


def _toy_urdf() -> str:
    """A 3-finger toy hand on a 6-DoF virtual arm, with tilted origins and odd axes."""
    links, joints = ["arm_base"], [_joint("base_weld", "fixed", "world", "arm_base",
                                          "0.1 -0.2 0.3", "0.1 0.2 0.3")]
    parent = "arm_base"
    for i, n in enumerate(ARM):
        child = f"arm_{n}"
        links.append(child)
        kind = "prismatic" if i < 3 else "revolute"
        joints.append(_joint(n, kind, parent, child, axis=["1 0 0", "0 1 0", "0 0 1"][i % 3],
                             lim=(-0.4, 0.4) if i < 3 else (-2.0, 2.0)))
        parent = child
    links.append("palm")
    joints.append(_joint("mount", "fixed", parent, "palm", "0 0 0.03", "0 0.3 0"))
    for f, (xyz, rpy, ax0) in FINGERS.items():
        prev = "palm"
        for k in range(3):
            child = f"{f}{k}"
            links.append(child)
            joints.append(_joint(f"{f}_j{k}", "revolute", prev, child,
                                 xyz if k == 0 else "0 0 0.04", rpy if k == 0 else "0 0 0",
                                 ax0 if k == 0 else "0.2 1 0.1", (-0.3, 1.5)))
            prev = child
        links.append(f"{f}_tip")
        joints.append(_joint(f"{f}_tipweld", "fixed", prev, f"{f}_tip", "0 0 0.03"))
    return f'<robot name="toy">{"".join(map(_link, links))}{"".join(joints)}</robot>'


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    path = tmp_path_factory.mktemp("toy") / "toy.urdf"
    path.write_text(_toy_urdf())
    joints = tuple(ARM + [f"{f}_j{k}" for f in FINGERS for k in range(3)])
    hand = HandDescription(
        name="toy", model=str(path), policy_joints=joints, arm_joints=tuple(ARM),
        wrist_body="palm", palm=Palm("palm", (1, 0, 0), (0.03, 0, 0.06)),
        fingertips=tuple(BodyPoint(f"{f}tip", f"{f}_tip") for f in FINGERS),
        dexrep_points=(), occupancy=OccupancyAnchor("palm", (0, 0, 0)),
        pregrasp={f"{f}_j1": 0.3 for f in FINGERS})
    config = {"fingers": {f: {"tip": {"fingertip": f"{f}tip"}, "base": {"body": f"{f}1"}}
                          for f in FINGERS},
              "scales": {"wrist": 1.0, "finger": 1.0},
              "pinch": {"eps_enter": 0.0, "eps_leave": 0.0}}
    return hand, config


def _drake_points(hand, q, points):
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    plant = MultibodyPlant(0.0)
    Parser(plant).AddModels(str(hand.model_path))
    plant.Finalize()
    ctx = plant.CreateDefaultContext()
    q_full = plant.GetPositions(ctx)
    for name, v in zip(hand.policy_joints, q):
        q_full[plant.GetJointByName(name).position_start()] = v
    plant.SetPositions(ctx, q_full)
    return np.array([plant.EvalBodyPoseInWorld(ctx, plant.GetBodyByName(b)) @ np.array(o)
                     for b, o in points])


def _random_q(hand, rng, arm_scale=1.0):
    lo, hi = hand.joint_limits()
    q = rng.uniform(lo, hi)
    n = len(hand.arm_joints)
    q[:n] = np.clip(q[:n] * arm_scale, lo[:n], hi[:n])
    return q


def _hands(toy):
    from dexdrake.hands.description import load_hand

    return [toy[0], load_hand("allegro"), load_hand("adroit")]


def test_casadi_fk_matches_drake(toy):
    rng = np.random.default_rng(0)
    for hand in _hands(toy):
        points = [(p.body, p.offset) for p in hand.fingertips] + [(hand.wrist_body, (0, 0, 0))]
        fk = fk_function(hand.model_path, hand.policy_joints, points)
        for _ in range(5):
            q = _random_q(hand, rng)
            np.testing.assert_allclose(np.asarray(fk(q)), _drake_points(hand, q, points),
                                       atol=1e-9, err_msg=hand.name)


def test_fk_holds_joints_outside_the_order_at_their_defaults(toy):
    hand, _ = toy
    held = ("ARTy", "thumb_j1")  # a prismatic and a revolute joint, at their default 0
    order = [j for j in hand.policy_joints if j not in held]
    points = [(p.body, p.offset) for p in hand.fingertips]
    fk = fk_function(hand.model_path, order, points)
    rng = np.random.default_rng(4)
    for _ in range(3):
        q = _random_q(hand, rng)
        q[[hand.policy_joints.index(j) for j in held]] = 0.0
        sub = [v for j, v in zip(hand.policy_joints, q) if j not in held]
        np.testing.assert_allclose(np.asarray(fk(sub)), _drake_points(hand, q, points), atol=1e-9)


def test_fk_refuses_welds_unknown_joints_and_bodies(toy):
    tree = extract_tree(toy[0].model_path)
    palm = [("palm", np.zeros(3))]
    for joint in ("thumb_tipweld", "thumb_j9"):
        with pytest.raises(DexdrakeError, match=rf"joints \['{joint}'\] are not revolute/prismatic joints of the model"):
            symbolic_points(tree, ["ARTx", joint], palm)
    with pytest.raises(DexdrakeError, match="body 'wrist' is not in the model"):
        symbolic_points(tree, ["ARTx"], [("wrist", np.zeros(3))])


def test_extract_tree_refuses_floating_base(tmp_path):
    path = tmp_path / "free.urdf"
    path.write_text(f'<robot name="free">{_link("a")}</robot>')
    with pytest.raises(DexdrakeError, match=r"free.urdf: joint 'a' has unsupported type 'quaternion_floating' "
                                            r"\(supported: revolute, prismatic, weld; anchor floating bases with a weld\)"):
        extract_tree(path)


def _keypoints_from_robot(r: Retargeter, q) -> np.ndarray:
    """21 human keypoints placed exactly on the robot's points at configuration q."""
    kp = np.zeros((21, 3))
    kp[r.human_index] = r.robot_points(q)
    return kp


def test_retarget_recovers_own_fk(toy):
    hand, config = toy
    r = Retargeter(hand, config)
    rng = np.random.default_rng(1)
    for _ in range(5):
        q_true = np.clip(r.reference_q() + rng.normal(0, 0.3, r.num_joints), r.lower, r.upper)
        kp = _keypoints_from_robot(r, q_true)
        q = r.retarget_frame(kp, None, None)
        res = r.residuals(kp, q)
        assert res["all"].max() < 1e-3, res
        np.testing.assert_allclose(r.robot_points(q), r.robot_points(q_true), atol=2e-3)


def test_scales_auto_for_shipped_hands():
    for name in ("allegro", "adroit"):
        r = Retargeter(name)
        assert np.all((r.scales > 0.5) & (r.scales < 2.5)), (name, r.scales)


def test_joint_limits_respected(toy):
    hand, config = toy
    r = Retargeter(hand, config)
    rng = np.random.default_rng(2)
    kp = rng.normal(0, 0.3, (21, 3))  # wildly unreachable keypoints
    q = r.retarget_frame(kp, None, None)
    assert np.all(q >= r.lower - 1e-12) and np.all(q <= r.upper + 1e-12)
    q2 = r.retarget_frame(kp * 2, None, q)
    assert np.all(q2 >= r.lower - 1e-12) and np.all(q2 <= r.upper + 1e-12)
    assert np.any(np.isclose(q2, r.lower) | np.isclose(q2, r.upper))


def _robot_demo(r: Retargeter, n=30):
    q0 = r.reference_q()
    q1 = np.clip(q0 + np.random.default_rng(3).normal(0, 0.4, r.num_joints), r.lower, r.upper)
    qs = q0 + np.linspace(0, 1, n)[:, None] * (q1 - q0)
    kp = np.stack([_keypoints_from_robot(r, q) for q in qs])
    return HumanDemo(kp, np.arange(n) / 30.0, "", np.zeros((n, 3)),
                     np.tile([1.0, 0, 0, 0], (n, 1)), DemoMeta()), qs


def test_warm_start(toy):
    hand, config = toy
    few = dict(config, solver={"iterations": 3, "first_iterations": 200},
               weights={"smooth": 0.0})
    r = Retargeter(hand, few)
    demo, _ = _robot_demo(r)
    Q = r.retarget_sequence(demo, progress=False)
    assert Q.shape == (demo.num_frames, r.num_joints)
    warm = max(r.residuals(demo.keypoints[t], Q[t])["all"].max() for t in range(len(Q)))
    assert warm < 2e-3  # 3 iterations per frame suffice when warm-started
    # a warm start at the solution stays there
    q = r.retarget_frame(demo.keypoints[-1], None, Q[-1])
    np.testing.assert_allclose(q, Q[-1], atol=1e-4)
    # the same 3 iterations from the cold-start guess do much worse on the last frame
    cold = Retargeter(hand, dict(few, solver={"iterations": 3, "first_iterations": 3}))
    qc = cold.retarget_frame(demo.keypoints[-1], None, None)
    assert cold.residuals(demo.keypoints[-1], qc)["all"].max() > 5 * warm


def test_pinch_projection_and_hysteresis(toy):
    hand, config = toy
    r = Retargeter(hand, dict(config, pinch={"eps_enter": 0.03, "eps_leave": 0.05}))
    kp = np.zeros((21, 3))
    kp[0] = [0, 0, 0]
    for f, x in (("thumb", 0.0), ("index", 0.02), ("middle", 0.06)):
        kp[HUMAN_TIP[f]] = [x, 0, 0.15]
        kp[HUMAN_BASE[f]] = [x, 0, 0.08]
    tf = [i for i, k in enumerate(r.kv.kind) if k == "thumb-finger"]  # thumb->index, ->middle
    T, w, _ = r.targets(kp, None)
    assert w[tf[0]] == 200 and np.linalg.norm(T[tf[0]]) == pytest.approx(1e-4)
    assert w[tf[1]] == 1.0
    kp[HUMAN_TIP["index"]][0] = 0.04  # 4 cm: stays projected (leave at 5 cm) ...
    assert r.targets(kp, None)[1][tf[0]] == 200
    kp[HUMAN_TIP["index"]][0] = 0.06  # ... and leaves beyond 5 cm
    assert r.targets(kp, None)[1][tf[0]] == 1.0
    kp[HUMAN_TIP["index"]][0] = 0.04  # from outside, 4 cm does not enter
    assert r.targets(kp, None)[1][tf[0]] == 1.0


def test_retarget_synthetic_demo_with_object():
    import trimesh

    from dexdrake.demos.synthetic import synthesize_demo

    mesh = trimesh.creation.box((0.06, 0.06, 0.12))
    demo = synthesize_demo(mesh, "box", "top", seed=0)
    r = Retargeter("allegro")
    Q = r.retarget_sequence(demo, object_mesh=mesh, progress=False)
    assert np.all(np.isfinite(Q)) and np.all((Q >= r.lower - 1e-12) & (Q <= r.upper + 1e-12))
    res = np.mean([r.residuals(demo.keypoints[t], Q[t])["all"].mean()
                   for t in range(len(Q))])
    assert res < 0.05  # key vectors within 5 cm on average (spec reference: 44 mm)


def test_bad_inputs(toy):
    hand, config = toy
    r = Retargeter(hand, config)
    with pytest.raises(Exception, match="21, 3"):
        r.retarget_frame(np.zeros((20, 3)), None, None)
    with pytest.raises(Exception, match="object_points"):
        r.retarget_frame(np.zeros((21, 3)), np.zeros((2, 3)), None)
    with pytest.raises(Exception, match="q_prev"):
        r.retarget_frame(np.zeros((21, 3)), None, np.zeros(3))
    with pytest.raises(Exception, match="fingers"):
        Retargeter(hand, {"fingers": {"index": config["fingers"]["index"]}})


def test_palm_term_and_squeeze_targets():
    from dexdrake.demos.human_hand import palm_centre

    r = Retargeter("adroit")
    assert r.config.palm is not None and r.config.weight("object_depth") > 0
    rng = np.random.default_rng(0)
    q_true = np.clip(r.reference_q() + rng.normal(0, 0.05, r.num_joints), r.lower, r.upper)
    kp = np.zeros((21, 3))
    kp[r.human_index] = r.robot_points(q_true)
    target = palm_centre(kp, r.config.palm.out, r.config.palm.along)
    T, w, _ = r.targets(kp, None)
    palm = np.array([k == "palm" for k in r.kv.kind])
    np.testing.assert_allclose(T[palm][0], target)
    assert w[palm][0] == r.config.weight("palm")
    # a human tip touching the object: the robot tip's goal lies object_depth inside
    tip_to_anchor = np.array([[0.0, 0.0, -0.005], [0.0, 0.0, -0.05]])  # 5 mm and 5 cm away
    out = r._squeeze(tip_to_anchor, np.array([0.005, 0.05]), np.array([[0, 0, 1.0]] * 2))
    np.testing.assert_allclose(out[0], [0, 0, r.config.weight("object_depth")])  # anchor - goal
    np.testing.assert_allclose(out[1], tip_to_anchor[1])  # far tips keep the human target


def test_unknown_weight_is_refused(toy):
    hand, config = toy
    with pytest.raises(Exception, match="unknown weights"):
        Retargeter(hand, {**config, "weights": {"objekt": 1.0}})


def _capture(T=40, seed=0):
    """A MediaPipe-like right-hand trajectory in an arbitrary capture frame (rotated,
    1.4 m away), as a demo without an object: the synthetic hand closes and turns."""
    from scipy.spatial.transform import Rotation

    from dexdrake.demos import human_hand as hh

    closed = np.array([[-0.45, 0.95, 0.6, 0.7]] + [[0.0, 1.5, 1.7, 1.2]] * 4)
    R0 = Rotation.random(random_state=seed).as_matrix()
    kp = []
    for a in np.linspace(0, 1, T):
        R = R0 @ Rotation.from_rotvec([0.0, 0.3 * np.sin(3 * a), 0.2 * a]).as_matrix()
        kp.append(hh.hand_keypoints(hh.OPEN_POSE + 0.8 * a * (closed - hh.OPEN_POSE)) @ R.T
                  + [0.5, -1.2, 0.6] + [0.0, 0.06 * a, 0.0])
    kp = np.array(kp)
    return HumanDemo(kp, np.arange(T) / 30.0, "", np.zeros((T, 3)),
                     np.tile([1.0, 0, 0, 0], (T, 1)), DemoMeta())


def _twist_deg(r: Retargeter, q, kp) -> float:
    """Twist (deg) of the robot's palm about the human's finger axis: the angle between the
    palm normals, the robot's projected onto the human's palm-normal/thumb plane."""
    from dexdrake.demos.hand_frame import hand_frames

    Rr, _ = r.hand_frame(q)
    Rh, _ = hand_frames(kp)
    x = Rh.T @ Rr[:, 0]
    return float(np.degrees(abs(np.arctan2(x[1], x[0]))))


@pytest.mark.parametrize("hand", ["allegro", "adroit"])
def test_any_capture_frame_starts_inside_reach(hand):
    """Issue 15: a capture-frame trajectory left the arm at its limits in 92 % of frames
    with the palm twisted ~47 deg; placed on the robot's home frame, neither happens."""
    demo = _capture()
    r = Retargeter(hand)
    n = len(r.hand.arm_joints)
    raw = r.retarget_sequence(demo, progress=False)  # the old behaviour: capture frame as is
    assert np.mean([_twist_deg(r, q, k) for q, k in zip(raw, demo.keypoints)]) > 15
    at_limit = lambda Q: np.mean(np.any(np.isclose(Q[:, :n], r.lower[:n], atol=1e-3)  # noqa: E731
                                        | np.isclose(Q[:, :n], r.upper[:n], atol=1e-3), axis=1))
    assert at_limit(raw) > 0.9
    Q = r.retarget_sequence(demo, progress=False, place=True)
    assert at_limit(Q) == 0.0
    kp = r.place(demo.keypoints)
    twist = [_twist_deg(r, Q[t], kp[t]) for t in range(len(Q))]
    assert max(twist) < 10.0 and np.mean(twist) < 5.0, twist
    res = np.mean([r.residuals(kp[t], Q[t])["all"].mean() for t in range(len(Q))])
    assert res < 0.03


def test_fixed_wrist_moves_fingers_only():
    demo = _capture(T=15)
    r = Retargeter("allegro", fixed_wrist=True)
    n = len(r.hand.arm_joints)
    Q = r.retarget_sequence(demo, progress=False)
    np.testing.assert_allclose(Q[:, :n], np.broadcast_to(r.reference_q()[:n], (len(Q), n)))
    assert np.ptp(Q[:, n:], axis=0).max() > 0.3  # the fingers close
    kp = r.place(demo.keypoints)
    np.testing.assert_allclose(kp[:, 0], np.broadcast_to(r.home()[1], (len(Q), 3)), atol=1e-12)
    assert max(_twist_deg(r, Q[t], kp[t]) for t in range(len(Q))) < 1e-6
    assert Retargeter("allegro").lower[0] < r.lower[0] or Retargeter("allegro").upper[0] > \
        r.upper[0]  # the shared joint-limit arrays were not changed


def test_output_filter_does_not_feed_back(toy):
    from dexdrake.retarget.retargeter import low_pass

    hand, config = toy
    demo, _ = _robot_demo(Retargeter(hand, config))
    raw = Retargeter(hand, config).retarget_sequence(demo, progress=False)
    filtered = Retargeter(hand, dict(config, solver={"filter": 0.3})).retarget_sequence(
        demo, progress=False)
    np.testing.assert_allclose(filtered, low_pass(raw, 0.3), atol=1e-12)
    np.testing.assert_allclose(filtered[0], raw[0])
    assert np.abs(np.diff(filtered, axis=0)).mean() < np.abs(np.diff(raw, axis=0)).mean()
    with pytest.raises(Exception, match="solver.filter"):
        Retargeter(hand, dict(config, solver={"filter": 0.0}))


def _allegro_errors(weights: dict | None = None, seed: int = 3, T: int = 150):
    """(wrist->tip mm, thumb->finger mm, jitter rad/frame) of the shipped fixed-wrist Allegro
    config (scale 1.6, optional weight overrides) on a seeded MediaPipe-like capture of the
    synthetic hand, measured as scripts/bench_retarget.py measures them."""
    from dexdrake.demos.captures import grasp_trajectory, mediapipe_like

    cfg = _allegro_yaml()
    cfg["scales"] = {"wrist": 1.6, "finger": 1.6}
    cfg["weights"].update(weights or {})
    r = Retargeter("allegro", cfg, fixed_wrist=True)
    raw = mediapipe_like(grasp_trajectory(T, seed), seed)
    Q = r.retarget_sequence(HumanDemo(raw, np.arange(T) / 30.0, "", np.zeros((T, 3)),
                                      np.tile([1.0, 0, 0, 0], (T, 1)), DemoMeta()),
                            progress=False)
    kp = r.place(raw)
    wt, tf = [], []
    for q, k in zip(Q, kp):
        P = r.robot_points(q)
        tips, H = P[1:5], k[[HUMAN_TIP[f] for f in r.config.fingers]]
        wt.append(np.linalg.norm((tips - P[0]) - 1.6 * (H - k[0]), axis=1).mean())
        tf.append(np.linalg.norm((tips[1:] - tips[0]) - 1.6 * (H[1:] - H[0]), axis=1).mean())
    n = len(r.hand.arm_joints)
    return 1000 * np.mean(wt), 1000 * np.mean(tf), np.abs(np.diff(Q[:, n:], axis=0)).mean()


def test_allegro_objective_accuracy_on_a_noisy_capture():
    wrist, thumb, jitter = _allegro_errors()
    # measured 42.8 mm, 51.2 mm, 0.0174 rad/frame (dex-retargeting's DexPilot with its filter
    # is worse on all three on such captures in scripts/bench_retarget.py)
    assert wrist < 44.0 and thumb < 52.5 and jitter < 0.019, (wrist, thumb, jitter)
    # the `thumb` weight buys thumb->finger accuracy (measured 52.7 mm at 1)
    _, thumb1, _ = _allegro_errors({"thumb": 1.0})
    assert thumb < thumb1 - 1.0, (thumb, thumb1)


def test_adaptive_low_pass():
    from dexdrake.retarget.retargeter import low_pass

    rng = np.random.default_rng(0)
    still = rng.normal(0.0, 0.01, (200, 1))
    ramp = np.linspace(0.0, 2.0, 200)[:, None]  # 0.01 rad/frame
    plain = low_pass(ramp, 0.05)
    adaptive = low_pass(ramp, 0.05, speed=0.005)
    assert abs(adaptive[-1, 0] - 2.0) < 1e-3 < abs(plain[-1, 0] - 2.0) - 0.1  # no lag
    np.testing.assert_allclose(low_pass(still, 0.05, speed=np.inf), low_pass(still, 0.05))
    jitter = np.abs(np.diff(low_pass(still, 0.05, speed=0.08), axis=0)).mean()
    assert jitter < 0.1 * np.abs(np.diff(still, axis=0)).mean()  # noise is smoothed
    with pytest.raises(Exception, match="filter_speed"):
        Retargeter("allegro", {**_allegro_yaml(), "solver": {"filter_speed": 0}})


def _allegro_yaml() -> dict:
    import yaml

    from dexdrake.retarget.config import CONFIG_DIR

    return yaml.safe_load((CONFIG_DIR / "allegro.yaml").read_text())


def test_compiled_function_matches_casadi_and_is_cached(tmp_path, monkeypatch):
    import os
    import shutil

    import casadi as ca

    from dexdrake.retarget.retargeter import _compiled

    monkeypatch.setenv("DEXDRAKE_CACHE", str(tmp_path))
    x = ca.SX.sym("x", 3)
    f = ca.Function("f", [x], [ca.sin(x) * ca.sumsqr(x)])
    g = _compiled(f)
    if shutil.which(os.environ.get("CC", "cc")) is None:  # no compiler: CasADi's VM
        assert g is f
        return
    (lib,) = (tmp_path / "casadi").glob("f_*.so")
    np.testing.assert_allclose(np.asarray(g([0.1, -0.2, 0.3])), np.asarray(f([0.1, -0.2, 0.3])),
                               rtol=1e-12)
    built = lib.stat().st_mtime_ns
    _compiled(f)
    assert lib.stat().st_mtime_ns == built  # loaded from the cache, not rebuilt
