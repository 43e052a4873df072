"""The arm's inverse kinematics: arm joint positions that put the palm's grasp centre (hand
description `palm.centre`) at a point, optionally with the palm near a rotation, on a
private context of the scene's plant (the fingers stay at their default positions)."""

from __future__ import annotations

import numpy as np
from pydrake.math import RotationMatrix
from pydrake.multibody.tree import JacobianWrtVariable


class ArmIK:
    """IK over the arm joints of `scene` (a GraspScene or a HandKinematics). Rotation errors are weighted by
    `orientation_weight` (m per unit: position wins); `damping` (m) damps `step`."""

    def __init__(self, scene, orientation_weight: float = 0.01, damping: float = 1e-3):
        hand = scene.hand
        self.plant, self.ctx = scene.plant, scene.plant.CreateDefaultContext()
        self.palm_frame = self.plant.GetFrameByName(hand.palm.body, scene.hand_instance)
        self.world = self.plant.world_frame()
        self.centre = np.array(hand.palm.centre)
        self.n_arm = len(hand.arm_joints)
        self.index = scene.q_index[: self.n_arm]
        lo, hi = hand.joint_limits()
        self.lo, self.hi = lo[: self.n_arm], hi[: self.n_arm]
        self.orientation_weight, self.damping = orientation_weight, damping
        self._w = np.r_[np.full(3, orientation_weight), np.ones(3)]  # `step`'s weights: rotation (m per rad), position
        self._damped_eye = damping**2 * np.eye(self.n_arm)
        self._q = self.plant.GetPositions(self.ctx)  # the private context's positions
        self._q_arm: np.ndarray | None = None  # the arm positions the private context holds

    def _set_arm(self, q_arm: np.ndarray):
        """Puts the arm of the private context at q_arm; returns the palm body's pose in the world.
        Positions equal to those it holds are not set again, so the context's kinematics stay
        cached (a residual and its Jacobian, or the label's palm pose and the lift's first step,
        evaluate them once)."""
        if self._q_arm is None or not (self._q_arm == q_arm).all():
            self._q[self.index] = q_arm
            self.plant.SetPositions(self.ctx, self._q)
            self._q_arm = np.array(q_arm, dtype=float)
        return self.palm_frame.CalcPoseInWorld(self.ctx)

    def palm_pose(self, q_arm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Grasp-centre position and palm rotation in the world for arm positions q_arm."""
        X = self._set_arm(q_arm)
        return X.multiply(self.centre), X.rotation().matrix()

    def solve(self, target: np.ndarray, q_seed: np.ndarray, R_target: np.ndarray | None = None,
              stay: float = 0.0) -> np.ndarray:
        """Arm positions that put the grasp centre at `target`, with the palm rotation near
        `R_target` (when given) and, weighted by `stay` (m per rad), near q_seed: bounded
        Levenberg-Marquardt on `residual` with its analytic `residual_jacobian`, from q_seed
        (cheaper than scipy's least_squares with finite differences for the same solutions:
        scripts/bench_arm_ik.py measures both)."""
        seed = np.clip(q_seed, self.lo, self.hi)
        margin = 1e-3 * (self.hi - self.lo)  # start strictly inside the bounds
        q = np.clip(seed, self.lo + margin, self.hi - margin)
        args = (target, R_target, stay, seed)
        r = self.residual(q, *args)
        cost, mu = r @ r, 1e-4  # mu: the Levenberg-Marquardt damping
        for _ in range(200):  # (it converges in about ten)
            J = self.residual_jacobian(q, *args)
            descent = -J.T @ r  # joints on a limit that descent pushes outward stay; the step is projected
            free = ~(((q <= self.lo) & (descent < 0)) | ((q >= self.hi) & (descent > 0)))
            Jf = J[:, free]
            JtJ, Jtr, eye = Jf.T @ Jf, -Jf.T @ r, np.eye(int(free.sum()))
            while True:  # damp more until the step lowers the cost
                dq = np.zeros_like(q)
                dq[free] = np.linalg.solve(JtJ + mu * eye, Jtr)
                q_new = np.minimum(np.maximum(q + dq, self.lo), self.hi)
                r_new = self.residual(q_new, *args)
                cost_new = r_new @ r_new
                if cost_new <= cost:
                    mu = max(mu / 3, 1e-12)
                    break
                mu *= 4
                if mu > 1e6:  # no step lowers the cost: a minimum
                    return q
            moved, gain = float(np.abs(q_new - q).max()), cost - cost_new
            q, r, cost = q_new, r_new, cost_new
            if moved < 1e-10 or gain <= 1e-16 * cost:
                break
        return q

    def residual(self, q_arm: np.ndarray, target: np.ndarray, R_target: np.ndarray | None, stay: float,
                 seed: np.ndarray) -> np.ndarray:
        """`solve`'s residual: the grasp centre's offset from target; the weighted difference
        of the palm rotation's last two columns from R_target's; stay * (q_arm - seed)."""
        p, R = self.palm_pose(q_arm)
        parts = [p - target]
        if R_target is not None:
            parts.append(self.orientation_weight * (R - R_target)[:, 1:].ravel())
        if stay:
            parts.append(stay * (q_arm - seed))
        return np.concatenate(parts)

    def residual_jacobian(self, q_arm: np.ndarray, target: np.ndarray, R_target: np.ndarray | None, stay: float,
                          seed: np.ndarray) -> np.ndarray:
        """d residual / d q_arm, analytic: a rotation column r turns as w_k x r, w_k joint k's
        angular Jacobian column."""
        X = self._set_arm(q_arm)
        Jw, Jv = self._jacobian()
        rows = [Jv]
        if R_target is not None:
            R = X.rotation().matrix()
            turn = np.stack([_skew(R[:, j]).T @ Jw for j in (1, 2)], axis=1)  # [i, j, k]: (w_k x r_j)_i
            rows.append(self.orientation_weight * turn.reshape(6, self.n_arm))
        if stay:
            rows.append(stay * np.eye(self.n_arm))
        return np.vstack(rows)

    def _jacobian(self) -> tuple[np.ndarray, np.ndarray]:
        """The grasp centre's angular and translational Jacobians (3 x n_arm each, world frame)
        at the private context's arm positions."""
        J = self._spatial_jacobian()
        return J[:3], J[3:]

    def _spatial_jacobian(self) -> np.ndarray:
        """The grasp centre's spatial Jacobian (6 x n_arm: angular rows, then translational)."""
        return self.plant.CalcJacobianSpatialVelocity(
            self.ctx, JacobianWrtVariable.kQDot, self.palm_frame, self.centre, self.world, self.world
        )[:, self.index]

    def step(self, target: np.ndarray, R_target: np.ndarray, q_arm: np.ndarray, steps: int,
             tol: float = 0.0) -> np.ndarray:
        """`solve` near q_arm, cheaply: up to `steps` damped least-squares steps on the grasp
        centre's spatial Jacobian from q_arm (the same weighting), stopping once the weighted
        pose error is below `tol`; joints a step would push past a limit stay on it and the
        others take the step."""
        w, lo, hi = self._w, self.lo, self.hi
        q = np.minimum(np.maximum(q_arm, lo), hi)
        for _ in range(steps):
            X = self._set_arm(q)
            rotation = RotationMatrix(R_target @ X.rotation().matrix().T).ToAngleAxis()
            error = w * np.concatenate([rotation.angle() * rotation.axis(), target - X.multiply(self.centre)])
            if error @ error < tol * tol:
                break
            J = w[:, None] * self._spatial_jacobian()
            dq = np.linalg.solve(J.T @ J + self._damped_eye, J.T @ error)
            if ((q + dq < lo) | (q + dq > hi)).any():
                dq = self._held_step(J, error, q)
            q = np.minimum(np.maximum(q + dq, lo), hi)
        return q

    def _held_step(self, J: np.ndarray, error: np.ndarray, q: np.ndarray) -> np.ndarray:
        """`step`'s damped least-squares step with the joints it would push past a limit held,
        repeated until none is (the last step's, if every joint ends held)."""
        free, dq = np.ones(self.n_arm, dtype=bool), np.zeros(self.n_arm)
        while free.any():
            Jf = J[:, free]
            dq[:] = 0.0
            dq[free] = np.linalg.solve(Jf.T @ Jf + self.damping**2 * np.eye(int(free.sum())), Jf.T @ error)
            blocked = free & ((q + dq < self.lo) | (q + dq > self.hi))
            if not blocked.any():
                break
            free &= ~blocked
        return dq


def _skew(r: np.ndarray) -> np.ndarray:
    """The matrix of r x . (so w x r = skew(r).T @ w)."""
    return np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
