"""The workspace box of a real station: commanded set-points whose hand leaves it are refused.

`WorkspaceBox(hand, lower, upper)` evaluates the forward kinematics of a set-point (policy
order, arm and fingers) on a plant of the hand's model alone (the arm's base welded where
the model puts it, the world frame of every mode) and checks the palm's grasp centre and
every fingertip (the hand description's points) against the axis-aligned box
[lower, upper] (m, world frame). A set-point outside is a fault, not a clamp: clamping a
Cartesian point back into the box needs an inverse kinematics whose answer the policy never
asked for (a different posture, possibly through the table), while a fault ends in the
safe stop with the arm held where it was.

`WorkspaceGuard` is the same check in the diagram: input "command" (n), output "command"
(passed through), raising StationFault when the command leaves the box.
"""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import BasicVector, Context, LeafSystem

from dexdrake.errors import DexdrakeError
from dexdrake.hands.description import HandDescription
from dexdrake.hands.kinematics import hand_kinematics


class WorkspaceBox:
    """Forward kinematics of set-points against a box (module docstring)."""

    def __init__(self, hand: HandDescription, lower, upper):
        self.lower, self.upper = np.asarray(lower, float), np.asarray(upper, float)
        if self.lower.shape != (3,) or self.upper.shape != (3,) or np.any(self.lower >= self.upper):
            raise DexdrakeError(f"workspace box: lower {lower} must be below upper {upper} (3 values each)")
        kinematics = hand_kinematics(hand)
        self.plant = plant = kinematics.plant
        instance, self.q_index = kinematics.hand_instance, kinematics.q_index
        self.context = plant.CreateDefaultContext()

        def frame(body: str):
            return plant.GetBodyByName(body, instance).body_frame()

        self.points = [("palm", frame(hand.palm.body), np.asarray(hand.palm.centre, float))]
        self.points += [(p.name, frame(p.body), np.asarray(p.offset, float)) for p in hand.fingertips]

    def positions(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """World positions (m) of the palm centre and the fingertips at set-point `q`."""
        full = self.plant.GetPositions(self.context)
        full[self.q_index] = q
        self.plant.SetPositions(self.context, full)
        return {name: self.plant.CalcPointsPositions(self.context, frame, offset.reshape(3, 1),
                                                     self.plant.world_frame()).ravel()
                for name, frame, offset in self.points}

    def violation(self, q: np.ndarray) -> str | None:
        """None when every point of set-point `q` is inside the box, else what leaves it."""
        if not np.all(np.isfinite(q)):
            return None  # a non-finite command is the command guard's (held, never sent)
        for name, p in self.positions(np.asarray(q, float)).items():
            if np.any(p < self.lower) or np.any(p > self.upper):
                return (f"workspace: the set-point puts the {name} at {np.round(p, 3).tolist()} m, outside "
                        f"the box {self.lower.tolist()} .. {self.upper.tolist()}")
        return None


class WorkspaceGuard(LeafSystem):
    """Passes "command" through; raises `fault(message)` when it leaves `box`."""

    def __init__(self, box: WorkspaceBox, num_joints: int, fault: type[Exception]):
        super().__init__()
        self.box, self._fault = box, fault
        self._in = self.DeclareVectorInputPort("command", num_joints)
        self.DeclareVectorOutputPort("command", num_joints, self._calc)

    def _calc(self, context: Context, out: BasicVector) -> None:
        q = self._in.Eval(context)
        why = self.box.violation(q)
        if why is not None:
            raise self._fault(why)
        out.SetFromVector(q)
