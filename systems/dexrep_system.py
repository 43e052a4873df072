"""DexRepSystem: a LeafSystem wrapper over dexdrake.dexrep.feature_sets.FeatureExtractor.

Inputs:  "plant_state" (the plant's full [q; v]) and "query_object" (SceneGraph's
         QueryObject; read only on the "scenegraph" path).
Output:  "features", the selected feature set's vector (see FeatureExtractor).
"""

from __future__ import annotations

from pydrake.common.value import AbstractValue
from pydrake.geometry import QueryObject
from pydrake.systems.framework import BasicVector, LeafSystem

from dexdrake.dexrep.feature_sets import FeatureExtractor
from dexdrake.dexrep.geometry import ObjectGeometry
from dexdrake.hands.description import HandDescription


class DexRepSystem(LeafSystem):
    def __init__(self, hand: HandDescription, plant, hand_instance, object_instance,
                 geometry: ObjectGeometry, feature_set: str = "DexRep", path: str = "fast",
                 distance_geometry_id=None):
        super().__init__()
        self._plant = plant
        self._plant_context = plant.CreateDefaultContext()
        bodies = [plant.get_body(i) for i in plant.GetBodyIndices(object_instance)]
        if len(bodies) != 1:
            raise ValueError(f"object instance must hold exactly one body, found {len(bodies)}")
        self._object_body = bodies[0]
        self.extractor = FeatureExtractor(hand, plant, hand_instance, geometry, feature_set, path,
                                          distance_geometry_id)
        nx = plant.num_multibody_states()
        self.DeclareVectorInputPort("plant_state", nx)
        self.DeclareAbstractInputPort("query_object", AbstractValue.Make(QueryObject()))
        self.DeclareVectorOutputPort("features", self.extractor.size, self._calc)

    def _calc(self, context, output: BasicVector) -> None:
        x = self.get_input_port(0).Eval(context)
        self._plant.SetPositionsAndVelocities(self._plant_context, x)
        X_WO = self._plant.EvalBodyPoseInWorld(self._plant_context, self._object_body)
        query = self.get_input_port(1).Eval(context) if self.extractor.path == "scenegraph" else None
        output.SetFromVector(self.extractor(self._plant_context, X_WO, query))
