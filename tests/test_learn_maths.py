"""DAPG's demo-weight term and the NPG maths beyond test_learn.py (mutation testing found these
unchecked; see scripts/mutation.py)."""

from dataclasses import replace

import pytest

from dexdrake.learn.dapg import DAPGConfig, demo_weight


def test_demo_weight_scales_with_the_largest_advantage():
    cfg = replace(DAPGConfig(), lam0=0.2, lam1=0.9, max_adv=4.0)
    assert demo_weight(cfg, 0) == pytest.approx(0.2 * 4.0)
    assert demo_weight(cfg, 3) == pytest.approx(0.2 * 0.9**3 * 4.0)
