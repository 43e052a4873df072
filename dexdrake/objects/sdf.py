"""SDFormat text for one rigid object: inertia, visual, convex contact pieces, distance mesh."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

DISTANCE_GEOMETRY_NAME = "distance_mesh"
"""Name of the collision element holding the watertight, non-convex mesh.obj.

It exists only for SceneGraph signed-distance queries (ComputeSignedDistanceToPoint gives
the true closest point on a closed non-convex Mesh). For point contact Drake would replace
it by its convex hull, so a scene MUST remove it from contact, e.g. with
`exclude_distance_geometry_from_contact(scene_graph)` after all models are added.
"""


def _proximity(friction: float) -> str:
    mu = f"{friction:.6g}"
    return (
        "<drake:proximity_properties>"
        f"<drake:mu_dynamic>{mu}</drake:mu_dynamic><drake:mu_static>{mu}</drake:mu_static>"
        "</drake:proximity_properties>"
    )


def _uri(path: Path) -> str:
    return escape(Path(path).resolve().as_uri())


def object_sdf(
    model_name: str,
    mesh_path: Path,
    pieces: Sequence[Path],
    mass: float,
    inertia: np.ndarray,
    friction: float,
    supports: np.ndarray,
    support_radius: float,
) -> str:
    """SDF text of a free rigid object whose link frame is the object frame (origin = COM),
    with contact spheres of `support_radius` at the (k, 3) `supports` (objects/support.py).

    Paths are written absolute so the text can be parsed from anywhere (AddModelsFromString).
    """
    i = np.asarray(inertia, dtype=float)
    collisions = "".join(
        f'<collision name="convex_{k:02d}"><geometry><mesh><uri>{_uri(p)}</uri><drake:declare_convex/>'
        f"</mesh></geometry>{_proximity(friction)}</collision>\n      "
        for k, p in enumerate(pieces)
    ) + "".join(
        f'<collision name="support_{k:02d}"><pose>{c[0]:.6g} {c[1]:.6g} {c[2]:.6g} 0 0 0</pose>'
        f"<geometry><sphere><radius>{support_radius:.6g}</radius></sphere></geometry>{_proximity(friction)}</collision>\n      "
        for k, c in enumerate(supports)
    )
    return f"""<?xml version="1.0"?>
<sdf version="1.9" xmlns:drake="http://drake.mit.edu">
  <model name="{escape(model_name)}">
    <link name="{escape(model_name)}">
      <inertial>
        <mass>{mass:.10g}</mass>
        <inertia>
          <ixx>{i[0, 0]:.10g}</ixx><ixy>{i[0, 1]:.10g}</ixy><ixz>{i[0, 2]:.10g}</ixz>
          <iyy>{i[1, 1]:.10g}</iyy><iyz>{i[1, 2]:.10g}</iyz><izz>{i[2, 2]:.10g}</izz>
        </inertia>
      </inertial>
      <visual name="visual"><geometry><mesh><uri>{_uri(mesh_path)}</uri></mesh></geometry></visual>
      {collisions}<collision name="{DISTANCE_GEOMETRY_NAME}"><geometry><mesh><uri>{_uri(mesh_path)}</uri></mesh></geometry>{_proximity(friction)}</collision>
    </link>
  </model>
</sdf>
"""
