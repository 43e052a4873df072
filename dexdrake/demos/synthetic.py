"""A synthetic human grasp source: the kinematic hand of `human_hand` grasps and lifts an object.

Each demo: the open hand approaches the object from a seeded direction, each finger closes
along a straight line in joint space from the open pose towards a grasp-type closed pose and
stops at its first contact with the object or the table (found with signed-distance
queries, refined by bisection to 0.5 mm), the hand and object lift together by 8 cm, and the
sequence is trimmed and canonicalised as the paper does (see `trim`).
Grasp types: "top" (palm down), "side" (palm facing the object, thumb up), "pinch" (thumb
and index from above; offered for small objects).

Reachability: a robot arm reaches an object from a limited range of directions (the
Adroit's virtual arm turns at most 0.75 rad about the vertical). A demo can be made for one
episode placement (object yaw psi): with a world `heading` h, the hand's heading in the
object frame is h - psi plus a small spread, so that once the object is placed at psi the
human hand approaches along h in the world. The heading is the fingers' horizontal
direction for top/pinch grasps and the approach direction (palm normal) for side grasps.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

from dexdrake.demos import human_hand as hh
from dexdrake.demos.format import DemoMeta, HumanDemo
from dexdrake.demos.trim import SignedDistance, canonicalize, trim_demo
from dexdrake.eval.seeds import check_training_seeds

GRASP_TYPES = ("top", "side", "pinch")
_WRAP = np.array([[-0.45, 0.95, 0.6, 0.7]] + [[0.0, 1.5, 1.7, 1.2]] * 4)
_PINCH = np.array([[-0.45, 0.45, 0.45, 0.5], [0.0, 1.0, 1.0, 0.6], [0.0, 1.1, 1.1, 0.6],
                   [0.0, 1.5, 1.7, 1.2], [0.0, 1.5, 1.7, 1.2]])
_CLOSED = {"top": _WRAP, "side": _WRAP, "pinch": _PINCH}
# point between the fingers (hand frame) put on the object's grasp point before backing off;
# for top grasps 1.5 cm nearer the fingertips, so the palm sits back and the fingers reach
# over the object's far side (as a scripted robot grasp does)
_CENTRE = {"top": np.array([0.04, 0.0, 0.095]), "side": np.array([0.04, 0.0, 0.08]),
           "pinch": np.array([0.06, 0.03, 0.10])}
FPS = 60.0
CONTACT_TOL = 5e-4  # m, bisection tolerance on the contact closure
CLEARANCE = 0.003  # m, palm/finger clearance kept when placing the open hand
ADROIT_HEADING = np.pi / 2  # world +y: the Adroit arm's fingers point along it at rest
HEADING_SPREAD = 0.15  # rad, uniform spread of the hand heading around the requested one


@dataclass
class SyntheticGrasp:
    """What was generated, for inspection: hand pose, closure per finger, grasp type."""

    grasp: str
    R_WH: np.ndarray  # hand orientation in the world
    p_WH: np.ndarray  # wrist position in the world at grasp
    closure: np.ndarray  # (5,) fraction of the open->closed path reached per finger
    contacts: np.ndarray  # (5,) bool: the finger stopped on the object (not the table)


def grasp_types_for(mesh: trimesh.Trimesh) -> list[str]:
    """Grasp types that suit the object: pinch for small objects, side for tall ones."""
    ext = mesh.extents
    types = ["top"]
    if ext[2] >= 0.05:
        types.append("side")
    if max(ext[0], ext[1]) <= 0.08 or ext[2] <= 0.04:
        types.append("pinch")
    return types


def _hand_orientation(grasp: str, rng: np.random.Generator, heading: float | None = None
                      ) -> np.ndarray:
    """Hand frame in the object frame; `heading` (None: uniform) is the yaw of the fingers
    (top, pinch: z = (cos, sin, 0)) or of the palm normal (side: x = (cos, sin, 0))."""
    if heading is None:
        yaw = rng.uniform(-np.pi, np.pi)
    else:
        yaw = heading + rng.uniform(-HEADING_SPREAD, HEADING_SPREAD)
    tilt = rng.uniform(-0.25, 0.25, size=2)
    if grasp == "side":
        a = np.array([np.cos(yaw), np.sin(yaw), 0.0])  # palm normal = approach direction
        y = np.array([0.0, 0.0, 1.0])
    else:
        a = np.array([0.0, 0.0, -1.0])
        y = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    x = a + tilt[0] * np.cross(a, y) + tilt[1] * y
    x /= np.linalg.norm(x)
    y = y - x * (x @ y)
    y /= np.linalg.norm(y)
    return np.stack([x, y, np.cross(x, y)], axis=1)


class _Scene:
    """Signed distance to the object (at its resting pose) and to the table plane z = 0."""

    def __init__(self, mesh: trimesh.Trimesh, rest_height: float):
        self.sdf = SignedDistance(mesh.vertices, mesh.faces)
        self.offset = np.array([0.0, 0.0, rest_height])

    def clearance(self, pts_world: np.ndarray, radius: np.ndarray, table: bool = True
                  ) -> float:
        d = self.sdf(pts_world - self.offset)
        if table:
            d = np.minimum(d, pts_world[:, 2])
        return float(np.min(d - radius))


def _to_world(R, p, kp):
    return kp @ R.T + p


def _close_finger(scene: _Scene, R, p, f: int, open_a, closed_a) -> tuple[float, bool]:
    """Largest closure s in [0, 1] with the finger clear of object and table."""
    def clear(s: float) -> bool:
        k = _to_world(R, p, hh.finger_keypoints(f, open_a + s * (closed_a - open_a)))
        pts, rad = hh.finger_samples(k)
        return scene.clearance(pts, rad) >= 0.0

    lo, steps = 0.0, 40
    for i in range(1, steps + 1):
        s = i / steps
        if not clear(s):
            hi = s
            while (hi - lo) * 0.1 > CONTACT_TOL:  # ~10 cm of tip travel over the full path
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if clear(mid) else (lo, mid)
            k = _to_world(R, p, hh.finger_keypoints(f, open_a + lo * (closed_a - open_a)))
            pts, rad = hh.finger_samples(k)
            return lo, scene.clearance(pts, rad, table=False) < 2 * CONTACT_TOL
    return 1.0, False


def synthesize_grasp(mesh: trimesh.Trimesh, rest_height: float, grasp: str,
                     rng: np.random.Generator, attempts: int = 8,
                     heading: float | None = None) -> SyntheticGrasp:
    """Place the open hand against the object and close every finger onto it; retried with
    new random hand orientations (around `heading`, see `_hand_orientation`) until at least
    2 fingers touch the object (else the attempt with the most contacts is returned)."""
    best = None
    for _ in range(attempts):
        g = _attempt_grasp(mesh, rest_height, grasp, rng, heading)
        if best is None or g.contacts.sum() > best.contacts.sum():
            best = g
        if g.contacts.sum() >= 2:
            break
    return best


def _attempt_grasp(mesh: trimesh.Trimesh, rest_height: float, grasp: str,
                   rng: np.random.Generator, heading: float | None) -> SyntheticGrasp:
    if grasp not in GRASP_TYPES:
        raise ValueError(f"unknown grasp type {grasp!r}; valid: {', '.join(GRASP_TYPES)}")
    scene = _Scene(mesh, rest_height)
    R = _hand_orientation(grasp, rng, heading)
    target = scene.offset + rng.uniform(-0.01, 0.01, 3) * np.array([1, 1, 0])
    if grasp == "pinch":
        target = target + np.array([0, 0, 0.5 * mesh.extents[2] - 0.01])
    open_kp = hh.hand_keypoints(hh.OPEN_POSE)
    pts = [hh.palm_samples(open_kp)] + [hh.finger_samples(open_kp[1 + 4 * f: 5 + 4 * f])
                                        for f in range(5)]
    P = np.concatenate([a for a, _ in pts])
    rad = np.concatenate([r for _, r in pts]) + CLEARANCE
    p = target - R @ _CENTRE[grasp]
    back = -R[:, 0]  # away from the palm side
    for _ in range(200):
        low = float(np.min(_to_world(R, p, P)[:, 2] - rad))
        p[2] += max(0.0, -low)  # keep the open hand above the table
        if scene.clearance(_to_world(R, p, P), rad) >= 0:
            break
        p = p + 0.002 * back
    else:
        raise RuntimeError("could not place the open hand clear of the object")
    closed = _CLOSED[grasp]
    res = [_close_finger(scene, R, p, f, hh.OPEN_POSE[f], closed[f]) for f in range(5)]
    return SyntheticGrasp(grasp, R, p, np.array([s for s, _ in res]),
                          np.array([c for _, c in res]))


def _smooth(n: int) -> np.ndarray:
    t = np.linspace(0, 1, n)
    return 10 * t**3 - 15 * t**4 + 6 * t**5  # min-jerk profile


def demo_from_grasp(g: SyntheticGrasp, mesh: trimesh.Trimesh, rest_height: float,
                    object_name: str, fps: float = FPS, approach: float = 0.25,
                    lift: float = 0.08) -> HumanDemo:
    """The full (untrimmed) sequence: approach, close, lift."""
    n_app, n_close, n_hold, n_lift = int(1.6 * fps), int(0.6 * fps), int(0.1 * fps), int(fps)
    open_pose, closed = hh.OPEN_POSE, _CLOSED[g.grasp]
    final = open_pose + g.closure[:, None] * (closed - open_pose)
    back = -g.R_WH[:, 0]
    frames, obj_z = [], []
    for s in _smooth(n_app):
        frames.append((g.p_WH + (1 - s) * approach * back, open_pose, 0.0))
    for s in _smooth(n_close)[1:]:
        frames.append((g.p_WH, open_pose + s * (final - open_pose), 0.0))
    frames += [(g.p_WH, final, 0.0)] * n_hold
    for s in _smooth(n_lift)[1:]:
        frames.append((g.p_WH + [0, 0, lift * s], final, lift * s))
    kp = np.stack([_to_world(g.R_WH, p, hh.hand_keypoints(pose)) for p, pose, _ in frames])
    obj_z = np.array([dz for _, _, dz in frames])
    T = len(frames)
    pos = np.zeros((T, 3))
    pos[:, 2] = rest_height + obj_z
    quat = np.tile([1.0, 0, 0, 0], (T, 1))
    meta = DemoMeta(subject="synthetic-adult-right", fps=fps, source="synthetic",
                    extra={"grasp": g.grasp, "closure": g.closure.round(4).tolist(),
                           "contacts": g.contacts.tolist()})
    return HumanDemo(kp, np.arange(T) / fps, object_name, pos, quat, meta)


def synthesize_demo(mesh: trimesh.Trimesh, object_name: str, grasp: str, seed: int,
                    rest_height: float | None = None, heading: float | None = None
                    ) -> HumanDemo:
    """One trimmed, canonical demo of `grasp` on `mesh` (object frame, origin at the COM);
    `heading`: the hand's heading in the object frame (None: uniform)."""
    rng = np.random.default_rng(seed)
    h = float(-mesh.bounds[0, 2]) if rest_height is None else rest_height
    g = synthesize_grasp(mesh, h, grasp, rng, heading=heading)
    demo = demo_from_grasp(g, mesh, h, object_name)
    demo.meta.extra["seed"] = seed
    demo = trim_demo(demo, SignedDistance(mesh.vertices, mesh.faces))
    return canonicalize(demo, rest_height=h)


def synthesize_object_demos(object_name: str, count: int, seed: int = 0,
                            heading: float | None = ADROIT_HEADING,
                            placement_yaw: Callable[[int], float] | None = None) -> list[HumanDemo]:
    """`count` demos of a library object.

    With a world `heading` (default: the Adroit's), demo i is made for the replay episode
    whose seed is its own seed (seed * 1000 + i): the hand heads along `heading` in the
    world once the object is placed at that episode's yaw, `placement_yaw(episode_seed)`
    (the replay's placement rule, passed in by the caller); meta.extra records
    "episode_seed" and "placement_yaw", and the grasp types are the palm-down ones (top,
    and pinch for small objects), which a hand on an arm reaching from above can make.
    With heading None: uniform headings, cycling over every grasp type that suits the object.
    """
    from dexdrake.objects.library import get_object

    if heading is not None and placement_yaw is None:
        raise ValueError("synthesize_object_demos: a world heading needs placement_yaw")
    check_training_seeds([seed * 1000 + count - 1], "demo episode seeds (seed * 1000 + i)")
    info = get_object(object_name)
    mesh = trimesh.load(info.mesh_path, force="mesh")
    types = grasp_types_for(mesh)
    if heading is not None:
        types = [t for t in types if t != "side"]
    demos = []
    for i in range(count):
        s, psi = seed * 1000 + i, None
        if heading is not None:
            psi = float(placement_yaw(s))
        demo = synthesize_demo(mesh, object_name, types[i % len(types)], s,
                               rest_height=float(info.rest_height),
                               heading=None if psi is None else heading - psi)
        if psi is not None:
            demo.meta.extra.update(episode_seed=s, placement_yaw=round(psi, 6),
                                   world_heading=round(float(heading), 6))
        demos.append(demo)
    return demos
