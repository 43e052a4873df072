"""DAPG's demo-weight term and the NPG maths beyond test_learn.py (mutation testing found these
unchecked; see scripts/mutation.py)."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from dexdrake.errors import DexdrakeError
from dexdrake.learn.dapg import DAPGConfig, demo_weight
from dexdrake.learn.npg import (conjugate_gradient, fisher_vector_product, flat_grad, flat_params, gaussian_kl,
                                set_flat_params)
from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig


def test_demo_weight_scales_with_the_largest_advantage():
    cfg = replace(DAPGConfig(), lam0=0.2, lam1=0.9, max_adv=4.0)
    assert demo_weight(cfg, 0) == pytest.approx(0.2 * 4.0)
    assert demo_weight(cfg, 3) == pytest.approx(0.2 * 0.9**3 * 4.0)


def _tiny_policy() -> DexRepNetPolicy:
    torch.manual_seed(3)
    config = PolicyConfig.from_blocks({"a": 3, "b": 2}, 2, feature_set="toy", hand="toy", hidden_sizes=(6,),
                                      encoder_dim=3)
    return DexRepNetPolicy(config)


def test_gaussian_kl_is_the_closed_form():
    rng = np.random.default_rng(0)
    m0, m1, s0, s1 = (rng.normal(size=(4, 3)) for _ in range(4))
    want = np.mean(np.sum(s1 - s0 + (np.exp(2 * s0) + (m0 - m1) ** 2) / (2 * np.exp(2 * s1)) - 0.5, axis=-1))
    got = gaussian_kl(*(torch.as_tensor(x) for x in (m0, s0, m1, s1)))
    assert float(got) == pytest.approx(want, rel=1e-12)
    assert float(gaussian_kl(*(torch.as_tensor(x) for x in (m0, s0, m0, s0)))) == pytest.approx(0.0, abs=1e-12)


def test_flat_grad_fills_unused_parameters_with_zeros_and_frees_the_graph():
    used, unused = torch.nn.Parameter(torch.tensor([1.0, 2.0])), torch.nn.Parameter(torch.ones(2, 2))
    out = (used**2).sum()
    g = flat_grad(out, [used, unused])
    assert g.tolist() == [2.0, 4.0, 0.0, 0.0, 0.0, 0.0] and not g.requires_grad
    with pytest.raises(RuntimeError):  # the graph is freed unless asked to keep it
        flat_grad(out, [used, unused])


def test_conjugate_gradient_stops_at_its_iteration_count_and_tolerance():
    eig = torch.linspace(1.0, 50.0, 12, dtype=torch.float64)  # 12 distinct eigenvalues: 12 steps to converge
    b = torch.ones(12, dtype=torch.float64)
    ten = conjugate_gradient(lambda v: eig * v, b)
    assert torch.equal(ten, conjugate_gradient(lambda v: eig * v, b, iters=10))
    assert not torch.allclose(ten, conjugate_gradient(lambda v: eig * v, b, iters=11), atol=1e-9)
    assert torch.allclose(conjugate_gradient(lambda v: eig * v, b, iters=12), b / eig, atol=1e-9)
    # A residual exactly at the tolerance is converged already.
    at_tol = conjugate_gradient(lambda v: eig * v, torch.tensor([1.0] + [0.0] * 11, dtype=torch.float64),
                                residual_tol=1.0)
    assert torch.count_nonzero(at_tol) == 0


def test_fisher_vector_product_is_linear_reusable_and_damped_by_default():
    policy, obs = _tiny_policy(), torch.randn(6, 5)
    matvec, undamped = fisher_vector_product(policy, obs), fisher_vector_product(policy, obs, damping=0.0)
    n = sum(p.numel() for p in policy.trainable_parameters())
    a, b = torch.randn(n), torch.randn(n)
    assert torch.allclose(matvec(a + b), matvec(a) + matvec(b), atol=1e-5)  # the graph survives repeated calls
    assert torch.allclose(matvec(a) - undamped(a), 1e-4 * a, atol=1e-7)


def test_flat_params_round_trip_in_order_and_refuse_a_wrong_size():
    params = [torch.nn.Parameter(torch.tensor([1.0, 2.0])), torch.nn.Parameter(torch.tensor([[3.0], [4.0]])),
              torch.nn.Parameter(torch.tensor([0.5]))]
    assert flat_params(params).tolist() == [1.0, 2.0, 3.0, 4.0, 0.5]
    set_flat_params(params, torch.tensor([5.0, 6.0, 7.0, 8.0, 9.0]))
    assert [p.tolist() for p in params] == [[5.0, 6.0], [[7.0], [8.0]], [9.0]]
    with pytest.raises(DexdrakeError, match="flat vector has 3 entries, parameters need 5"):
        set_flat_params(params, torch.zeros(3))
