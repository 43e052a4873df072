"""Retargeting configs: which robot frames stand for which human keypoints, scales, weights.

One YAML file per hand in `dexdrake/retarget/configs/<hand>.yaml`:

    hand: allegro
    wrist: {body: palm_link, offset: [0, 0, -0.095]}   # robot point for human keypoint 0
    fingers:                                             # any subset of thumb..little
      thumb: {tip: {fingertip: thtip}, base: {body: link_14.0}}
      index: {tip: {body: link_3.0_tip, offset: [0, 0, 0]}, base: {body: link_1.0}}
    palm: {out: 0.051, along: 0.72}                     # optional palm grasp-centre term
    scales: {wrist: auto, finger: auto, object: 1.0}    # k_i; auto = robot/human length
    weights: {wrist: 1.0, base: 1.0, finger: 1.0, thumb: 1.0, object: 1.0,
              object_decay: 0.03, object_contact: 0.012, object_depth: 0.0, palm: 1.0,
              wrist_position: 0.05, smooth: 4.0e-3}   # base, thumb: x wrist, x finger
    pinch: {eps_enter: 0.03, eps_leave: 0.05, eta1: 1.0e-4, eta2: 0.03, s1: 200, s2: 400}
    solver: {iterations: 10, first_iterations: 80, damping: 1.0e-6, filter: 1.0,
             filter_speed: .inf}

A point is `{fingertip: NAME}` (a fingertip of the hand description) or
`{body: BODY, offset: [x, y, z]}`; `human:` overrides the human keypoint it matches
(defaults: tip 4/8/12/16/20, base 2/5/9/13/17 for thumb/index/middle/ring/little).

`palm` (optional) adds a term that puts a robot palm point (default: the hand
description's grasp centre; override with body/offset) where the human's palm centre is:
`out` m out of the human palm plane (wrist, index and little MCPs) along its normal, at
`along` of the way from the wrist to the middle MCP (see `human_hand.palm_centre`).
`solver.filter` low-passes the output trajectory (alpha, 1 = off), adaptively when
`solver.filter_speed` (rad/frame) is finite: joints moving that fast are not filtered
(`retargeter.low_pass`).
Finger-to-object targets move `object_depth` inside the object's surface when the human
fingertip is within `object_contact` of it (fading out at twice that), so the position
servos squeeze the object instead of stopping at its surface.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from dexdrake.errors import DexdrakeError, UnknownNameError
from dexdrake.hands.description import HandDescription

FINGER_NAMES = ("thumb", "index", "middle", "ring", "little")
HUMAN_TIP = {"thumb": 4, "index": 8, "middle": 12, "ring": 16, "little": 20}
HUMAN_BASE = {"thumb": 2, "index": 5, "middle": 9, "ring": 13, "little": 17}
CONFIG_DIR = Path(__file__).parent / "configs"


@dataclass(frozen=True)
class RobotPoint:
    name: str
    body: str
    offset: tuple[float, float, float]
    human: int  # index of the matching human keypoint (MediaPipe order)


@dataclass(frozen=True)
class PinchParams:
    eps_enter: float = 0.03
    eps_leave: float = 0.05
    eta1: float = 1e-4
    eta2: float = 0.03
    s1: float = 200.0
    s2: float = 400.0


@dataclass(frozen=True)
class PalmTerm:
    point: RobotPoint  # robot palm point (its `human` field is unused: -1)
    out: float = 0.051  # m out of the human palm plane
    along: float = 0.72  # fraction of the wrist -> middle MCP segment


@dataclass(frozen=True)
class RetargetConfig:
    hand: str
    wrist: RobotPoint
    fingers: tuple[str, ...]  # in FINGER_NAMES order
    tips: tuple[RobotPoint, ...]
    bases: tuple[RobotPoint, ...]
    scales: dict[str, float | str] = field(default_factory=dict)
    weights: dict[str, float] = field(default_factory=dict)
    pinch: PinchParams = PinchParams()
    palm: PalmTerm | None = None
    iterations: int = 10
    first_iterations: int = 80
    damping: float = 1e-6
    filter: float = 1.0  # output low-pass alpha (1: none); see retargeter.low_pass
    filter_speed: float = np.inf  # rad/frame at which the low-pass lets a joint through

    def weight(self, key: str) -> float:
        return float(self.weights.get(key, _DEFAULT_WEIGHTS[key]))

    def scale(self, key: str) -> float | str:
        return self.scales.get(key, "auto" if key != "object" else 1.0)


_DEFAULT_WEIGHTS = {"wrist": 1.0, "base": 1.0, "finger": 1.0, "thumb": 1.0, "object": 1.0,
                    "object_decay": 0.03, "object_contact": 0.012, "object_depth": 0.0,
                    "palm": 1.0, "wrist_position": 0.05, "smooth": 4e-3}


def _point(hand: HandDescription, name: str, d: dict, human: int) -> RobotPoint:
    if not isinstance(d, dict):
        raise DexdrakeError(f"retarget config {hand.name}: {name} must be a mapping")
    if "fingertip" in d:
        tips = {t.name: t for t in hand.fingertips}
        if d["fingertip"] not in tips:
            raise UnknownNameError(f"fingertip of hand {hand.name}", d["fingertip"], tips)
        t = tips[d["fingertip"]]
        body, offset = t.body, t.offset
    elif "body" in d:
        body, offset = d["body"], tuple(float(x) for x in d.get("offset", (0, 0, 0)))
    else:
        raise DexdrakeError(f"retarget config {hand.name}: {name} needs 'fingertip' or 'body'")
    return RobotPoint(name, body, tuple(offset), int(d.get("human", human)))


def _palm(hand: HandDescription, d: dict) -> PalmTerm:
    if not isinstance(d, dict):
        raise DexdrakeError(f"retarget config {hand.name}: palm must be a mapping")
    spec = {k: d[k] for k in ("body", "offset") if k in d} or {
        "body": hand.palm.body, "offset": list(hand.palm.centre)}
    return PalmTerm(_point(hand, "palm", spec, -1), float(d.get("out", 0.051)),
                    float(d.get("along", 0.72)))


def config_from_dict(hand: HandDescription, d: dict) -> RetargetConfig:
    """Build a RetargetConfig from its YAML mapping, checking names against the hand."""
    fingers = d.get("fingers") or {}
    unknown = [f for f in fingers if f not in FINGER_NAMES]
    if unknown or "thumb" not in fingers:
        raise DexdrakeError(f"retarget config {hand.name}: fingers must include thumb and be "
                            f"among {FINGER_NAMES}; got {list(fingers)}")
    order = tuple(f for f in FINGER_NAMES if f in fingers)
    tips = tuple(_point(hand, f"{f}.tip", fingers[f]["tip"], HUMAN_TIP[f]) for f in order)
    bases = tuple(_point(hand, f"{f}.base", fingers[f]["base"], HUMAN_BASE[f]) for f in order)
    wrist = _point(hand, "wrist", d.get("wrist") or {"body": hand.wrist_body}, 0)
    s = d.get("solver") or {}
    unknown = sorted(set(d.get("weights") or {}) - set(_DEFAULT_WEIGHTS))
    if unknown:
        raise DexdrakeError(f"retarget config {hand.name}: unknown weights {unknown}; "
                            f"valid: {sorted(_DEFAULT_WEIGHTS)}")
    return RetargetConfig(
        hand=hand.name, wrist=wrist, fingers=order, tips=tips, bases=bases,
        scales=dict(d.get("scales") or {}), weights=dict(d.get("weights") or {}),
        pinch=PinchParams(**(d.get("pinch") or {})),
        palm=_palm(hand, d["palm"]) if d.get("palm") is not None else None,
        iterations=_number(hand, "solver.iterations", s.get("iterations", 10), int),
        first_iterations=_number(hand, "solver.first_iterations", s.get("first_iterations", 80), int),
        damping=_number(hand, "solver.damping", s.get("damping", 1e-6)),
        filter=_alpha(hand, s.get("filter", 1.0)),
        filter_speed=_speed(hand, s.get("filter_speed", np.inf)),
    )


def _number(hand: HandDescription, field: str, value, kind: type = float) -> float:
    """`value` as a `kind` (float or int); else one line naming the field."""
    try:
        return kind(value)
    except (TypeError, ValueError):
        raise DexdrakeError(f"retarget config {hand.name}: {field} must be "
                            f"{'an integer' if kind is int else 'a number'}, got {value!r}") from None


def _alpha(hand: HandDescription, value) -> float:
    alpha = _number(hand, "solver.filter", value)
    if not 0.0 < alpha <= 1.0:
        raise DexdrakeError(f"retarget config {hand.name}: solver.filter must be in (0, 1], got {value!r}")
    return alpha


def _speed(hand: HandDescription, value) -> float:
    speed = _number(hand, "solver.filter_speed", value)
    if not speed > 0.0:
        raise DexdrakeError(f"retarget config {hand.name}: solver.filter_speed must be a "
                            f"positive number of rad/frame, got {value!r}")
    return speed


def load_config(hand: HandDescription, config: str | Path | dict | None = None
                ) -> RetargetConfig:
    """The config for `hand`: a mapping, a YAML path, or (None) the shipped configs/<hand>.yaml."""
    if isinstance(config, dict):
        return config_from_dict(hand, config)
    path = Path(config) if config is not None else CONFIG_DIR / f"{hand.name}.yaml"
    if not path.is_file():
        shipped = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))
        raise DexdrakeError(f"no retarget config {path} (shipped: {', '.join(shipped)}); "
                            "see dexdrake/retarget/config.py for the schema")
    return config_from_dict(hand, yaml.safe_load(path.read_text()))


def auto_scale(robot_len: np.ndarray, human_len: np.ndarray) -> np.ndarray:
    """Per-vector scale k = robot length / human length (human lengths floored at 1 cm)."""
    return np.asarray(robot_len) / np.maximum(np.asarray(human_len), 0.01)
