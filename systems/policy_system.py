"""PolicySystem: runs a DexRepNet policy checkpoint inside a Drake diagram at the control rate.

Ports: input "observation" (the env observation vector, obs_dim) -> output "action"
(action_dim, normalised to [-1, 1]). The action is discrete state updated by a periodic
event every `control_period` seconds (a zero-order hold between updates; zeros, or
`initial_action`, before the first update). Actions pass `guard` (dexdrake/command_guard.py:
a non-finite action holds the last one, one outside [-1, 1] is clipped; `guard.counts`).
With an `actions` map (dexdrake/hands/action_map.py) it also has input "hand_state" (the
measured [q; v]) and output "command": the action's joint set-points, computed in the same
update from the positions measured then (held between updates).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydrake.systems.framework import BasicVector, Context, DiscreteValues, LeafSystem

from dexdrake.errors import DexdrakeError
from dexdrake.hands.action_map import ActionMap
from dexdrake.learn.policy import DexRepNetPolicy, load_policy
from dexdrake.command_guard import CommandGuard
from dexdrake.systems.station import LoopTimer


class PolicySystem(LeafSystem):
    def __init__(
        self,
        policy: DexRepNetPolicy | str | Path,
        control_period: float,
        deterministic: bool = True,
        seed: int = 0,
        initial_action: np.ndarray | None = None,
        actions: ActionMap | None = None,
    ):
        """`policy` is a loaded policy or a checkpoint path (see dexdrake.learn.policy).

        With deterministic=False actions are sampled from the Gaussian head with a
        numpy Generator seeded by `seed` (owned by the system, not the context).
        """
        super().__init__()
        if control_period <= 0:
            raise DexdrakeError(f"control_period must be positive, got {control_period}")
        torch.set_num_threads(1)
        self.metadata: dict[str, Any] = {}
        if isinstance(policy, (str, Path)):
            policy, self.metadata = load_policy(policy)
        self.policy = policy.eval()
        self._rng = None if deterministic else np.random.default_rng(seed)
        obs_dim, act_dim = policy.config.obs_dim, policy.config.action_dim
        init = np.zeros(act_dim) if initial_action is None else np.asarray(initial_action, dtype=float)
        if init.shape != (act_dim,):
            raise DexdrakeError(f"initial_action has shape {init.shape}, expected ({act_dim},)")
        self.guard = CommandGuard(-np.ones(act_dim), np.ones(act_dim))
        self.timer = LoopTimer()  # update times: the policy rate
        self._obs_port = self.DeclareVectorInputPort("observation", BasicVector(obs_dim))
        state = self.DeclareDiscreteState(init)
        self.DeclareStateOutputPort("action", state)
        self.actions = actions
        if actions is not None:
            self._hand_port = self.DeclareVectorInputPort("hand_state", BasicVector(2 * act_dim))
            self.DeclareStateOutputPort("command", self.DeclareDiscreteState(actions.mid))
        self.DeclarePeriodicDiscreteUpdateEvent(control_period, 0.0, self._update)

    def compute_action(self, observation: np.ndarray) -> np.ndarray:
        """The policy's raw action for one observation (mean unless sampling was requested)."""
        with torch.inference_mode():
            action, _ = self.policy.act(observation, self._rng)
        return action

    def _update(self, context: Context, discrete_state: DiscreteValues) -> None:
        self.timer.tick(context.get_time())
        action = self.compute_action(self._obs_port.Eval(context))
        action = self.guard(action, context.get_discrete_state(0).get_value())
        discrete_state.set_value(0, action)
        if self.actions is not None:
            q = self._hand_port.Eval(context)[: len(action)]
            discrete_state.set_value(1, self.actions.command(action, q))

    def hold(self, context: Context, q: np.ndarray) -> None:
        """Set the held action (and command) to those of joint positions `q` (this system's context)."""
        context.get_mutable_discrete_state(0).SetFromVector(np.clip(self.actions.normalise(q, q), -1.0, 1.0))
        context.get_mutable_discrete_state(1).SetFromVector(q)
