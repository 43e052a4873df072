"""The DexRepNet paper's success rates, the numbers our tables set beside their own."""

from __future__ import annotations

# DexRepNet Table I, success % of DexRep on unseen GRAB objects, keyed by the library's procedural
# namesakes (the near split): a namesake is not the scanned GRAB object.
PAPER_UNSEEN: dict[str, float] = {
    "mug": 100.0,
    "camera": 99.0,
    "binoculars": 97.3,
    "apple": 100.0,
    "toothpaste": 94.0,
    "frying_pan": 81.3,
    "toothbrush": 64.0,
    "elephant": 100.0,
    "hand": 100.0,
    "pyramid_small": 3.3,
}
PAPER_AVERAGE: dict[str, float] = {"seen": 93.0, "unseen": 83.9}
# Ablations on the 10 unseen GRAB objects (average success %).
PAPER_ABLATIONS: dict[str, float] = {
    "Hand2obj": 23.8,
    "pGlo": 32.1,
    "Loc-Geo": 68.0,
    "Surf": 53.3,
    "Occ+Surf": 63.2,
    "Occ+Surf+pGlo": 64.2,
    "DexRep+pGlo": 76.2,
    "DexRep": 83.9,
}
# Table II: success % on the unseen GRAB objects of hands with fewer fingers, per feature set
# (fingers -> {feature set: success %}).
PAPER_FEWER_FINGERS: dict[int, dict[str, float]] = {
    2: {"Hand2obj": 9.0, "pGlo": 38.3, "DexRep": 68.8},
    3: {"Hand2obj": 17.9, "pGlo": 56.4, "DexRep": 81.8},
    4: {"Hand2obj": 0.0, "pGlo": 18.6, "DexRep": 83.9},
}
