"""Retargeting quality and speed against dex-retargeting, both run live in this run.

Equal terms: the Allegro hand, fixed wrist (16 finger DoF), the same forward kinematics
(the peer's URDF is written here from dexdrake's own Allegro model: the arm frozen at the
reference pose, a `wrist` link at the retarget config's wrist point), the same 1.6 scale
and the same world-frame key vectors (human keypoints in the canonical hand frame placed
on the robot's home frame). The peer is dex-retargeting's DexPilot optimizer (NLopt SLSQP,
torch loss), with and without its low-pass filter (alpha 0.2, as its Allegro config).

One metric for both, on every frame, with dexdrake's FK:
    wrist->tip    mean || (tip_R - wrist_R) - 1.6 (tip_H - wrist_H) ||   (mm)
    thumb->finger mean || (f_R - thumb_R) - 1.6 (f_H - thumb_H) ||       (mm)
    jitter        mean |q_t - q_t-1| over the 16 finger joints          (rad/frame)
    ms/frame      CPU time (time.process_time) per frame, one thread

Data (`dexdrake/demos/captures.py`): the synthetic adult hand moving between grasp poses
(--motion grasps, --frames) or the object grasp demos of `dexdrake demos synth` (--motion
demos), in an arbitrary capture frame, with 2 mm white noise (--noise gaussian) or the
seeded errors of a monocular MediaPipe capture (--noise mediapipe: another hand's bone
lengths, slow depth-heavy drift, jitter, glitches); --save writes them for --keypoints. Or a
keypoint file (--keypoints FILE, read as `dexdrake demos import` reads it), e.g. a real
capture: MediaPipe Holistic fingerspelling of real signers, which
`scripts/pose_to_keypoints.py --lexicon LANG` writes into the cache from the `captures` extra
(it prints the path).

Needs the `bench` extra: pip install -e '.[bench]'. Without it only our row is printed.

    OMP_NUM_THREADS=1 python scripts/bench_retarget.py [--frames 600] [--seed 0]
        [--motion grasps|demos] [--noise gaussian|mediapipe] [--save F.npy] [--keypoints F]
    OMP_NUM_THREADS=1 python scripts/bench_retarget.py \
        --keypoints "$(python scripts/pose_to_keypoints.py --lexicon ase)"
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from dexdrake.demos.captures import grasp_trajectory, mediapipe_like  # noqa: E402
from dexdrake.demos.format import DemoMeta, HumanDemo  # noqa: E402
from dexdrake.retarget.retargeter import Retargeter  # noqa: E402

SCALE = 1.6  # DexPilot's Allegro/human ratio, used by both sides
TIPS = {"thumb": 4, "index": 8, "middle": 12, "ring": 16}
FILTER_ALPHA = 0.2  # dex-retargeting's Allegro teleop config


def object_demo_keypoints(seed: int) -> np.ndarray:
    """(T, 21, 3): the synthetic grasp demos (approach, close, lift) of four library objects,
    one after another, at 30 fps, noise-free."""
    from dexdrake.demos.synthetic import synthesize_object_demos

    demos = [d for name in ("mug", "banana", "can_soda", "box_cube")
             for d in synthesize_object_demos(name, 2, seed, heading=None)]
    return np.concatenate([d.keypoints[::2] for d in demos])


def peer_urdf(r: Retargeter, folder: Path) -> Path:
    """dexdrake's Allegro model as a fixed-base URDF for pinocchio: arm joints frozen at
    the reference pose, Drake tags, meshes and transmissions removed, and a `wrist` link at
    the retarget config's wrist point. Same kinematics as dexdrake's FK."""
    tree = ET.parse(r.hand.model_path)
    root = tree.getroot()
    for tag in ("transmission",):
        for e in root.findall(tag):
            root.remove(e)
    for link in root.findall("link"):
        for tag in ("visual", "collision"):
            for e in link.findall(tag):
                link.remove(e)
    q_ref = dict(zip(r.joint_names, r.reference_q()))
    for j in root.findall("joint"):
        name = j.get("name")
        if name in r.hand.arm_joints:
            axis = np.array([float(x) for x in j.find("axis").get("xyz").split()])
            value = q_ref[name] * axis
            origin = j.find("origin")
            key = "xyz" if j.get("type") == "prismatic" else "rpy"
            origin.set(key, " ".join(f"{v:.9g}" for v in value))
            j.set("type", "fixed")
            for tag in ("axis", "limit", "dynamics"):
                for e in j.findall(tag):
                    j.remove(e)
    for e in list(root):
        if e.tag.startswith("{"):
            root.remove(e)
    if not any(link.get("name") == "world" for link in root.findall("link")):
        root.insert(0, ET.Element("link", name="world"))
    root.append(ET.Element("link", name="wrist"))
    w = ET.SubElement(root, "joint", name="wrist_point", type="fixed")
    ET.SubElement(w, "parent", link=r.config.wrist.body)
    ET.SubElement(w, "child", link="wrist")
    ET.SubElement(w, "origin", xyz=" ".join(f"{v:.9g}" for v in r.config.wrist.offset),
                  rpy="0 0 0")
    path = folder / "allegro_right.urdf"
    tree.write(path)
    return path


def metrics(r: Retargeter, Q: np.ndarray, kp: np.ndarray) -> dict[str, float]:
    """Wrist->tip and thumb->finger errors (mm) and jitter (rad/frame) with dexdrake's FK."""
    names = [t.name for t in r.config.tips]  # robot tip order of the config
    human_tips = [TIPS[f] for f in r.config.fingers]
    wt, tf = [], []
    for q, k in zip(Q, kp):
        P = r.robot_points(q)
        wrist, tips = P[0], P[1:1 + len(names)]
        H = k[human_tips]
        wt.append(np.linalg.norm((tips - wrist) - SCALE * (H - k[0]), axis=1).mean())
        tf.append(np.linalg.norm((tips[1:] - tips[0]) - SCALE * (H[1:] - H[0]), axis=1).mean())
    n = len(r.hand.arm_joints)
    return {"wrist": 1000 * np.mean(wt), "thumb": 1000 * np.mean(tf),
            "jitter": float(np.mean(np.abs(np.diff(Q[:, n:], axis=0))))}


def run_ours(r: Retargeter, demo: HumanDemo) -> tuple[np.ndarray, float]:
    r.retarget_sequence(HumanDemo(demo.keypoints[:5], demo.time[:5], "", demo.object_pos[:5],
                                  demo.object_quat[:5], demo.meta), progress=False)  # warm-up
    t = time.process_time()
    Q = r.retarget_sequence(demo, progress=False)
    return Q, 1000 * (time.process_time() - t) / demo.num_frames


def run_peer(r: Retargeter, kp: np.ndarray, alpha: float, folder: Path
             ) -> tuple[np.ndarray, float]:
    """dex-retargeting's DexPilot on the same world-frame key vectors; joint angles in
    dexdrake's policy order (arm at the reference pose)."""
    from dex_retargeting.retargeting_config import RetargetingConfig

    tips = {t.name: t.body for t in r.hand.fingertips}
    cfg = RetargetingConfig(
        type="DexPilot", urdf_path=str(peer_urdf(r, folder)), wrist_link_name="wrist",
        finger_tip_link_names=[tips[f"{f}_tip"] for f in r.config.fingers],
        scaling_factor=SCALE, low_pass_alpha=alpha)
    seq = cfg.build()
    idx = seq.optimizer.target_link_human_indices
    order = [seq.joint_names.index(j) for j in r.joint_names[len(r.hand.arm_joints):]]
    Q = np.tile(r.reference_q(), (len(kp), 1))
    n = len(r.hand.arm_joints)
    t = time.process_time()
    for k, frame in enumerate(kp):
        Q[k, n:] = seq.retarget(frame[idx[1]] - frame[idx[0]])[order]
    return Q, 1000 * (time.process_time() - t) / len(kp)


def check_same_fk(r: Retargeter, folder: Path) -> float:
    """Largest tip-position difference (m) between pinocchio on the peer URDF and dexdrake."""
    import pinocchio as pin

    model = pin.buildModelFromUrdf(str(folder / "allegro_right.urdf"))
    data = model.createData()
    rng = np.random.default_rng(0)
    worst = 0.0
    n = len(r.hand.arm_joints)
    for _ in range(5):
        q = r.reference_q()
        q[n:] = rng.uniform(r.lower[n:], r.upper[n:])
        qp = pin.neutral(model)
        for name, v in zip(r.joint_names[n:], q[n:]):
            qp[model.joints[model.getJointId(name)].idx_q] = v
        pin.framesForwardKinematics(model, data, qp)
        for i, tip in enumerate(r.config.tips):
            p = data.oMf[model.getFrameId(tip.body)].translation
            worst = max(worst, float(np.linalg.norm(p - r.robot_points(q)[1 + i])))
    return worst


def equal_terms_config(r: Retargeter) -> dict:
    """The shipped Allegro config with the peer's scale (1.6) on every key vector."""
    import yaml

    from dexdrake.retarget.config import CONFIG_DIR

    d = yaml.safe_load((CONFIG_DIR / f"{r.hand.name}.yaml").read_text())
    d["scales"] = {**d.get("scales", {}), "wrist": SCALE, "finger": SCALE}
    return d


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--motion", choices=("grasps", "demos"), default="grasps",
                    help="synthetic motion: random grasp poses (--frames) or the object "
                    "grasp demos of `dexdrake demos synth` (4 objects, 30 fps)")
    ap.add_argument("--noise", choices=("gaussian", "mediapipe"), default="gaussian",
                    help="2 mm white noise, or a MediaPipe-like capture "
                    "(`captures.mediapipe_like`)")
    ap.add_argument("--save", type=Path, help="also write the synthetic keypoints (.npy)")
    ap.add_argument("--keypoints", type=Path, help="a keypoint file (.npy/.npz/.pkl/.json/.csv) "
                    "instead of the synthetic trajectory")
    args = ap.parse_args()
    if args.keypoints:
        from dexdrake.demos.loaders import load_keypoint_array

        raw = load_keypoint_array(args.keypoints).keypoints
        source = str(args.keypoints)
    else:
        if args.motion == "grasps":
            raw = grasp_trajectory(args.frames, args.seed,
                                   0.002 if args.noise == "gaussian" else 0.0)
        else:
            raw = object_demo_keypoints(args.seed)
        if args.noise == "mediapipe":
            raw = mediapipe_like(raw, args.seed)
        elif args.motion == "demos":
            raw = raw + np.random.default_rng(args.seed).normal(0.0, 0.002, raw.shape)
        source = f"synthetic {args.motion}, seed {args.seed}, {args.noise} noise"
        if args.save:
            np.save(args.save, raw.astype(np.float32))
    base = Retargeter("allegro", fixed_wrist=True)
    r = Retargeter("allegro", equal_terms_config(base), fixed_wrist=True)
    kp = r.place(raw)
    T = len(kp)
    demo = HumanDemo(kp, np.arange(T) / 30.0, "", np.zeros((T, 3)), np.tile([1.0, 0, 0, 0], (T, 1)),
                     DemoMeta())
    print(f"Allegro, fixed wrist, 16 DoF, scale {SCALE}; {T} frames ({source}); one thread, "
          f"CPU ms/frame; load average {os.getloadavg()[0]:.1f}")
    rows = []
    Q, ms = run_ours(r, demo)
    rows.append(("dexdrake (CasADi LM)", metrics(r, Q, kp), ms))
    try:
        import dex_retargeting  # noqa: F401
    except ImportError:
        print("dex-retargeting is not installed (pip install -e '.[bench]'): peer rows skipped")
    else:
        with tempfile.TemporaryDirectory(prefix="bench_retarget_") as tmp:
            folder = Path(tmp)
            for label, alpha in ((f"dex-retargeting 0.5 DexPilot, filter {FILTER_ALPHA}", FILTER_ALPHA),
                                 ("dex-retargeting 0.5 DexPilot, unfiltered", -1.0)):
                Qp, msp = run_peer(r, kp, alpha, folder)
                rows.append((label, metrics(r, Qp, kp), msp))
            print(f"same FK: largest tip difference pinocchio vs dexdrake "
                  f"{1000 * check_same_fk(r, folder):.4f} mm")
    print(f"{'retargeter':44s} {'wrist->tip mm':>13s} {'thumb->finger mm':>16s} "
          f"{'jitter rad/fr':>13s} {'ms/frame':>9s} {'vs ours':>9s}")
    for label, m, t in rows:
        print(f"{label:44s} {m['wrist']:13.1f} {m['thumb']:16.1f} {m['jitter']:13.4f} "
              f"{t:9.2f} {t / rows[0][2]:8.1f}x")


if __name__ == "__main__":
    main()
