"""Deterministic generators of hand-sized household-like objects (manifold3d solids).

Every object is a named `Recipe`: a builder function plus its parameters (metres). A
builder returns a manifold3d `Manifold` posed in its stable resting orientation (z up,
resting on z = 0); `build_mesh` turns it into a trimesh with the origin at the centre of
mass. Variations of one builder with different parameters give the object count. The
objects are procedural stand-ins, not scans. Splits:
- "train": the training set (the augmented split scales its objects and adds superquadric
  shapes, dexdrake.objects.augment);
- "unseen": reported only (test seeds); builders and categories of their own, and each
  farther from every training and augmented object (dexdrake.objects.similarity) than the
  median training object is from its nearest training neighbour (tests/test_objects.py);
- "validation": probes and choices (DAgger probes, candidate policies); builders and
  categories shared with no other split;
- "near": namesakes of the DexRepNet paper's unseen GRAB objects (mug, camera, apple, ...),
  reported in a table of their own (models/weights/eval_block2_near.md); some are near training
  objects (the small pyramid is the training pyramid's builder scaled down).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import manifold3d as mf
import numpy as np
import trimesh

from dexdrake.errors import UnknownNameError

SEGMENTS = 40  # circular segments of round parts: ~1-3k triangles per object

Solid = mf.Manifold


# ---------------------------------------------------------------- primitives
def _union(parts: Sequence[Solid]) -> Solid:
    return mf.Manifold.batch_boolean(list(parts), mf.OpType.Add)


def _box(size: Sequence[float], centre: Sequence[float] = (0, 0, 0)) -> Solid:
    return mf.Manifold.cube(tuple(float(s) for s in size), True).translate(tuple(centre))


def _cyl(h: float, r: float, r_top: float | None = None, base=(0, 0, 0), seg: int = SEGMENTS):
    """Upright (frustum of a) cylinder with its base centre at `base`."""
    top = r if r_top is None else r_top
    return mf.Manifold.cylinder(h, r, top, seg).translate(tuple(base))


def _cyl_x(length: float, r: float, centre=(0, 0, 0), seg: int = SEGMENTS) -> Solid:
    """Cylinder along x centred at `centre`."""
    return mf.Manifold.cylinder(length, r, r, seg, True).rotate((0, 90, 0)).translate(tuple(centre))


def _sphere(r: float, centre=(0, 0, 0), seg: int = 24) -> Solid:
    return mf.Manifold.sphere(r, seg).translate(tuple(centre))


def _ellipsoid(radii: Sequence[float], centre=(0, 0, 0), seg: int = 28) -> Solid:
    return mf.Manifold.sphere(1.0, seg).scale(tuple(radii)).translate(tuple(centre))


def _hull(points: np.ndarray) -> Solid:
    return mf.Manifold.hull_points(np.asarray(points, dtype=float))


def _tube(points: Sequence[Sequence[float]], radii: float | Sequence[float], seg: int = 16):
    """A swept-sphere tube through `points` (union of hulls of consecutive spheres)."""
    pts = np.asarray(points, dtype=float)
    rs = np.broadcast_to(np.asarray(radii, dtype=float), (len(pts),))
    balls = [_sphere(float(r), p, seg) for p, r in zip(pts, rs)]
    return _union([mf.Manifold.batch_hull([a, b]) for a, b in zip(balls[:-1], balls[1:])])


def _revolve(profile: Sequence[Sequence[float]], seg: int = SEGMENTS) -> Solid:
    """Revolve a closed (r, z) profile (r >= 0) about the z axis."""
    pts = np.asarray(profile, dtype=float)
    area = 0.5 * np.sum(pts[:, 0] * np.roll(pts[:, 1], -1) - np.roll(pts[:, 0], -1) * pts[:, 1])
    if area < 0:
        pts = pts[::-1]
    return mf.CrossSection([pts]).revolve(seg)


def _arc(centre_rz: Sequence[float], radius: float, a0: float, a1: float, n: int) -> list:
    """Points (r, z) on a circular arc, angles in radians measured from +r toward +z."""
    angles = np.linspace(a0, a1, n)
    return [(centre_rz[0] + radius * np.cos(a), centre_rz[1] + radius * np.sin(a)) for a in angles]


def _handle_loop(x0: float, z_lo: float, z_hi: float, reach: float, r: float) -> Solid:
    """A C-shaped handle in the xz plane from (x0, z_hi) out by `reach` and back to (x0, z_lo)."""
    zc, half = 0.5 * (z_lo + z_hi), 0.5 * (z_hi - z_lo)
    t = np.linspace(-np.pi / 2, np.pi / 2, 9)
    pts = [(x0 + reach * np.cos(a), 0.0, zc + half * np.sin(a)) for a in t]
    return _tube(pts, r)


# ---------------------------------------------------------------- builders
def cup(radius_bottom: float, radius_top: float, height: float, wall: float = 0.004) -> Solid:
    """Tapered open cup without a handle."""
    rb, rt, t = radius_bottom, radius_top, wall
    return _revolve([(0, 0), (rb, 0), (rt, height), (rt - t, height), (rb - t, t), (0, t)])


def mug(radius: float, height: float, handle_reach: float, wall: float = 0.005) -> Solid:
    """Straight mug with a C handle on +x."""
    body = cup(radius, radius, height, wall)
    handle = _handle_loop(radius - wall / 2, 0.25 * height, 0.8 * height, handle_reach, 0.006)
    return _union([body, handle])


def bottle(radius: float, height: float, neck_radius: float, neck_length: float) -> Solid:
    """Solid bottle: body, rounded shoulder, neck and a slightly wider cap."""
    body_h = height - neck_length
    shoulder = radius - neck_radius
    prof = [(0, 0), (radius - 0.003, 0), (radius, 0.003), (radius, body_h - shoulder)]
    prof += _arc((neck_radius, body_h - shoulder), shoulder, 0.0, np.pi / 2, 7)[1:]
    cap_r, cap_h = neck_radius + 0.002, min(0.02, 0.5 * neck_length)
    prof += [(neck_radius, height - cap_h), (cap_r, height - cap_h), (cap_r, height), (0, height)]
    return _revolve(prof)


def box(sx: float, sy: float, sz: float) -> Solid:
    """Rectangular box resting on a face."""
    return _box((sx, sy, sz), (0, 0, sz / 2))


def sphere(radius: float) -> Solid:
    """Ball."""
    return _sphere(radius, (0, 0, radius), 32)


def cylinder(radius: float, height: float, lying: bool = False) -> Solid:
    """Cylinder standing on its base or lying on its side (axis along x)."""
    if lying:
        return _cyl_x(height, radius, (0, 0, radius))
    return _cyl(height, radius)


def torus(major: float, minor: float) -> Solid:
    """Ring lying flat."""
    circle = mf.CrossSection.circle(minor, 20).translate((major, minor))
    return circle.revolve(SEGMENTS)


def pyramid(base: float, height: float, sides: int = 4) -> Solid:
    """Regular pyramid with `sides` base edges."""
    ang = np.arange(sides) * 2 * np.pi / sides + np.pi / sides
    r = base / (2 * np.sin(np.pi / sides))
    pts = [(r * np.cos(a), r * np.sin(a), 0.0) for a in ang] + [(0.0, 0.0, height)]
    return _hull(np.array(pts))


def banana(arc_radius: float, arc_degrees: float, radius: float) -> Solid:
    """Curved tapered tube lying in the horizontal plane, thickest in the middle."""
    a = np.radians(np.linspace(-arc_degrees / 2, arc_degrees / 2, 11))
    rs = radius * (0.45 + 0.55 * np.sin(np.linspace(0, np.pi, 11)) ** 0.5)
    pts = [(arc_radius * np.cos(t), arc_radius * np.sin(t), r) for t, r in zip(a, rs)]
    return _tube(pts, rs)


def hammer(handle_length: float, handle_radius: float, head: Sequence[float]) -> Solid:
    """Handle along x lying flat, box head across y; both rest on the table."""
    hx, hy, hz = head
    handle = _tube([(0, 0, handle_radius), (handle_length, 0, handle_radius)], handle_radius)
    return _union([handle, _box((hx, hy, hz), (handle_length, 0, hz / 2))])


def knife(blade_length: float, blade_width: float, handle_length: float) -> Solid:
    """Flat blade (4 mm thick) with a thicker handle, lying flat."""
    t = 0.004
    blade = mf.CrossSection(
        [np.array([(0, 0), (blade_length, 0), (blade_length, 0.3 * blade_width),
                   (0.8 * blade_length, blade_width), (0, blade_width)])]
    ).extrude(t)
    blade = blade.translate((0, -blade_width / 2, 0))
    handle = _box((handle_length, 0.022, 0.016), (-handle_length / 2, 0, 0.008))
    return _union([blade, handle])


def plate(radius: float, height: float, base_ratio: float = 0.6) -> Solid:
    """Shallow dish with a foot and a raised rim."""
    rb, t = base_ratio * radius, 0.005
    return _revolve([(0, 0), (rb, 0), (radius, height), (radius - 0.006, height), (rb - 0.004, t), (0, t)])


def book(width: float, depth: float, thickness: float) -> Solid:
    """Book lying flat with a rounded spine along one edge."""
    cover = _box((width, depth, thickness), (0, 0, thickness / 2))
    spine = mf.Manifold.cylinder(width, thickness / 2, thickness / 2, 24, True)
    spine = spine.rotate((0, 90, 0)).translate((0, depth / 2, thickness / 2))
    return _union([cover, spine])


def can(radius: float, height: float) -> Solid:
    """Drink can with bevelled rims."""
    b = 0.005
    return _revolve([(0, 0), (radius - b, 0), (radius, b), (radius, height - b), (radius - b, height), (0, height)])


def cone(radius: float, height: float, top_radius: float = 0.0) -> Solid:
    """Cone or frustum standing on its base."""
    return _cyl(height, radius, top_radius)


def capsule(radius: float, length: float) -> Solid:
    """Capsule lying on its side along x (length = total length)."""
    half = length / 2 - radius
    return mf.Manifold.batch_hull([_sphere(radius, (-half, 0, radius), 24), _sphere(radius, (half, 0, radius), 24)])


def wine_glass(bowl_radius: float, stem_height: float, bowl_height: float) -> Solid:
    """Glass: foot disc, stem, hollow rounded bowl."""
    foot, stem_r, t = 0.75 * bowl_radius, 0.004, 0.003
    z0 = stem_height
    outer = [(bowl_radius * np.sin(a), z0 + bowl_height * 0.6 * (1 - np.cos(a))) for a in np.linspace(0.15, np.pi / 2, 7)]
    top = z0 + bowl_height
    inner_r = bowl_radius - t
    inner = [(inner_r * np.sin(a), z0 + t + (bowl_height * 0.6 - t) * (1 - np.cos(a))) for a in np.linspace(np.pi / 2, 0.0, 7)]
    prof = [(0, 0), (foot, 0), (foot, 0.004), (stem_r, 0.012), (stem_r, z0)] + outer
    prof += [(bowl_radius, top), (inner_r, top)] + inner + [(0, z0 + t)]
    return _revolve(prof)


def teapot(radius: float, height: float) -> Solid:
    """Round body with a flat base, a spout on -x, a handle on +x and a lid knob."""
    prof = [(0, 0), (0.7 * radius, 0)]
    prof += [(radius * np.cos(a), height / 2 + height / 2 * np.sin(a)) for a in np.linspace(-np.pi / 2 + 0.8, np.pi / 2 - 0.6, 9)]
    prof += [(0, height)]
    body = _revolve(prof)
    knob = _sphere(0.012, (0, 0, height + 0.004), 16)
    spout = _tube([(-0.7 * radius, 0, 0.35 * height), (-radius - 0.02, 0, 0.6 * height), (-radius - 0.035, 0, 0.85 * height)], [0.012, 0.009, 0.007])
    handle = _handle_loop(0.85 * radius, 0.3 * height, 0.8 * height, 0.35 * radius, 0.006)
    return _union([body, knob, spout, handle])


def bowl(radius: float, height: float) -> Solid:
    """Hollow rounded bowl on a foot ring."""
    t = 0.004
    outer = [(radius * np.sin(a), height * (1 - np.cos(a))) for a in np.linspace(0.35, np.pi / 2, 8)]
    inner = [((radius - t) * np.sin(a), t + (height - t) * (1 - np.cos(a))) for a in np.linspace(np.pi / 2, 0.0, 8)]
    return _revolve([(0, 0), (outer[0][0], 0)] + outer + [(radius, height), (radius - t, height)] + inner + [(0, t)])


def flashlight(body_radius: float, length: float, head_radius: float) -> Solid:
    """Flashlight standing on its wide head."""
    head_h = 0.25 * length
    return _revolve([(0, 0), (head_radius, 0), (head_radius, head_h), (body_radius, head_h + 0.015), (body_radius, length), (0, length)])


def vase(radius: float, height: float, waves: float = 1.0) -> Solid:
    """Hollow vase with a wavy profile."""
    z = np.linspace(0, height, 12)
    r = radius * (0.75 + 0.25 * np.sin(np.pi * waves * z / height + 0.3))
    t = 0.004
    outer = list(zip(r, z))
    inner = [(ri - t, zi) for ri, zi in zip(r[::-1], z[::-1]) if zi >= t][:-1] + [(r[1] - t, t)]
    return _revolve([(0, 0)] + outer + inner + [(0, t)])


def prism(side: float, length: float) -> Solid:
    """Triangular prism lying on a rectangular face, axis along x."""
    h = side * np.sqrt(3) / 2
    tri = [(-side / 2, 0), (side / 2, 0), (0, h)]
    pts = [(x, y, z) for x in (-length / 2, length / 2) for y, z in tri]
    return _hull(np.array(pts))


def ellipsoid(a: float, b: float, c: float) -> Solid:
    """Ellipsoid with semi-axes a >= b >= c, lying on its flattest side."""
    return _ellipsoid((a, b, c), (0, 0, c), 32)


def hex_prism(radius: float, height: float) -> Solid:
    """Hexagonal prism standing on a hexagon."""
    return _cyl(height, radius, None, seg=6)


def phone(width: float, length: float, thickness: float, corner: float = 0.008) -> Solid:
    """Rounded-rectangle slab lying flat."""
    cx, cy = width / 2 - corner, length / 2 - corner
    corners = [_cyl(thickness, corner, None, (sx * cx, sy * cy, 0), 16) for sx in (-1, 1) for sy in (-1, 1)]
    return mf.Manifold.batch_hull(corners)


def mouse(length: float, width: float, height: float) -> Solid:
    """Half ellipsoid (computer mouse) on its flat face."""
    return _ellipsoid((length / 2, width / 2, height), (0, 0, 0), 32).trim_by_plane((0, 0, 1), 0.0)


def wrench(length: float, head_radius: float, thickness: float = 0.006) -> Solid:
    """Flat wrench: bar with a ring end and an open-jaw end, lying flat."""
    bar = _box((length, 0.9 * head_radius, thickness), (0, 0, thickness / 2))
    heads = [_cyl(thickness, head_radius, None, (s * length / 2, 0, 0), 24) for s in (-1, 1)]
    hole = _cyl(thickness * 3, 0.5 * head_radius, None, (length / 2, 0, -thickness), 6)
    jaw = _box((head_radius * 1.2, 0.8 * head_radius, thickness * 3), (-length / 2 - 0.6 * head_radius, 0, thickness / 2))
    return _union([bar] + heads) - hole - jaw


def lightbulb(bulb_radius: float, base_radius: float, base_height: float) -> Solid:
    """Bulb standing on its screw base."""
    neck = base_height + 0.8 * bulb_radius
    prof = [(0, 0), (base_radius, 0), (base_radius, base_height)]
    prof += [(bulb_radius * np.cos(a), neck + bulb_radius * np.sin(a)) for a in np.linspace(-0.7, np.pi / 2, 10)]
    return _revolve(prof)


def l_block(length: float, width: float, thickness: float) -> Solid:
    """L-shaped block lying flat."""
    a = _box((length, thickness, width), (0, 0, width / 2))
    b = _box((thickness, length * 0.6, width), (-length / 2 + thickness / 2, length * 0.3, width / 2))
    return _union([a, b])


def camera(body: Sequence[float], lens_radius: float, lens_length: float) -> Solid:
    """Box body with a lens cylinder on the front (-y) and a shutter button."""
    bx, by, bz = body
    core = _box(body, (0, 0, bz / 2))
    lens = mf.Manifold.cylinder(lens_length, lens_radius, lens_radius * 0.9, SEGMENTS)
    lens = lens.rotate((90, 0, 0)).translate((0.1 * bx, -by / 2 + 0.001, 0.45 * bz))
    button = _cyl(0.006, 0.006, None, (0.3 * bx, 0, bz - 0.001), 16)
    return _union([core, lens, button])


def binoculars(tube_radius: float, length: float, gap: float) -> Solid:
    """Two parallel tubes lying along x, a bridge and narrower eyepieces."""
    y = tube_radius + gap / 2
    tubes = [_cyl_x(length, tube_radius, (0, s * y, tube_radius)) for s in (-1, 1)]
    eyes = [_cyl_x(0.03, 0.7 * tube_radius, (length / 2 + 0.014, s * y, tube_radius)) for s in (-1, 1)]
    bridge = _box((0.4 * length, 2 * y, 1.2 * tube_radius), (0, 0, tube_radius))
    return _union(tubes + eyes + [bridge])


def apple(radius: float) -> Solid:
    """Sphere with dimples at both poles and a short stem."""
    body = _sphere(radius, (0, 0, radius), 32).scale((1, 1, 0.9))
    h = 1.8 * radius
    dimples = [_sphere(0.35 * radius, (0, 0, -0.2 * radius), 20), _sphere(0.35 * radius, (0, 0, h + 0.2 * radius), 20)]
    body = body - _union(dimples)
    stem = _cyl(0.25 * radius + 0.015, 0.003, 0.002, (0, 0, h - 0.05 * radius - 0.01), 10)
    return _union([body, stem])


def pear(radius: float, height: float) -> Solid:
    """Pear: revolved profile, wide bottom, narrow top, with a stem."""
    z = np.linspace(0, height, 14)
    s = z / height
    r = radius * (np.sin(np.pi * np.clip(s * 1.15, 0, 1)) ** 0.6 * (1 - 0.45 * s) + 0.0)
    r[0], r[-1] = 0.5 * radius, 0.0
    prof = [(0, 0)] + [(max(ri, 0.004), zi) for ri, zi in zip(r, z)][:-1] + [(0.004, height), (0, height)]
    stem = _cyl(0.015, 0.003, 0.002, (0, 0, height - 0.002), 10)
    return _union([_revolve(prof), stem])


def toothpaste(length: float, radius: float, crimp_width: float) -> Solid:
    """Tube lying flat: round at the cap end, flattened to a crimp at the other, plus a cap."""
    cap_end = _cyl_x(0.004, radius, (0, 0, radius), 24)
    crimp = _box((0.004, crimp_width, 0.003), (length, 0, 0.0015))
    tube = mf.Manifold.batch_hull([cap_end, crimp])
    cap = _cyl_x(0.02, 0.6 * radius, (-0.01, 0, radius), 16)
    return _union([tube, cap])


def frying_pan(radius: float, depth: float, handle_length: float) -> Solid:
    """Shallow hollow pan with a long handle rising slightly along +x."""
    t = 0.004
    pan = _revolve([(0, 0), (radius - depth * 0.4, 0), (radius, depth), (radius - t, depth), (radius - depth * 0.4 - t, t), (0, t)])
    handle = _tube([(radius - 0.004, 0, depth - 0.006), (radius + handle_length, 0, depth + 0.012)], [0.007, 0.009])
    return _union([pan, handle])


def toothbrush(length: float, width: float, bristle_height: float) -> Solid:
    """Thin flat handle with a bristle block at one end, lying bristles up."""
    handle = _box((length, width, 0.007), (0, 0, 0.0035))
    head = _box((0.028, 0.9 * width, bristle_height), (length / 2 - 0.016, 0, 0.007 + bristle_height / 2 - 0.001))
    return _union([handle, head])


def elephant(body_length: float) -> Solid:
    """Toy elephant: ellipsoid body, four legs, head, trunk and flat ears."""
    L = body_length
    leg_h, leg_r = 0.35 * L, 0.1 * L
    body_c = (0, 0, leg_h + 0.25 * L)
    body = _ellipsoid((0.5 * L, 0.3 * L, 0.3 * L), body_c)
    legs = [_cyl(leg_h + 0.15 * L, leg_r, None, (sx * 0.3 * L, sy * 0.16 * L, 0), 16) for sx in (-1, 1) for sy in (-1, 1)]
    head_c = (0.55 * L, 0, leg_h + 0.45 * L)
    head = _sphere(0.22 * L, head_c, 24)
    trunk = _tube([(0.7 * L, 0, leg_h + 0.4 * L), (0.8 * L, 0, leg_h + 0.15 * L), (0.82 * L, 0, 0.25 * L), (0.9 * L, 0, 0.15 * L)], [0.07 * L, 0.055 * L, 0.045 * L, 0.04 * L], 12)
    ears = [_ellipsoid((0.04 * L, 0.2 * L, 0.18 * L), (0.45 * L, s * 0.22 * L, leg_h + 0.48 * L), 16) for s in (-1, 1)]
    return _union([body, head, trunk] + legs + ears)


def hand(palm_length: float, palm_width: float) -> Solid:
    """Flat open hand lying palm down: a rounded palm, four fingers and a thumb."""
    t = 0.022
    r = t / 2
    palm = phone(palm_width, palm_length, t, 0.01)
    fingers = []
    lengths = (0.75, 0.85, 0.8, 0.62)
    for i, f in enumerate(lengths):
        y = (-0.375 + 0.25 * i) * (palm_width - t)
        fingers.append(_tube([(y, palm_length / 2 - 0.01, r), (y * 1.15, palm_length / 2 + f * palm_length, r)], [0.95 * r, 0.8 * r], 12))
    thumb = _tube([(palm_width / 2 - 0.01, -0.1 * palm_length, r), (palm_width / 2 + 0.35 * palm_length, 0.3 * palm_length, r)], [r, 0.85 * r], 12)
    return _union([palm, thumb] + fingers)


def spray_bottle(radius: float, height: float) -> Solid:
    """Bottle with a trigger head: cylinder body, neck and a box head with a nozzle on +x."""
    body = _cyl(height * 0.7, radius)
    neck = _cyl(0.02, 0.4 * radius, None, (0, 0, height * 0.7 - 0.001), 24)
    head = _box((0.06, 0.03, 0.045), (0.012, 0, height * 0.7 + 0.04))
    trigger = _box((0.012, 0.012, 0.04), (0.025, 0, height * 0.7 + 0.005))
    return _union([body, neck, head, trigger])


def _rest(solid: Solid) -> Solid:
    """`solid` moved to rest on z = 0."""
    return solid.translate((0, 0, -solid.bounding_box()[2]))


def stool(seat_radius: float, height: float, seat_thickness: float = 0.012, leg_radius: float = 0.006) -> Solid:
    """Round seat on three splayed legs."""
    seat = _cyl(seat_thickness, seat_radius, None, (0, 0, height - seat_thickness))
    legs = []
    for a in np.radians([90, 210, 330]):
        top = (0.55 * seat_radius * np.cos(a), 0.55 * seat_radius * np.sin(a), height - seat_thickness)
        foot = (0.95 * seat_radius * np.cos(a), 0.95 * seat_radius * np.sin(a), leg_radius)
        legs.append(_tube([foot, top], leg_radius, 12))
    return _rest(_union([seat] + legs))


def dumbbell(length: float, bar_radius: float, weight_radius: float, weight_width: float) -> Solid:
    """Bar along x with a disc weight at each end, lying on the discs' rims."""
    bar = _cyl_x(length, bar_radius, (0, 0, weight_radius))
    weights = [_cyl_x(weight_width, weight_radius, (s * (length - weight_width) / 2, 0, weight_radius))
               for s in (-1, 1)]
    return _union([bar] + weights)


def star(outer: float, inner: float, thickness: float, points: int = 5) -> Solid:
    """Star prism lying flat: `points` tips at radius `outer`, notches at `inner`."""
    a = np.arange(2 * points) * np.pi / points + np.pi / 2
    r = np.where(np.arange(2 * points) % 2 == 0, outer, inner)
    return mf.CrossSection([np.stack([r * np.cos(a), r * np.sin(a)], 1)]).extrude(thickness)


def pipe_cross(arm: float, radius: float) -> Solid:
    """Plus-shaped pipe fitting lying flat: four round arms of length `arm` from a centre."""
    arms = [_cyl_x(2 * arm, radius, (0, 0, radius)), _cyl_x(2 * arm, radius, (0, 0, radius)).rotate((0, 0, 90))]
    caps = [_sphere(1.15 * radius, (0, 0, 1.15 * radius), 20)]
    return _rest(_union(arms + caps))


def horseshoe(radius: float, thickness: float, width: float, degrees: float = 240.0) -> Solid:
    """Flat arc of `degrees` (a horseshoe magnet's shape) of rectangular section, lying flat."""
    a = np.radians(np.linspace(-degrees / 2, degrees / 2, 25))
    outer = [(radius * np.cos(t), radius * np.sin(t)) for t in a]
    inner = [((radius - width) * np.cos(t), (radius - width) * np.sin(t)) for t in a[::-1]]
    return mf.CrossSection([np.array(outer + inner)]).extrude(thickness)


def arch(radius: float, width: float, depth: float) -> Solid:
    """Half ring standing on its two feet (a toy bridge), `depth` thick along y."""
    a = np.radians(np.linspace(0, 180, 25))
    outer = [(radius * np.cos(t), radius * np.sin(t)) for t in a]
    inner = [((radius - width) * np.cos(t), (radius - width) * np.sin(t)) for t in a[::-1]]
    section = mf.CrossSection([np.array(outer + inner)]).extrude(depth)
    return section.translate((0, 0, -depth / 2)).rotate((90, 0, 0))


def jack(arm: float, rod_radius: float, ball_radius: float) -> Solid:
    """Toy jack: three orthogonal rods with balls on their ends, resting on three balls."""
    tips = [np.eye(3)[i] * s * arm for i in range(3) for s in (-1, 1)]
    rods = [_tube([tips[2 * i], tips[2 * i + 1]], rod_radius, 12) for i in range(3)]
    balls = [_sphere(ball_radius, t, 16) for t in tips]
    body = _union(rods + balls).rotate((0, 0, 45)).rotate((np.degrees(np.arctan(np.sqrt(2))), 0, 0))
    return _rest(body)


def chair(seat: float, height: float, back: float, leg: float = 0.007) -> Solid:
    """Toy chair: square seat on four legs with a backrest on -y."""
    t = 0.01
    top = _box((seat, seat, t), (0, 0, height - t / 2))
    legs = [_box((leg * 2, leg * 2, height - t), (sx * (seat / 2 - leg), sy * (seat / 2 - leg), (height - t) / 2))
            for sx in (-1, 1) for sy in (-1, 1)]
    rest = _box((seat, t, back), (0, -seat / 2 + t / 2, height + back / 2 - 0.001))
    return _union([top, rest] + legs)


def cactus(radius: float, height: float, arm_radius: float) -> Solid:
    """Potted-cactus toy: an upright stem with two arms that bend upwards."""
    stem = _tube([(0, 0, radius), (0, 0, height - radius)], radius, 16)
    base = _cyl(radius, radius, None, seg=24)
    arms = [_tube([(0, 0, 0.45 * height), (s * 2.2 * radius, 0, 0.45 * height), (s * 2.2 * radius, 0, (0.65 + 0.1 * s) * height)],
                  arm_radius, 12) for s in (-1, 1)]
    return _union([stem, base] + arms)


def scissors(length: float, ring_radius: float, thickness: float = 0.006) -> Solid:
    """Closed scissors lying flat: two blades along +x and two finger rings behind the pivot."""
    blade = mf.CrossSection([np.array([(0, -0.009), (length, -0.001), (length, 0.001), (0, 0.009)])]).extrude(thickness)
    rings = []
    for s in (-1, 1):
        c = (-ring_radius * 1.1, s * ring_radius * 0.95, 0)
        ring = _cyl(thickness, ring_radius, None, c, 24) - _cyl(3 * thickness, 0.6 * ring_radius, None, (c[0], c[1], -thickness), 24)
        rings.append(ring)
    return _union([blade] + rings)


def hourglass(radius: float, height: float, waist: float) -> Solid:
    """Solid hourglass: two cones joined at a narrow waist between flat end discs."""
    h, d = height, 0.012
    return _revolve([(0, 0), (radius, 0), (radius, d), (waist, h / 2), (radius, h - d), (radius, h), (0, h)])


def bell(radius: float, height: float, handle_length: float) -> Solid:
    """Hand bell resting on its rim: a flared hollow body with a handle on top."""
    t = 0.004
    outer = [(radius, 0.0), (0.75 * radius, 0.35 * height), (0.55 * radius, 0.8 * height), (0.35 * radius, height)]
    inner = [(0.35 * radius - t, height - t), (0.55 * radius - t, 0.8 * height - t), (0.75 * radius - t, 0.35 * height),
             (radius - t, 0.0)]
    body = _revolve(outer + [(0, height), (0, height - t)] + inner)
    handle = _cyl(handle_length, 0.011, 0.009, (0, 0, height - 0.002), 20)
    return _union([body, handle, _sphere(0.013, (0, 0, height + handle_length), 16)])


# ---------------------------------------------------------------- registry
SPLITS = ("train", "unseen", "validation", "near")


@dataclass(frozen=True)
class Recipe:
    """One named object: a builder with its parameters, a category and a split."""

    name: str
    category: str
    split: str
    builder: Callable[..., Solid]
    params: dict[str, Any] = field(default_factory=dict)

    def build(self) -> Solid:
        return self.builder(**self.params)


def _recipes() -> dict[str, Recipe]:
    out: dict[str, Recipe] = {}

    def add(name: str, category: str, split: str, builder: Callable[..., Solid], **params: Any):
        out[name] = Recipe(name, category, split, builder, params)

    tr, un, va, ne = "train", "unseen", "validation", "near"
    add("cup_tall", "cup", tr, cup, radius_bottom=0.03, radius_top=0.04, height=0.12)
    add("cup_short", "cup", tr, cup, radius_bottom=0.035, radius_top=0.045, height=0.08)
    add("bottle_water", "bottle", tr, bottle, radius=0.033, height=0.22, neck_radius=0.013, neck_length=0.05)
    add("bottle_wine", "bottle", tr, bottle, radius=0.037, height=0.25, neck_radius=0.012, neck_length=0.09)
    add("bottle_small", "bottle", tr, bottle, radius=0.028, height=0.15, neck_radius=0.011, neck_length=0.035)
    add("box_cube", "box", tr, box, sx=0.07, sy=0.07, sz=0.07)
    add("box_cereal", "box", tr, box, sx=0.16, sy=0.05, sz=0.22)
    add("box_flat", "box", tr, box, sx=0.12, sy=0.08, sz=0.035)
    add("box_bar", "box", tr, box, sx=0.2, sy=0.045, sz=0.045)
    add("sphere_small", "sphere", tr, sphere, radius=0.03)
    add("sphere_medium", "sphere", tr, sphere, radius=0.045)
    add("sphere_large", "sphere", tr, sphere, radius=0.06)
    add("cylinder_thin", "cylinder", tr, cylinder, radius=0.02, height=0.18)
    add("cylinder_wide", "cylinder", tr, cylinder, radius=0.05, height=0.08)
    add("cylinder_lying", "cylinder", tr, cylinder, radius=0.03, height=0.16, lying=True)
    add("torus_thin", "torus", tr, torus, major=0.06, minor=0.015)
    add("torus_fat", "torus", tr, torus, major=0.045, minor=0.025)
    add("pyramid_tri", "pyramid", tr, pyramid, base=0.14, height=0.1, sides=3)
    add("pyramid_large", "pyramid", tr, pyramid, base=0.14, height=0.12, sides=4)
    add("pyramid_hex", "pyramid", tr, pyramid, base=0.07, height=0.12, sides=6)
    add("banana", "banana", tr, banana, arc_radius=0.13, arc_degrees=90, radius=0.018)
    add("banana_straight", "banana", tr, banana, arc_radius=0.3, arc_degrees=35, radius=0.02)
    add("hammer", "hammer", tr, hammer, handle_length=0.2, handle_radius=0.013, head=(0.03, 0.1, 0.03))
    add("hammer_mallet", "hammer", tr, hammer, handle_length=0.17, handle_radius=0.012, head=(0.05, 0.09, 0.05))
    add("knife_chef", "knife", tr, knife, blade_length=0.14, blade_width=0.035, handle_length=0.1)
    add("knife_small", "knife", tr, knife, blade_length=0.09, blade_width=0.02, handle_length=0.08)
    add("plate_dinner", "plate", tr, plate, radius=0.11, height=0.022)
    add("plate_side", "plate", tr, plate, radius=0.08, height=0.018)
    add("book_novel", "book", tr, book, width=0.13, depth=0.2, thickness=0.03)
    add("book_thin", "book", tr, book, width=0.15, depth=0.21, thickness=0.012)
    add("can_soda", "can", tr, can, radius=0.033, height=0.122)
    add("can_food", "can", tr, can, radius=0.042, height=0.11)
    add("cone_tall", "cone", tr, cone, radius=0.04, height=0.15)
    add("cone_frustum", "cone", tr, cone, radius=0.06, height=0.08, top_radius=0.03)
    add("capsule_short", "capsule", tr, capsule, radius=0.025, length=0.12)
    add("capsule_long", "capsule", tr, capsule, radius=0.018, length=0.2)
    add("wine_glass", "wine_glass", tr, wine_glass, bowl_radius=0.04, stem_height=0.08, bowl_height=0.09)
    add("wine_glass_flute", "wine_glass", tr, wine_glass, bowl_radius=0.03, stem_height=0.09, bowl_height=0.12)
    add("teapot", "teapot", tr, teapot, radius=0.07, height=0.12)
    add("bowl_deep", "bowl", tr, bowl, radius=0.07, height=0.07)
    add("bowl_shallow", "bowl", tr, bowl, radius=0.09, height=0.045)
    add("flashlight", "flashlight", tr, flashlight, body_radius=0.015, length=0.18, head_radius=0.022)
    add("vase", "vase", tr, vase, radius=0.05, height=0.2, waves=1.5)
    add("prism_tri", "prism", tr, prism, side=0.06, length=0.16)
    add("prism_wedge", "prism", tr, prism, side=0.1, length=0.08)
    add("egg_large", "ellipsoid", tr, ellipsoid, a=0.06, b=0.045, c=0.04)
    add("ellipsoid_flat", "ellipsoid", tr, ellipsoid, a=0.09, b=0.05, c=0.025)
    add("hex_prism", "hex_prism", tr, hex_prism, radius=0.035, height=0.12)
    add("phone", "phone", tr, phone, width=0.075, length=0.15, thickness=0.009)
    add("mouse", "mouse", tr, mouse, length=0.11, width=0.065, height=0.04)
    add("wrench", "wrench", tr, wrench, length=0.17, head_radius=0.02)
    add("lightbulb", "lightbulb", tr, lightbulb, bulb_radius=0.032, base_radius=0.014, base_height=0.03)
    add("l_block", "l_block", tr, l_block, length=0.14, width=0.04, thickness=0.035)

    add("mug", "mug", ne, mug, radius=0.04, height=0.1, handle_reach=0.035)
    add("mug_wide", "mug", ne, mug, radius=0.05, height=0.085, handle_reach=0.03)
    add("camera", "camera", ne, camera, body=(0.12, 0.06, 0.075), lens_radius=0.03, lens_length=0.045)
    add("binoculars", "binoculars", ne, binoculars, tube_radius=0.025, length=0.12, gap=0.012)
    add("apple", "apple", ne, apple, radius=0.04)
    add("pear", "pear", ne, pear, radius=0.036, height=0.11)
    add("toothpaste", "toothpaste", ne, toothpaste, length=0.16, radius=0.018, crimp_width=0.05)
    add("frying_pan", "frying_pan", ne, frying_pan, radius=0.07, depth=0.03, handle_length=0.095)
    add("toothbrush", "toothbrush", ne, toothbrush, length=0.18, width=0.012, bristle_height=0.012)
    add("elephant", "elephant", ne, elephant, body_length=0.12)
    add("hand", "hand", ne, hand, palm_length=0.09, palm_width=0.08)
    add("pyramid_small", "pyramid", ne, pyramid, base=0.06, height=0.05, sides=4)
    add("spray_bottle", "spray_bottle", ne, spray_bottle, radius=0.035, height=0.2)

    add("stool", "stool", un, stool, seat_radius=0.045, height=0.08)
    add("stool_bar", "stool", un, stool, seat_radius=0.035, height=0.12)
    add("dumbbell", "dumbbell", un, dumbbell, length=0.16, bar_radius=0.011, weight_radius=0.035, weight_width=0.025)
    add("star", "star", un, star, outer=0.07, inner=0.024, thickness=0.016)
    add("pipe_cross", "pipe_cross", un, pipe_cross, arm=0.065, radius=0.011)
    add("horseshoe", "horseshoe", un, horseshoe, radius=0.06, thickness=0.016, width=0.018)
    add("arch", "arch", un, arch, radius=0.07, width=0.025, depth=0.035)
    add("jack", "jack", un, jack, arm=0.06, rod_radius=0.007, ball_radius=0.013)

    add("chair", "chair", va, chair, seat=0.07, height=0.07, back=0.06)
    add("cactus", "cactus", va, cactus, radius=0.018, height=0.15, arm_radius=0.012)
    add("scissors", "scissors", va, scissors, length=0.11, ring_radius=0.022)
    add("hourglass", "hourglass", va, hourglass, radius=0.04, height=0.13, waist=0.012)
    add("bell", "bell", va, bell, radius=0.05, height=0.08, handle_length=0.06)
    return out


RECIPES: dict[str, Recipe] = _recipes()


def recipe_names(split: str | None = None) -> list[str]:
    """Names of the recipes, optionally only those of one split (SPLITS)."""
    return sorted(n for n, r in RECIPES.items() if split is None or r.split == split)


def get_recipe(name: str) -> Recipe:
    """The recipe called `name`; UnknownNameError lists the valid names."""
    if name not in RECIPES:
        raise UnknownNameError("object recipe", name, RECIPES)
    return RECIPES[name]


def to_trimesh(solid: Solid) -> trimesh.Trimesh:
    """Convert a manifold3d solid to a trimesh (no processing beyond vertex merge)."""
    mesh = solid.to_mesh()
    return trimesh.Trimesh(np.asarray(mesh.vert_properties[:, :3], dtype=float), np.asarray(mesh.tri_verts), process=True)


def build_mesh(name: str) -> trimesh.Trimesh:
    """Build recipe `name` in the object frame: origin at the centre of mass, z up, resting pose."""
    mesh = to_trimesh(get_recipe(name).build())
    mesh.apply_translation(-mesh.center_mass)
    return mesh
