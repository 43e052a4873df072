"""Support spheres: small contact spheres tucked into the corners of each convex piece.

Drake's point contact gives one witness point per pair of convex shapes. An object resting
on a face is then held at a single point of that face, away from its centre of mass: it
rocks, and each step the witness moves to the deeper side. Objects sink into the table
that way, whatever the penetration allowance. A few spheres at each piece's extreme
vertices give a resting face several contact points at its corners (the usual remedy for
boxes under point contact). Each sphere lies inside the piece, tangent to the faces at its
vertex, so the object's shape is unchanged. Hydroelastic contact would hold objects too,
at one SAP constraint per contact polygon instead of per point.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dexdrake.objects.meshfile import load_obj

SPHERES_PER_PIECE = 8  # a box's corners; a round or flat piece's extremes
SPHERE_RADIUS = 5e-4  # m


def support_centres(piece: Path) -> np.ndarray:
    """(k, 3) centres, k <= SPHERES_PER_PIECE, of spheres of SPHERE_RADIUS at the piece's
    extreme vertices.

    Vertices are farthest-point sampled on the piece's hull from its lowest one; each centre
    sits the radius inside every hull face at its vertex (least squares where more than three
    faces meet), so the sphere touches the vertex's faces; a sphere that would stick out of
    the piece by more than a tenth of its radius (a piece thinner than the sphere, a sliver)
    is left out.
    """
    hull = load_obj(piece).convex_hull
    vertices, faces, normals = np.asarray(hull.vertices), np.asarray(hull.faces), np.asarray(hull.face_normals)
    offsets = np.einsum("ij,ij->i", normals, vertices[faces[:, 0]])
    chosen = [int(np.argmin(vertices[:, 2]))]
    distance = np.linalg.norm(vertices - vertices[chosen[0]], axis=1)
    while len(chosen) < min(SPHERES_PER_PIECE, len(vertices)):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(vertices - vertices[chosen[-1]], axis=1))
    centres = []
    for i in chosen:
        n = normals[(faces == i).any(axis=1)]
        offset = np.linalg.lstsq(n, -SPHERE_RADIUS * np.ones(len(n)), rcond=None)[0]
        centre = vertices[i] + offset
        if (offsets - normals @ centre).min() >= 0.9 * SPHERE_RADIUS:  # depth inside the piece
            centres.append(centre)
    return np.array(centres).reshape(-1, 3)
