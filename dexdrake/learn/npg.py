"""Natural policy gradient pieces: flat parameters, Fisher-vector products, CG, the step.

The Fisher matrix F is the Hessian of the mean KL(pi_old || pi_theta) at theta = theta_old,
applied to a vector by double back-propagation (never formed). The step solves F x = g by
conjugate gradient and takes theta += alpha x with alpha = sqrt(delta / (g^T F^-1 g)), as
mjrl's NPG does with its "normalised step size" delta. The KL's quadratic model is then
KL ~ 1/2 dtheta^T F dtheta = 1/2 alpha^2 g^T F^-1 g = delta / 2: the target KL is delta / 2.
Because the quadratic model can be far off (far from a BC optimum, or with a nearly singular
F), the step measures the real KL afterwards and halves alpha while it exceeds
`max_kl_ratio` times the target (a backtracking safeguard; the step is undone if no
halving helps). The log-std parameter is clamped into its bounds after every trial step.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import nn

from dexdrake.errors import DexdrakeError
from dexdrake.learn.policy import DexRepNetPolicy


def flat_params(params: Sequence[nn.Parameter]) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in params])


def set_flat_params(params: Sequence[nn.Parameter], flat: torch.Tensor) -> None:
    """Write a flat vector back into `params` (in order)."""
    total = sum(p.numel() for p in params)
    if flat.numel() != total:
        raise DexdrakeError(f"flat vector has {flat.numel()} entries, parameters need {total}")
    offset = 0
    with torch.no_grad():
        for p in params:
            p.copy_(flat[offset : offset + p.numel()].view_as(p))
            offset += p.numel()


def flat_grad(
    output: torch.Tensor, params: Sequence[nn.Parameter], create_graph: bool = False, retain_graph: bool = False
) -> torch.Tensor:
    """d output / d params as one flat vector (zeros for parameters output does not use)."""
    grads = torch.autograd.grad(
        output, list(params), create_graph=create_graph, retain_graph=retain_graph or create_graph, allow_unused=True
    )
    return torch.cat([(torch.zeros_like(p) if g is None else g).reshape(-1) for g, p in zip(grads, params)])


def conjugate_gradient(
    matvec: Callable[[torch.Tensor], torch.Tensor], b: torch.Tensor, iters: int = 10, residual_tol: float = 1e-10
) -> torch.Tensor:
    """Approximately solve A x = b for symmetric positive-definite A given only x -> A x."""
    x = torch.zeros_like(b)
    r = b.clone()
    p = b.clone()
    rr = torch.dot(r, r)
    for _ in range(iters):
        if rr <= residual_tol:
            break
        ap = matvec(p)
        alpha = rr / torch.dot(p, ap)
        x += alpha * p
        r -= alpha * ap
        rr_new = torch.dot(r, r)
        p = r + (rr_new / rr) * p
        rr = rr_new
    return x


def gaussian_kl(
    mean_old: torch.Tensor, log_std_old: torch.Tensor, mean_new: torch.Tensor, log_std_new: torch.Tensor
) -> torch.Tensor:
    """Mean over samples of KL(N_old || N_new) for diagonal Gaussians."""
    var_old, var_new = torch.exp(2 * log_std_old), torch.exp(2 * log_std_new)
    kl = log_std_new - log_std_old + (var_old + (mean_old - mean_new) ** 2) / (2 * var_new) - 0.5
    return kl.sum(-1).mean()


def policy_kl(policy: DexRepNetPolicy, obs: torch.Tensor, mean_old: torch.Tensor, log_std_old: torch.Tensor) -> torch.Tensor:
    return gaussian_kl(mean_old, log_std_old, policy(obs), policy.clamped_log_std())


def fisher_vector_product(
    policy: DexRepNetPolicy, obs: torch.Tensor, damping: float = 1e-4
) -> Callable[[torch.Tensor], torch.Tensor]:
    """v -> (F + damping I) v for the policy's trainable parameters at `obs`."""
    params = list(policy.trainable_parameters())
    with torch.no_grad():
        mean_old, log_std_old = policy(obs), policy.clamped_log_std()
    kl = policy_kl(policy, obs, mean_old, log_std_old)
    grad_kl = flat_grad(kl, params, create_graph=True)

    def matvec(v: torch.Tensor) -> torch.Tensor:
        fv = flat_grad(torch.dot(grad_kl, v), params, retain_graph=True)
        return fv + damping * v

    return matvec


@dataclass(frozen=True)
class NPGStep:
    alpha: float  # step length applied to the natural gradient (0 when the step was undone)
    grad_norm: float
    natural_grad_dot: float  # g^T F^-1 g
    step_norm: float
    kl: float  # measured mean KL(pi_old || pi_new) after the step
    kl_target: float  # step_size / 2, the quadratic model's KL for the full step
    backtracks: int  # halvings of alpha applied


def natural_gradient_step(
    policy: DexRepNetPolicy,
    grad: torch.Tensor,
    fisher_obs: torch.Tensor,
    step_size: float = 0.05,
    cg_iters: int = 10,
    damping: float = 1e-4,
    kl_obs: torch.Tensor | None = None,
    max_kl_ratio: float = 1.5,
    max_backtracks: int = 10,
) -> NPGStep:
    """Ascend `grad` (flat, over trainable parameters) along the natural gradient in place.

    The KL is measured on `kl_obs` (default `fisher_obs`); alpha is halved up to
    `max_backtracks` times while it exceeds max_kl_ratio * step_size / 2.
    """
    params = list(policy.trainable_parameters())
    if not params:
        raise DexdrakeError("policy has no trainable parameters")
    if step_size <= 0 or max_kl_ratio < 1 or max_backtracks < 0:
        raise DexdrakeError(f"need step_size > 0, max_kl_ratio >= 1, max_backtracks >= 0 "
                            f"(got {step_size}, {max_kl_ratio}, {max_backtracks})")
    kl_obs = fisher_obs if kl_obs is None else kl_obs
    policy.clamp_log_std_()
    with torch.no_grad():
        mean_old, log_std_old = policy(kl_obs), policy.clamped_log_std().clone()
    matvec = fisher_vector_product(policy, fisher_obs, damping)
    nat = conjugate_gradient(matvec, grad, iters=cg_iters)
    ngd = float(torch.dot(grad, nat))
    theta_old = flat_params(params)
    kl_target = step_size / 2
    alpha = (step_size / (abs(ngd) + 1e-20)) ** 0.5
    backtracks = 0
    while True:
        set_flat_params(params, theta_old + alpha * nat)
        policy.clamp_log_std_()
        with torch.no_grad():
            kl = float(policy_kl(policy, kl_obs, mean_old, log_std_old))
        if math.isfinite(kl) and kl <= max_kl_ratio * kl_target:
            break
        if backtracks == max_backtracks:  # no halving helped: undo the step
            set_flat_params(params, theta_old)
            alpha, kl = 0.0, 0.0
            break
        alpha *= 0.5
        backtracks += 1
    step_norm = float((flat_params(params) - theta_old).norm())
    return NPGStep(alpha=alpha, grad_norm=float(grad.norm()), natural_grad_dot=ngd, step_norm=step_norm, kl=kl,
                   kl_target=kl_target, backtracks=backtracks)
