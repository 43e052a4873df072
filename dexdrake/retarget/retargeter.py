"""Human keypoints -> robot joint angles, solved per frame with a bounded Levenberg-Marquardt
whose step (key vectors, analytic Jacobians, Cholesky solve, bounds, accept test) is one
CasADi function compiled to machine code (`_compiled`); a warm-started frame takes
`solver.iterations` such steps, the targets of a whole sequence are computed at once.

Objective per frame (DexRepNet, DexPilot-style), over the policy joints that can move (the
6 virtual arm joints are the global hand pose M_g; a fixed wrist solves the fingers only):
    1/2 sum_i w_i || v_i^R(q) - t_i ||^2 + w_smooth/2 || q - q_prev ||^2,   lo <= q <= hi
Key vectors v_i (robot) and their human counterparts v_i^H:
    wrist   wrist -> each fingertip and finger base        t_i = k_i v_i^H (k_i auto: robot/human);
            the base vectors (weight x `base`) hold the palm's orientation (left out
            with a fixed wrist)
    finger  thumb tip -> each tip (weight x `thumb`), tip -> tip      t_i = k_f v_i^H, or
            DexPilot's pinch projection: thumb-finger with human length < eps:
            t = eta1 * unit, w = s1; finger-finger with both fingers pinching: t = eta2 * unit,
            w = s2 (eps hysteresis eps_enter / eps_leave)
    object  fingertip -> object anchor (the object point closest to the human fingertip)
            t_i = v_i^H, w = w_obj / (1 + (d_i / decay)^2) with d_i the human tip's distance;
            within `object_contact` of the surface the human tip is replaced by a goal
            `object_depth` inside the surface (fading out at twice the distance), so the
            fingers' position servos squeeze the object
    palm    world origin -> robot palm grasp centre, t = the human palm centre
            (`human_hand.palm_centre`; optional, config `palm`)
    position  world origin -> wrist point, t = human wrist (small weight: holds the global
            position when no object is given)

What it trades: a robot hand whose proportions differ from the human's cannot match every
vector at once, so the weights choose. `thumb` sets the wrist->tip error against the
thumb->finger error (the thumb's opposition, which decides a grasp); the pinch terms trade
both for closing the robot's tips when the human pinches (their targets are not the scaled
human vectors); `w_smooth` and the output low-pass (`solver.filter`, `low_pass`) trade lag,
i.e. error on moving frames, for less jitter. The smoothness term damps the joint directions
that the key vectors hardly fix (where tracker noise moves q most) and leaves the well-fixed
ones almost free; the low-pass, adaptive with `solver.filter_speed`, smooths still joints
hard and follows moving ones closely. `solver.iterations` trades time for convergence: with
the warm start and the smoothness term a frame is near its optimum after one or two steps.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from dexdrake.demos.format import HumanDemo
from dexdrake.errors import DexdrakeError
from dexdrake.hands.description import HandDescription, load_hand
from dexdrake.retarget.config import RetargetConfig, auto_scale, load_config
from dexdrake.retarget.kinematics import extract_tree, symbolic_points


@dataclass(frozen=True)
class KeyVectors:
    """Index pairs (a -> b) into the extended point list [robot points (wrist, tips, bases,
    palm if configured), anchors, origin]."""

    a: np.ndarray
    b: np.ndarray
    kind: tuple[str, ...]  # wrist | thumb-finger | finger-finger | object | position | palm
    fingers: tuple[tuple[int, ...], ...]  # finger indices (into config.fingers) involved


def _key_vectors(cfg: RetargetConfig) -> KeyVectors:
    nf, has_palm = len(cfg.fingers), cfg.palm is not None
    wrist, tip, base, palm = 0, 1, 1 + nf, 1 + 2 * nf
    anchor = 1 + 2 * nf + has_palm
    origin = anchor + nf
    a, b, kind, fingers = [], [], [], []

    def add(i, j, k, f):
        a.append(i), b.append(j), kind.append(k), fingers.append(f)

    for f in range(nf):
        add(wrist, tip + f, "wrist", (f,))
        add(wrist, base + f, "wrist", (f,))
    for f in range(1, nf):  # finger 0 is the thumb
        add(tip, tip + f, "thumb-finger", (0, f))
    for f in range(1, nf):
        for g in range(f + 1, nf):
            add(tip + f, tip + g, "finger-finger", (f, g))
    for f in range(nf):
        add(tip + f, anchor + f, "object", (f,))
    add(origin, wrist, "position", ())
    if has_palm:
        add(origin, palm, "palm", ())
    return KeyVectors(np.array(a), np.array(b), tuple(kind), tuple(fingers))


class Retargeter:
    """Retargets 21 human keypoints to the joint angles (policy order) of a robot hand.

    Build once per hand (FK graph and solver functions are made here), then call
    `retarget_frame` per frame or `retarget_sequence` per demo.

    fixed_wrist: the arm joints stay at the reference pose and only the fingers are solved
    (a hand on a fixed mount); sequences are then put into the home frame frame by frame.
    """

    def __init__(self, hand_name: str | HandDescription,
                 config: str | Path | dict | RetargetConfig | None = None,
                 fixed_wrist: bool = False):
        self.hand = hand_name if isinstance(hand_name, HandDescription) else load_hand(hand_name)
        self.config = config if isinstance(config, RetargetConfig) else load_config(
            self.hand, config)
        cfg = self.config
        self.joint_names = self.hand.policy_joints
        self.lower, self.upper = (a.copy() for a in self.hand.joint_limits())  # cached arrays
        self.fixed_wrist = fixed_wrist
        if fixed_wrist:
            arm = [self.joint_names.index(j) for j in self.hand.arm_joints]
            self.lower[arm] = self.upper[arm] = self.reference_q()[arm]
        self.points = [cfg.wrist, *cfg.tips, *cfg.bases]
        self.human_index = np.array([p.human for p in self.points])
        tree = extract_tree(self.hand.model_path)
        fk_points = self.points + ([cfg.palm.point] if cfg.palm is not None else [])
        q, P = symbolic_points(tree, self.joint_names,
                               [(p.body, np.array(p.offset)) for p in fk_points])
        self.fk = ca.Function("fk", [q], [P])
        nf = len(cfg.fingers)
        self.kv = kv = _key_vectors(cfg)
        a = ca.SX.sym("anchors", 3 * nf)  # row-major (nf, 3)
        E = ca.vertcat(P, ca.reshape(a, 3, nf).T, ca.SX.zeros(1, 3))
        V = E[kv.b.tolist(), :] - E[kv.a.tolist(), :]
        v = ca.reshape(V.T, -1, 1)  # row-major flattening
        self._active = np.flatnonzero(self.lower < self.upper)  # the joints solved for
        kinds = np.array(kv.kind)
        self._masks = {c: kinds == c for c in ("wrist", "thumb-finger", "finger-finger",
                                               "object", "position", "palm")}
        self._base = self._masks["wrist"] & (np.arange(len(kinds)) % 2 == 1)  # wrist -> base
        vectors = ca.Function("vectors", [q, a], [v])
        # a fixed wrist has no object terms and its palm cannot turn: the object and
        # wrist->base vectors (which would only pull the abduction joints towards the human
        # knuckles, adding their tracker noise) are left out of the solve
        self._rows = np.flatnonzero(~(self._masks["object"] | self._base) if fixed_wrist
                                    else np.ones(len(kinds), bool))
        step = _compiled(self._lm_step(vectors, q, a))
        # zero-copy evaluation: inputs and outputs live in these numpy buffers
        n, m = len(self.joint_names), len(self._rows)
        self._in = [np.zeros(k) for k in (n, n, 3 * m, m, 3 * nf, 1, 1)]
        self._out = [np.zeros(k) for k in (n, 1, 1)]
        self._buf, self._eval = step.buffer()
        for i, arr in enumerate(self._in):
            self._buf.set_arg(i, memoryview(arr))
        for i, arr in enumerate(self._out):
            self._buf.set_res(i, memoryview(arr))
        self._tf = np.flatnonzero(self._masks["thumb-finger"])
        self._tf_finger = np.array([kv.fingers[i][1] for i in self._tf], int)
        self._ff = np.flatnonzero(self._masks["finger-finger"])
        self._ff_pair = np.array([kv.fingers[i] for i in self._ff], int).reshape(-1, 2)
        self.scales = self._scales()
        m = self._masks
        self._weights = (cfg.weight("wrist") * m["wrist"] + cfg.weight("finger") * (
            m["thumb-finger"] | m["finger-finger"]) + cfg.weight("palm") * m["palm"]
            + cfg.weight("wrist_position") * m["position"])  # object terms: per frame
        self._weights[self._base] *= cfg.weight("base")
        self._weights[self._tf] *= cfg.weight("thumb")
        self._pinch = np.zeros(nf, bool)
        self._smooth = cfg.weight("smooth")

    def _lm_step(self, vectors: ca.Function, q: ca.SX, a: ca.SX) -> ca.Function:
        """One bounded Levenberg-Marquardt step, compiled to a CasADi SX function
        (q, q_ref, targets, weights, anchors, smooth, mu) -> (q', mu', |dq|max): a Gauss-Newton
        step with analytic (symbolic) Jacobians for
            1/2 sum_i w_i ||v_i(q) - t_i||^2 + smooth/2 ||q - q_ref||^2,   lo <= q <= hi
        on the active joints (the solved vectors `_rows` only), solved by an unrolled Cholesky
        on the free set (joints at a bound that the gradient pushes out keep zero step); kept
        only if it lowers the cost, and the damping mu shrinks (kept) or grows (refused;
        |dq|max is then inf)."""
        act, rows = self._active, self._rows
        m = len(rows)
        lo, hi = self.lower[act], self.upper[act]
        x = q[act.tolist()]
        q_ref, t, w = ca.SX.sym("q_ref", q.numel()), ca.SX.sym("t", 3 * m), ca.SX.sym("w", m)
        smooth, mu = ca.SX.sym("smooth"), ca.SX.sym("mu")
        pick = np.ravel(3 * rows[:, None] + np.arange(3)).tolist()
        dx_ref = x - q_ref[act.tolist()]

        def residual(qq):  # (weighted residuals (3 m), cost)
            r = ca.vec(sw * ca.reshape(vectors(qq, a)[pick] - t, 3, m))
            dx = qq[act.tolist()] - q_ref[act.tolist()]
            return r, 0.5 * ca.dot(r, r) + 0.5 * smooth * ca.dot(dx, dx)

        sw = ca.repmat(ca.sqrt(w).T, 3, 1)  # (3, m): per component
        r, cost = residual(q)
        J = ca.jacobian(r, x)
        g = ca.mtimes(J.T, r) + smooth * dx_ref
        H = ca.mtimes(J.T, J) + (smooth + mu) * ca.SX.eye(len(act))
        fixed = ca.logic_or(ca.logic_and(x <= lo + 1e-9, g > 0),
                            ca.logic_and(x >= hi - 1e-9, g < 0))
        free = 1 - fixed
        step, ok = _cholesky_solve(H * ca.mtimes(free, free.T) + ca.diag(fixed), g * free)
        x_new = ca.fmin(ca.fmax(x - step, lo), hi)
        q_new = ca.SX(q)
        for k, i in enumerate(act):
            q_new[int(i)] = x_new[k]
        keep = ca.logic_and(ok, residual(q_new)[1] <= cost)
        return ca.Function("lm_step", [q, q_ref, t, w, a, smooth, mu], [
            ca.if_else(keep, q_new, q),
            ca.if_else(keep, ca.fmax(0.3 * mu, 1e-9), ca.fmax(10 * mu, 1e-6)),
            ca.if_else(keep, ca.mmax(ca.fabs(x_new - x)), np.inf)])

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def reference_q(self) -> np.ndarray:
        """The hand's pre-grasp pose (cold-start guess)."""
        return self.hand.pregrasp_vector()

    def hand_frame(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(R, origin): the robot hand's own hand frame at joint angles q, built from its
        wrist and finger-base points as `hand_frame.hand_frames` builds a human's."""
        from dexdrake.demos.hand_frame import LITTLE_MCP, hand_frames

        kp = np.zeros((21, 3))
        kp[self.human_index] = self.robot_points(q)
        little = max(int(i) for i in (13, LITTLE_MCP) if i in self.human_index)
        return hand_frames(kp, little)

    def home(self) -> tuple[np.ndarray, np.ndarray]:
        """The robot's hand frame at the reference pose: where `place` puts a human hand."""
        return self.hand_frame(self.reference_q())

    def place(self, keypoints: np.ndarray) -> np.ndarray:
        """A (T, 21, 3) right-hand sequence in any frame, put into the canonical hand frame
        (`hand_frame.canonical`; per frame when the wrist is fixed) and that frame placed on
        the robot's `home` frame, so the solve starts inside the arm's reach."""
        from dexdrake.demos.hand_frame import canonical

        R, origin = self.home()
        return canonical(keypoints, per_frame=self.fixed_wrist) @ R.T + origin

    def _scales(self) -> np.ndarray:
        from dexdrake.demos.human_hand import open_hand_keypoints

        cfg, kv = self.config, self.kv
        q0 = np.clip(np.zeros(self.num_joints), self.lower, self.upper)
        robot = self._extended(np.asarray(self.fk(q0)), np.zeros((len(cfg.fingers), 3)))
        human = self._extended(self._human_points(open_hand_keypoints()),
                               np.zeros((len(cfg.fingers), 3)))
        r_len = np.linalg.norm(robot[kv.b] - robot[kv.a], axis=1)
        h_len = np.linalg.norm(human[kv.b] - human[kv.a], axis=1)
        k = np.ones(len(kv.kind))
        wrist = np.array([c == "wrist" for c in kv.kind])
        finger = np.array([c in ("thumb-finger", "finger-finger") for c in kv.kind])
        sw, sf = cfg.scale("wrist"), cfg.scale("finger")
        k[wrist] = auto_scale(r_len[wrist], h_len[wrist]) if sw == "auto" else float(sw)
        tips = wrist & (np.arange(len(k)) % 2 == 0)  # wrist -> tip vectors
        k[finger] = np.median(auto_scale(r_len[tips], h_len[tips])) if sf == "auto" \
            else float(sf)
        k[np.array([c == "object" for c in kv.kind])] = float(cfg.scale("object"))
        return k

    @staticmethod
    def _extended(points: np.ndarray, anchors: np.ndarray) -> np.ndarray:
        return np.vstack([points, anchors, np.zeros((1, 3))])

    def _human_points(self, kp: np.ndarray) -> np.ndarray:
        """The human counterparts of the FK points: keypoints, then the palm centre;
        (..., 21, 3) -> (..., points, 3)."""
        pts = kp[..., self.human_index, :]
        palm = self.config.palm
        if palm is None:
            return pts
        from dexdrake.demos.human_hand import palm_centre

        return np.concatenate([pts, palm_centre(kp, palm.out, palm.along)[..., None, :]],
                              axis=-2)

    def reset(self) -> None:
        """Forget the pinch (hysteresis) state, e.g. at the start of a new sequence."""
        self._pinch[:] = False

    def targets(self, keypoints: np.ndarray, anchors: np.ndarray | None,
                normals: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(targets (m, 3), weights (m,), anchors used) for one frame; updates pinch state.

        normals: outward surface normals at the anchors (None: from anchor - tip)."""
        T, w, A = self._targets(np.asarray(keypoints, float)[None],
                                None if anchors is None else np.asarray(anchors, float)[None],
                                None if normals is None else np.asarray(normals, float)[None])
        return T[0], w[0], A[0]

    def _targets(self, kp: np.ndarray, anchors: np.ndarray | None,
                 normals: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`targets` for F frames at once: kp (F, 21, 3), anchors and normals (F, nf, 3) or
        None -> (F, m, 3), (F, m), (F, nf, 3); the pinch state runs through the frames."""
        cfg, kv, pp = self.config, self.kv, self.config.pinch
        nf = len(cfg.fingers)
        if kp.shape[1:] != (21, 3) or not np.all(np.isfinite(kp)):
            raise DexdrakeError(f"keypoints must be a finite (21, 3) array, got {kp.shape[1:]}")
        has_obj = anchors is not None
        A = anchors if has_obj else np.zeros((len(kp), nf, 3))
        if A.shape[1:] != (nf, 3):
            raise DexdrakeError(f"object_points must be ({nf}, 3): one per finger "
                                f"{cfg.fingers}, got {A.shape[1:]}")
        E = np.concatenate([self._human_points(kp), A, np.zeros((len(kp), 1, 3))], axis=1)
        vh = E[:, kv.b] - E[:, kv.a]
        T = vh * self.scales[:, None]
        d = np.linalg.norm(vh, axis=2)
        w = np.tile(self._weights, (len(kp), 1))
        if has_obj:
            obj = self._masks["object"]
            w[:, obj] = cfg.weight("object") / (1 + (d[:, obj] / cfg.weight("object_decay")) ** 2)
            T[:, obj] = self._squeeze(vh[:, obj], d[:, obj], normals)
        # DexPilot pinch projection with hysteresis (eps_enter to enter, eps_leave to leave)
        pinch = np.zeros((len(kp), nf), bool)
        state, d_tf = self._pinch[self._tf_finger], d[:, self._tf]
        for f, dist in enumerate(d_tf):
            state = dist < np.where(state, pp.eps_leave, pp.eps_enter)
            pinch[f, self._tf_finger] = state
        if len(kp):
            self._pinch[:] = pinch[-1]
        unit = vh / np.maximum(d, 1e-9)[..., None]
        projected = np.zeros(w.shape, bool)
        projected[:, self._tf] = pinch[:, self._tf_finger]
        s2 = np.zeros(w.shape, bool)
        if len(self._ff):
            s2[:, self._ff] = pinch[:, self._ff_pair].all(axis=2)
        T = np.where(projected[..., None], pp.eta1 * unit,
                     np.where(s2[..., None], pp.eta2 * unit, T))
        w = np.where(projected, pp.s1, np.where(s2, pp.s2, w))
        return T, w, A

    def _squeeze(self, tip_to_anchor: np.ndarray, d: np.ndarray, normals: np.ndarray | None
                 ) -> np.ndarray:
        """Object targets (tip -> anchor) with the tip goal moved `object_depth` inside the
        surface for human tips within `object_contact` (linear fade out to twice that)."""
        cfg = self.config
        depth, contact = cfg.weight("object_depth"), cfg.weight("object_contact")
        if depth <= 0.0:
            return tip_to_anchor
        if normals is None:  # outward normal from the anchor towards the (outside) tip
            normals = -tip_to_anchor / np.maximum(d, 1e-9)[..., None]
        s = np.clip(2.0 - d / contact, 0.0, 1.0)
        # goal = tip - s (d + depth) n  =>  anchor - goal = tip_to_anchor + s (d + depth) n
        return tip_to_anchor + (s * (d + depth))[..., None] * normals

    def retarget_frame(self, keypoints: np.ndarray, object_points: np.ndarray | None = None,
                       q_prev: np.ndarray | None = None,
                       object_normals: np.ndarray | None = None) -> np.ndarray:
        """Joint angles (policy order) for one frame of 21 world keypoints (MediaPipe order).

        object_points: (n_fingers, 3) world points of the object closest to each human
        fingertip of the config's fingers (None: no finger-to-object terms). q_prev: the
        previous frame's solution (warm start + smoothness); None = cold start.
        object_normals: outward surface normals at object_points (None: estimated).
        """
        if q_prev is None:
            self.reset()
        else:
            q_prev = np.asarray(q_prev, float)
            if q_prev.shape != (self.num_joints,):
                raise DexdrakeError(f"q_prev must have shape ({self.num_joints},), got "
                                    f"{q_prev.shape}")
        T, w, A = self.targets(keypoints, object_points, object_normals)
        return self._solve_frame(T[self._rows].ravel(), w[self._rows], A.ravel(), q_prev)

    def _solve_frame(self, t: np.ndarray, w: np.ndarray, a: np.ndarray,
                     q_prev: np.ndarray | None) -> np.ndarray:
        """A cold start (from the reference pose, no smoothness, `first_iterations`) or a
        warm start from q_prev (`smooth` towards it, `iterations`), for the solved vectors'
        flat targets t, weights w and flat anchors a."""
        q, q_ref, t_in, w_in, a_in, smooth, mu = self._in
        t_in[:], w_in[:], a_in[:], mu[0] = t, w, a, self.config.damping
        if q_prev is None:
            q[:], smooth[0], iterations = self.reference_q(), 0.0, self.config.first_iterations
        else:
            np.clip(q_prev, self.lower, self.upper, out=q)
            smooth[0], iterations = self._smooth, self.config.iterations
        q_ref[:] = q
        # up to `iterations` compiled LM steps (`_lm_step`); stop once a kept step moves no
        # joint by more than 1e-4 rad
        q_out, mu_out, moved = self._out
        for _ in range(iterations):
            self._eval()
            q[:], mu[0] = q_out, mu_out[0]
            if moved[0] < 1e-4:
                break
        return q.copy()

    def robot_points(self, q: np.ndarray) -> np.ndarray:
        """World positions of the config's robot points [wrist, tips..., bases...]."""
        return np.asarray(self.fk(np.asarray(q, float)))[: len(self.points)]

    def residuals(self, keypoints: np.ndarray, q: np.ndarray) -> dict[str, np.ndarray]:
        """Key-vector residuals ||v^R - k v^H|| (m) without pinch projection: 'wrist'
        (wrist->tip/base), 'finger' (tip->tip), and 'thumb' (vectors that involve the thumb)."""
        kv = self.kv
        nf = len(self.config.fingers)
        H = self._extended(self._human_points(np.asarray(keypoints)), np.zeros((nf, 3)))
        R = self._extended(np.asarray(self.fk(np.asarray(q, float))), np.zeros((nf, 3)))
        err = np.linalg.norm((R[kv.b] - R[kv.a]) - self.scales[:, None] * (H[kv.b] - H[kv.a]),
                             axis=1)
        kinds = np.array(kv.kind)
        wrist = kinds == "wrist"
        finger = (kinds == "thumb-finger") | (kinds == "finger-finger")
        thumb = np.array([0 in f for f in kv.fingers]) & (wrist | finger)
        return {"wrist": err[wrist], "finger": err[finger], "thumb": err[thumb],
                "all": err[wrist | finger]}

    def object_points(self, keypoints: np.ndarray, closest) -> np.ndarray:
        """Anchors for one frame: `closest(points (n, 3)) -> (n, 3)` object surface points."""
        return np.asarray(closest(self.human_tips(keypoints)))

    def human_tips(self, keypoints: np.ndarray) -> np.ndarray:
        """The human fingertip keypoints of the config's fingers, (n_fingers, 3)."""
        return np.asarray(keypoints)[[p.human for p in self.config.tips]]

    def retarget_sequence(self, demo: HumanDemo, object_mesh=None, progress: bool = True,
                          place: bool = False) -> np.ndarray:
        """(T, n_joints) joint trajectory for a demo, warm-started frame to frame.

        object_mesh: a trimesh.Trimesh in the object frame for finger-to-object vectors;
        None = look the demo's object up in the object library, and skip the object terms
        if it is not there. place: put the keypoints on the robot's home frame first
        (`place`; for demos without an object). A fixed-wrist retargeter always places them
        and has no object terms.
        """
        from tqdm import tqdm

        closest = None if self.fixed_wrist else _closest_point_fn(demo, object_mesh)
        keypoints = self.place(demo.keypoints) if place or self.fixed_wrist else demo.keypoints
        anchors = normals = None
        if closest is not None:
            found = [closest(self.human_tips(kp), t) for t, kp in enumerate(keypoints)]
            anchors, normals = (np.array([f[i] for f in found]) for i in (0, 1))
        self.reset()
        T, w, A = self._targets(np.asarray(keypoints, float), anchors, normals)
        F = demo.num_frames
        T, w, A = T[:, self._rows].reshape(F, -1), w[:, self._rows], A.reshape(F, -1)
        out = np.zeros((F, self.num_joints))
        q = None
        for t in tqdm(range(F), desc=f"retarget {self.hand.name}", disable=not progress,
                      unit="frame"):
            q = out[t] = self._solve_frame(T[t], w[t], A[t], q)
        return low_pass(out, self.config.filter, self.config.filter_speed)


def low_pass(Q: np.ndarray, alpha: float, speed: float = np.inf) -> np.ndarray:
    """Adaptive exponential low-pass of a (T, n) trajectory (one-euro style), per joint:
        y_t = y_t-1 + a_t (q_t - y_t-1),   a_t = alpha + (1 - alpha) min(1, |s_t| / speed)
    with s_t = 0.3 (q_t - y_t-1) + 0.7 s_t-1 the smoothed step (rad/frame): a still joint is
    smoothed with alpha (tracker noise), a moving one followed with less lag (speed = inf:
    the plain exponential low-pass; alpha 1: unchanged). Applied to the output only: each
    frame's solve still starts from the previous unfiltered solution, so the filter does
    not feed back into the fit."""
    out = np.array(Q, float)
    if alpha >= 1.0:
        return out
    step = np.zeros(out.shape[1:])
    for t in range(1, len(out)):
        d = out[t] - out[t - 1]
        step = 0.3 * d + 0.7 * step
        out[t] = out[t - 1] + (alpha + (1.0 - alpha) * np.minimum(1.0, np.abs(step) / speed)) * d
    return out


def _compiled(f: ca.Function) -> ca.Function:
    """`f` as machine code: its C source (CasADi code generation) compiled once by the
    system C compiler (`$CC`, else cc) into the cache, named by the source's hash, and loaded
    from there afterwards (about 10x faster than CasADi's virtual machine). `f` itself when
    no compiler is found, compiling fails or the cache cannot be written."""
    import hashlib
    import os
    import shutil
    import subprocess
    import tempfile

    from dexdrake.paths import cache_dir

    gen = ca.CodeGenerator(f"{f.name()}.c")
    gen.add(f)
    code = gen.dump()
    cc = shutil.which(os.environ.get("CC", "cc"))
    try:
        folder = cache_dir() / "casadi"
        lib = folder / f"{f.name()}_{hashlib.sha256(code.encode()).hexdigest()[:16]}.so"
        if not lib.exists():
            if cc is None:
                return f
            folder.mkdir(exist_ok=True)
            with tempfile.TemporaryDirectory(dir=folder) as tmp:
                src, out = Path(tmp) / "f.c", Path(tmp) / "f.so"
                src.write_text(code)
                if subprocess.run([cc, "-O1", "-fPIC", "-shared", str(src), "-o", str(out),
                                   "-lm"], capture_output=True).returncode != 0:
                    return f
                os.replace(out, lib)  # atomic: a concurrent build writes the same file
    except OSError:  # an unwritable cache
        return f
    return ca.external(f.name(), str(lib))


def _cholesky_solve(H: ca.SX, g: ca.SX) -> tuple[ca.SX, ca.SX]:
    """(H^-1 g, H positive definite) for a dense symmetric SX matrix, unrolled: the
    Cholesky factor, then forward and back substitution."""
    n = H.shape[0]
    L = [[ca.SX(0)] * n for _ in range(n)]
    ok = ca.SX(1)
    for j in range(n):
        s = H[j, j] - sum((L[j][k] * L[j][k] for k in range(j)), ca.SX(0))
        ok = ca.logic_and(ok, s > 0)
        L[j][j] = ca.sqrt(ca.fmax(s, 1e-300))
        for i in range(j + 1, n):
            L[i][j] = (H[i, j] - sum((L[i][k] * L[j][k] for k in range(j)), ca.SX(0))) / L[j][j]
    y = [ca.SX(0)] * n
    for i in range(n):
        y[i] = (g[i] - sum((L[i][k] * y[k] for k in range(i)), ca.SX(0))) / L[i][i]
    x = [ca.SX(0)] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - sum((L[k][i] * x[k] for k in range(i + 1, n)), ca.SX(0))) / L[i][i]
    return ca.vertcat(*x), ok


def _closest_point_fn(demo: HumanDemo, mesh):
    """closest(points_world, frame) -> (object surface points, outward normals) in the
    world, or None."""
    from dexdrake.demos.trim import SignedDistance, quat_wxyz_to_matrix

    if mesh is None and demo.object_name:
        try:
            import trimesh

            from dexdrake.objects.library import get_object

            mesh = trimesh.load(get_object(demo.object_name).mesh_path, force="mesh")
        except (ImportError, KeyError, AttributeError, OSError):
            mesh = None
    if mesh is None:
        return None
    sdf = SignedDistance(mesh.vertices, mesh.faces)
    Rs = quat_wxyz_to_matrix(demo.object_quat)

    def closest(p, t):
        R, x = Rs[t], demo.object_pos[t]
        c, n = sdf.closest_points_normals((p - x) @ R)
        return c @ R.T + x, n @ R.T

    return closest
