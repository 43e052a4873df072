"""DexRepSystem: the DexRep features (dexdrake.dexrep.feature_sets.FeatureExtractor) of the
hand and the object as the controller sees them, in every mode.

Inputs:  "hand_state"   [q; v] in policy joint order (2n): measured, or the plant's;
         "object_pose"  [x, y, z, qw, qx, qy, qz]: perceived, or the plant's;
         "query_object" SceneGraph's QueryObject (read only on the "scenegraph" path, which
                        needs the SceneGraph of the plant the features are computed on).
Output:  "features", the selected feature set's vector.
The hand's kinematics are evaluated on a private context of `plant` (a model of the robot:
the simulated scene's plant, or a scene built for the purpose on the station).
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import QueryObject
from pydrake.systems.framework import BasicVector, LeafSystem

from dexdrake.dexrep.feature_sets import FeatureExtractor, FeaturePath
from dexdrake.dexrep.geometry import ObjectGeometry
from dexdrake.hands.description import HandDescription
from dexdrake.systems.station import pose_from_vector


class DexRepSystem(LeafSystem):
    def __init__(self, hand: HandDescription, plant, hand_instance, geometry: ObjectGeometry,
                 feature_set: str = "DexRep", path: FeaturePath = "fast", distance_geometry_id=None):
        super().__init__()
        self._plant = plant
        self._plant_context = plant.CreateDefaultContext()
        joints = [plant.GetJointByName(j, hand_instance) for j in hand.policy_joints]
        self._q_index = np.array([j.position_start() for j in joints])
        self._v_index = np.array([j.velocity_start() for j in joints])
        self._n = hand.num_actuators
        self.extractor = FeatureExtractor(hand, plant, hand_instance, geometry, feature_set, path,
                                          distance_geometry_id)
        self._hand = self.DeclareVectorInputPort("hand_state", 2 * self._n)
        self._pose = self.DeclareVectorInputPort("object_pose", 7)
        self._query = self.DeclareAbstractInputPort("query_object", AbstractValue.Make(QueryObject()))
        self.DeclareVectorOutputPort("features", self.extractor.size, self._calc)

    def _calc(self, context, output: BasicVector) -> None:
        state = self._hand.Eval(context)
        q = self._plant.GetPositions(self._plant_context)
        q[self._q_index] = state[: self._n]
        self._plant.SetPositions(self._plant_context, q)
        v = self._plant.GetVelocities(self._plant_context)
        v[self._v_index] = state[self._n :]
        self._plant.SetVelocities(self._plant_context, v)
        X_WO = pose_from_vector(self._pose.Eval(context))
        query = self._query.Eval(context) if self.extractor.path == "scenegraph" else None
        output.SetFromVector(self.extractor(self._plant_context, X_WO, query))
