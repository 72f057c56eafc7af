"""Narrow phase: contact points between planes, spheres, capsules and boxes.

Every pair function works on one pair (no batch axis; the engine vmaps it) and returns a
`Contacts` with a fixed, static number P of point slots for its pair type:

    pair                 P   slots
    plane-sphere         1   the sphere's lowest point
    plane-capsule        2   the two end spheres (slot 0: local -z end, slot 1: +z end)
    plane-box            8   the eight corners, in a fixed order (_CORNER_SIGNS)
    sphere-sphere        1
    sphere-capsule       1
    sphere-box           1
    capsule-capsule      2   deepest pair of axis points; for parallel axes (|sin| < 0.02) both
                             ends of their overlap
    capsule-box          2   deepest axis point; for an axis parallel to a face (|sin| < 0.02)
                             both ends of the part of the axis over that face
    box-box              8   face contact: vertices of the clipped contact polygon (<= 8), in a
                             fixed order; edge contact: one point; plus the nearest corner pair
                             when the boxes are apart across a corner

Conventions (shared by all pairs, the contact constraint of DBD (84) with i = b, j = a):

- `point_a` (P, 3) is a world point on shape a's surface, `point_b` (P, 3) one on b's surface.
- `normal` (P, 3) is a unit vector from a to b: the direction in which b must move to separate.
- `distance` (P,) is the signed separation along the normal (negative = penetration depth), so
  that `point_b = point_a + distance * normal`, i.e. `distance = (point_b - point_a) . normal`.
- `active` (P,) is True where the slot holds a point for this configuration AND
  `distance < margin` (margin >= 0, metres: speculative contacts; `detect` keeps a slot also
  where its points were closer than the margin at the start of the substep).
- For plane pairs a is the plane; the plane is {x : n . x = d}, solid where n . x < d.
- Slots that are not active still hold finite numbers (meaningless where the slot is invalid).
- Depth semantics: for sphere, capsule and box pairs the deepest distance is the exact signed
  distance (the gap apart, minus the minimum translation distance overlapping). Capsule-box
  defines it by the deepest point of the capsule axis (box SDF along the axis, minus the radius),
  which is the same until the axis itself enters the box. Every capsule slot is a sphere of the
  capsule at an axis point against the other shape: when the axis is inside the box (penetration
  deeper than the radius) and the box normal there is not perpendicular to the axis, point_a is on
  that sphere rather than on the capsule's outer surface.
- A penetrating box-box edge-edge point whose closest points sit at an edge end keeps its two surface points
  and the edge-axis normal, so point_b = point_a + distance * normal holds only along the normal.

Shapes are given by their world pose: position (3,) and unit quaternion (4,) in (w, x, y, z),
already composed from the body pose and the shape's local pose. A capsule's axis is its local z
axis. Every point is computed relative to shape a's (or the box's) centre and only then offset by
that centre, so precision does not degrade far from the world origin more than it has to.

Differentiability: every normalisation or division that can meet zero uses the double-`where`
form, so values and gradients are finite at coincident centres, parallel axes, aligned faces and
identical poses. Discrete choices (which face, which slot) go to the first index on ties and use
biased tolerances (no hysteresis, no state), so a box resting on a box or a plane gets the same
slots frame after frame. Discrete picks are one-hot masks and masked sums rather than argmax and
gathers: under vmap and grad those become scatters that compile and run slowly on CPU.

`collide(kind_a, kind_b, size_a, pos_a, quat_a, size_b, pos_b, quat_b, margin)` dispatches on
static kinds PLANE, SPHERE, CAPSULE, BOX with one uniform signature; `num_points(kind_a, kind_b)`
gives P. In that signature a shape's `size` is (3,): sphere (radius, -, -), capsule
(radius, half_length, -), box half extents; a plane's size is ignored and its normal is the local
z axis of its pose, offset = normal . position (`plane_pose` builds such a pose).
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dbdjax.indexing import take
from dbdjax.math import (
    any_perpendicular,
    cross,
    quat_multiply,
    quat_rotate,
    quat_rotate_inverse,
    safe_norm,
    safe_normalize,
    safe_sqrt,
)
from dbdjax.model import with_world_row

PLANE, SPHERE, CAPSULE, BOX = 0, 1, 2, 3
KIND_NAMES = {PLANE: "plane", SPHERE: "sphere", CAPSULE: "capsule", BOX: "box"}

# Below this |sin(angle)|^2 two directions are treated as parallel (float32 rounding of a unit
# dot product is ~1e-7, so 1e-6 keeps the line-line solve well conditioned).
_PARALLEL_SIN2 = 1e-6
# Below this |component| a segment is parallel to a slab of the box frame.
_PARALLEL_COMPONENT = 1e-6
# A second capsule point is only made when the overlap it spans exceeds this fraction of the radii,
# so perpendicular crossings do not report the same point twice.
_MIN_SPREAD = 0.1
# Two capsule points (the ends of a line contact) are made when the capsule axis is parallel to the
# other axis or to the box face within this |sin(angle)|. Beyond it the contact is a single point:
# a second point at the far end would not lie on both surfaces (its error is radius * angle^2 / 2,
# 3e-5 m for a 15 cm radius at this angle).
_TWO_POINT_SIN = 0.02
# Box-box: relative and absolute (times the mean half extent) tolerances of the separating-axis
# choice. A face axis of b must beat the best face axis of a, and an edge axis the best face, by
# this much (Gregorius, "Robust contact creation for physics simulations", GDC 2015): the bias
# makes resting stacks keep one reference face instead of flipping on rounding noise.
_SAT_RELATIVE = 0.002
_SAT_FACE_ABSOLUTE = 1e-4
_SAT_EDGE_ABSOLUTE = 5e-4
# Below this |A_i x B_j|^2 an edge-edge axis is skipped (parallel edges: a face axis covers it).
_EDGE_AXIS_SIN2 = 1e-6
# Box-box face clipping tolerance (times the mean half extent): incident vertices this far outside
# the reference face still count as inside, reference corners must be this far inside the
# incident face. It keeps exactly aligned stacks at their four incident corners.
_CLIP_TOLERANCE = 1e-4


class Contacts(NamedTuple):
    """Contact slots of one shape pair (P points, P static per pair type).

    point_a: (P, 3) world point on shape a's surface, m.
    point_b: (P, 3) world point on shape b's surface, m.
    normal: (P, 3) unit normal from a to b (the direction b must move to separate).
    distance: (P,) signed separation along `normal`, m (negative = penetration);
        point_b = point_a + distance * normal.
    active: (P,) bool, the slot holds a point for this configuration and distance < margin.
    """

    point_a: jnp.ndarray
    point_b: jnp.ndarray
    normal: jnp.ndarray
    distance: jnp.ndarray
    active: jnp.ndarray


# ----------------------------------------------------------------------------------------------
# Helpers (candidates for dbdjax.math: _safe_divide, _normalize_or)
# ----------------------------------------------------------------------------------------------


def _safe_divide(numerator: jnp.ndarray, denominator: jnp.ndarray, eps: float, default: float = 0.0) -> jnp.ndarray:
    """numerator / denominator where |denominator| > eps, else `default`; finite gradient both ways."""
    ok = jnp.abs(denominator) > eps
    return jnp.where(ok, numerator / jnp.where(ok, denominator, 1.0), default)


def _normalize_or(v: jnp.ndarray, fallback: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(unit vector, norm) of v (..., 3); where v is zero the unit vector is `fallback` and norm 0."""
    unit, length = safe_normalize(v)
    return jnp.where((length > 0.0)[..., None], unit, fallback), length


def _first_max(v: jnp.ndarray) -> jnp.ndarray:
    """One-hot bool (n,) of the first largest entry of v (n,): exactly one entry is true.

    The index comes from one argmax and is compared with each position, never used to index (a
    gather, whose transpose under grad is a scatter). Not `v >= max(v)`: XLA may compute v once
    for the max and again, fused into the comparison, rounded differently, and then no entry
    passes. It did, compiled without the fusion emitters at LLVM -O0: a capsule's deepest point
    in a box came back as its centre, 0.11 m too shallow (tests/test_collision.py's deep
    penetration cases, session 70).
    """
    return jnp.arange(v.shape[0]) == jnp.argmax(v)


def _first_max3(v: jnp.ndarray) -> jnp.ndarray:
    """One-hot (..., 3) bool of the first largest of the last-axis components, by comparisons."""
    v0, v1, v2 = v[..., 0], v[..., 1], v[..., 2]
    is0 = (v0 >= v1) & (v0 >= v2)
    is1 = ~is0 & (v1 >= v2)
    return jnp.stack([is0, is1, ~is0 & ~is1], axis=-1)


def _max3(v: jnp.ndarray) -> jnp.ndarray:
    return jnp.maximum(jnp.maximum(v[..., 0], v[..., 1]), v[..., 2])


def _dot(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Dot product over the last axis as one reduction.

    math.dot's component-wise form fuses in the solver, but here, over arrays of candidate points,
    its slices (pads under grad) made the box-box gradient 25% slower to compile on CPU.
    """
    return jnp.sum(a * b, axis=-1)


def _matvec(matrix: jnp.ndarray, vector: jnp.ndarray) -> jnp.ndarray:
    """matrix (..., 3, 3) times vector (..., 3), as a reduction (see `_dot`)."""
    return jnp.sum(matrix * vector[..., None, :], axis=-1)


def _select(values: jnp.ndarray, one_hot: jnp.ndarray) -> jnp.ndarray:
    """The row of values (n, ...) marked by one_hot (n,), as a masked sum (elementwise, fuses).

    `where` rather than a product keeps inf/NaN of the other rows out of value and gradient.
    """
    mask = one_hot.reshape((-1,) + (1,) * (values.ndim - 1))
    return jnp.sum(jnp.where(mask, values, 0), axis=0).astype(values.dtype)


def _axes(quat: jnp.ndarray) -> jnp.ndarray:
    """Rows are the world directions of the local x, y, z axes of pose `quat` (4,) -> (3, 3)."""
    return quat_rotate(quat[None, :], jnp.eye(3, dtype=quat.dtype))


def _to_world(axes: jnp.ndarray, local: jnp.ndarray) -> jnp.ndarray:
    """Local vectors (..., 3) in the frame whose axes are the rows of `axes` -> world vectors."""
    return jnp.sum(local[..., :, None] * axes, axis=-2)


def _z_axis(quat: jnp.ndarray) -> jnp.ndarray:
    return quat_rotate(quat, jnp.array([0.0, 0.0, 1.0], dtype=quat.dtype))


def _make(point_a, point_b, normal, distance, valid, margin) -> Contacts:
    return Contacts(point_a, point_b, normal, distance, valid & (distance < margin))


def _sphere_pair(centre_a, radius_a, centre_b, radius_b, fallback):
    """Closest points of two spheres (any leading shape). Returns (point_a, point_b, normal, distance)."""
    normal, length = _normalize_or(centre_b - centre_a, fallback)
    radius_a = jnp.asarray(radius_a)[..., None]
    radius_b = jnp.asarray(radius_b)[..., None]
    return (
        centre_a + radius_a * normal,
        centre_b - radius_b * normal,
        normal,
        length - radius_a[..., 0] - radius_b[..., 0],
    )


def _point_box(x: jnp.ndarray, half: jnp.ndarray):
    """Closest surface point of the box |x_i| <= half_i to local points x (..., 3).

    Returns (surface point (..., 3), outward unit normal there (..., 3), signed distance (...)).
    Inside, the surface point is on the face of least depth (ties: lowest axis index, + side).
    """
    q = jnp.abs(x) - half
    distance_in = _max3(q)
    outside = distance_in > 0.0
    clamped = jnp.clip(x, -half, half)
    normal_out, distance_out = safe_normalize(x - clamped)
    on_k = _first_max3(q)
    sign = jnp.where(jnp.sum(jnp.where(on_k, x, 0.0), axis=-1, keepdims=True) >= 0.0, 1.0, -1.0)
    point_in = jnp.where(on_k, sign * half, x)
    normal_in = jnp.where(on_k, sign, 0.0).astype(x.dtype)
    return (
        jnp.where(outside[..., None], clamped, point_in),
        jnp.where(outside[..., None], normal_out, normal_in),
        jnp.where(outside, distance_out, distance_in),
    )


def _box_sdf(x: jnp.ndarray, half: jnp.ndarray) -> jnp.ndarray:
    """Signed distance of local points x (..., 3) to the box |x_i| <= half_i (exact, convex)."""
    q = jnp.abs(x) - half
    return safe_normalize(jnp.maximum(q, 0.0))[1] + jnp.minimum(_max3(q), 0.0)


# ----------------------------------------------------------------------------------------------
# Plane pairs (a = plane)
# ----------------------------------------------------------------------------------------------


def _plane_points(normal, offset, points_b, depth_offset, valid, margin) -> Contacts:
    """Points of b given as deepest points `points_b` (P, 3) against the plane n . x = offset."""
    distance = _dot(points_b, normal) - offset - depth_offset
    point_b = points_b - depth_offset[..., None] * normal
    point_a = points_b - (distance + depth_offset)[..., None] * normal
    normals = jnp.broadcast_to(normal, point_b.shape)
    return _make(point_a, point_b, normals, distance, valid, margin)


def plane_sphere(normal, offset, pos, radius, margin) -> Contacts:
    """Plane {n . x = offset} (a) against a sphere (b). P = 1.

    normal (3,) unit, offset m, pos (3,) sphere centre, radius m, margin m.
    """
    centres = pos[None, :]
    radii = jnp.broadcast_to(jnp.asarray(radius, pos.dtype), (1,))
    return _plane_points(normal, offset, centres, radii, jnp.ones(1, bool), margin)


def plane_capsule(normal, offset, pos, quat, radius, half_length, margin) -> Contacts:
    """Plane (a) against a capsule (b): its two end spheres. P = 2 (slot 0: -z end, slot 1: +z end).

    normal (3,), offset m, pos (3,), quat (4,) capsule pose, radius, half_length m, margin m.
    """
    axis = _z_axis(quat)
    ends = pos + jnp.array([-1.0, 1.0], pos.dtype)[:, None] * half_length * axis
    radii = jnp.broadcast_to(jnp.asarray(radius, pos.dtype), (2,))
    return _plane_points(normal, offset, ends, radii, jnp.ones(2, bool), margin)


_CORNER_SIGNS = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))  # (8, 3), fixed order


def plane_box(normal, offset, pos, quat, half_extents, margin) -> Contacts:
    """Plane (a) against a box (b): its eight corners, slot i = corner with signs _CORNER_SIGNS[i]. P = 8.

    normal (3,), offset m, pos (3,), quat (4,) box pose, half_extents (3,) m, margin m.
    """
    corners = pos + _to_world(_axes(quat), jnp.asarray(_CORNER_SIGNS, pos.dtype) * half_extents)
    return _plane_points(normal, offset, corners, jnp.zeros(8, pos.dtype), jnp.ones(8, bool), margin)


# ----------------------------------------------------------------------------------------------
# Sphere pairs (a = sphere)
# ----------------------------------------------------------------------------------------------


def sphere_sphere(pos_a, radius_a, pos_b, radius_b, margin) -> Contacts:
    """Sphere a against sphere b. P = 1. Coincident centres get the normal +z.

    pos_a, pos_b (3,) centres, radius_a, radius_b m, margin m.
    """
    fallback = jnp.array([0.0, 0.0, 1.0], pos_a.dtype)
    point_a, point_b, normal, distance = _sphere_pair(0.0 * pos_a, radius_a, pos_b - pos_a, radius_b, fallback)
    return _make(
        (pos_a + point_a)[None], (pos_a + point_b)[None], normal[None], distance[None], jnp.ones(1, bool), margin
    )


def sphere_capsule(pos_a, radius_a, pos_b, quat_b, radius_b, half_length_b, margin) -> Contacts:
    """Sphere a against capsule b (axis = local z of quat_b, half length along it). P = 1.

    A centre on the capsule axis gets a normal perpendicular to the axis.
    """
    axis = _z_axis(quat_b)
    d = pos_b - pos_a  # capsule centre relative to the sphere centre
    t = jnp.clip(-_dot(axis, d), -half_length_b, half_length_b)
    closest = d + t * axis
    point_a, point_b, normal, distance = _sphere_pair(0.0 * d, radius_a, closest, radius_b, any_perpendicular(axis))
    return _make(
        (pos_a + point_a)[None], (pos_a + point_b)[None], normal[None], distance[None], jnp.ones(1, bool), margin
    )


def _sphere_box_local(x, radius, half):
    """Spheres of centres x (..., 3) (box frame) against the box.

    Returns (point on sphere, point on box, unit normal sphere -> box, signed distance).
    """
    box_point, outward, centre_distance = _point_box(x, half)
    return x - radius * outward, box_point, -outward, centre_distance - radius


def sphere_box(pos_a, radius_a, pos_b, quat_b, half_extents_b, margin) -> Contacts:
    """Sphere a against box b. P = 1. A centre inside the box leaves through its nearest face.

    pos_a (3,), radius_a m, pos_b (3,), quat_b (4,), half_extents_b (3,) m, margin m.
    """
    axes = _axes(quat_b)
    x = _matvec(axes, pos_a - pos_b)
    point_a, point_b, normal, distance = _sphere_box_local(x, radius_a, half_extents_b)
    return _make(
        (pos_b + _to_world(axes, point_a))[None],
        (pos_b + _to_world(axes, point_b))[None],
        _to_world(axes, normal)[None],
        distance[None],
        jnp.ones(1, bool),
        margin,
    )


# ----------------------------------------------------------------------------------------------
# Capsule pairs
# ----------------------------------------------------------------------------------------------


def _two_slots(star, lo, hi, wide, line_contact):
    """Slot assignment of a capsule contact from its deepest axis parameter `star` and an interval [lo, hi].

    Slot 0 covers the lower half of [lo, hi], slot 1 the upper half. A line contact (`wide` and
    `line_contact`: axis parallel to the other axis or face) uses both: the half holding `star`
    gets `star`, the other its outer end (lo for slot 0, hi for slot 1), so a parallel pair whose
    deepest point flips between the ends on rounding noise keeps the same two points in the same
    slots. Otherwise only the slot of the half holding `star` is valid.
    Returns (star_in_0, valid (2,) bool).
    """
    star_in_0 = (star <= 0.5 * (lo + hi)) | ~wide
    both = wide & line_contact
    return star_in_0, jnp.stack([both | star_in_0, both | ~star_in_0])


def _closest_on_segments(d, u_a, half_a, u_b, half_b):
    """Closest points of segments s u_a (s in [-half_a, half_a]) and d + t u_b (t in [-half_b, half_b]).

    Returns (s*, b, c, f, lo, hi): the parameter of a deepest point on a, the dot products used to
    map s to t (t = clip(b s + f)), and the shadow [lo, hi] of segment b on segment a. Exactly
    parallel segments give s* = lo (deterministic). Ericson, Real-Time Collision Detection 5.1.9.
    """
    b = _dot(u_a, u_b)
    c = -_dot(u_a, d)  # u_a . (centre_a - centre_b)
    f = -_dot(u_b, d)  # u_b . (centre_a - centre_b)
    spread = half_b * jnp.abs(b)
    lo = jnp.clip(-c - spread, -half_a, half_a)
    hi = jnp.clip(-c + spread, -half_a, half_a)
    denominator = 1.0 - b * b
    parallel = denominator <= _PARALLEL_SIN2
    s_line = _safe_divide(b * f - c, denominator, _PARALLEL_SIN2)
    s = jnp.clip(jnp.where(parallel, lo, s_line), -half_a, half_a)
    t = jnp.clip(b * s + f, -half_b, half_b)
    star = jnp.clip(b * t - c, -half_a, half_a)
    return star, b, c, f, lo, hi


def capsule_capsule(pos_a, quat_a, radius_a, half_length_a, pos_b, quat_b, radius_b, half_length_b, margin) -> Contacts:
    """Capsule a against capsule b. P = 2.

    Slots 0 and 1 split the shadow of b's axis on a's axis in two halves; the half holding the
    deepest pair of axis points gets it. Capsules parallel within |sin| < 0.02 whose overlap is
    longer than 0.1 (r_a + r_b) make a line contact: the other half then gets the pair at its outer
    end (a's axis point there and its closest point on b's axis), so they rest on both ends of
    their overlap; otherwise only the deepest pair is valid. Intersecting axes use the normal along
    u_a x u_b, coincident parallel axes one perpendicular to u_a.

    pos_* (3,), quat_* (4,) (axis = local z), radius_*, half_length_* m, margin m.
    """
    u_a, u_b = _z_axis(quat_a), _z_axis(quat_b)
    d = pos_b - pos_a
    star, b, _, f, lo, hi = _closest_on_segments(d, u_a, half_length_a, u_b, half_length_b)
    wide = (hi - lo) > _MIN_SPREAD * (radius_a + radius_b)
    star_in_0, valid = _two_slots(star, lo, hi, wide, 1.0 - b * b <= _TWO_POINT_SIN**2)
    s = jnp.stack([jnp.where(star_in_0, star, lo), jnp.where(star_in_0, hi, star)])
    t = jnp.clip(b * s + f, -half_length_b, half_length_b)
    on_a = s[:, None] * u_a
    on_b = d + t[:, None] * u_b
    fallback, crossing = safe_normalize(cross(u_a, u_b))
    fallback = jnp.where(crossing > 0.0, fallback, any_perpendicular(u_a))
    point_a, point_b, normal, distance = _sphere_pair(on_a, radius_a, on_b, radius_b, fallback)
    return _make(pos_a + point_a, pos_a + point_b, normal, distance, valid, margin)


# Candidate parameters for the deepest point of a segment in a box (see _deepest_in_box).
_EDGE_AXIS = np.repeat(np.arange(3), 4)  # (12,) axis each box edge runs along
_EDGE_SIGNS = np.array([(s1, s2) for _ in range(3) for s1 in (-1.0, 1.0) for s2 in (-1.0, 1.0)])
_EDGE_MIDPOINT_SIGNS = np.zeros((12, 3))
for _index, _axis in enumerate(_EDGE_AXIS):
    _EDGE_MIDPOINT_SIGNS[_index, (_axis + 1) % 3] = _EDGE_SIGNS[_index, 0]
    _EDGE_MIDPOINT_SIGNS[_index, (_axis + 2) % 3] = _EDGE_SIGNS[_index, 1]
_FACE_AXIS = np.repeat(np.arange(3), 2)  # the six faces: axis and side
_FACE_SIDE = np.tile(np.array([-1.0, 1.0]), 3)
_FACE_PAIRS = np.array(list(itertools.combinations(range(6), 2)))  # (15, 2)
_EDGE_SELECT = np.eye(3)[_EDGE_AXIS]  # (12, 3): x[_EDGE_AXIS] as a product, no gather
_FACE_SELECT = np.eye(3)[_FACE_AXIS]  # (6, 3)
_PAIR_DIFFERENCE = np.eye(6)[_FACE_PAIRS[:, 1]] - np.eye(6)[_FACE_PAIRS[:, 0]]  # (15, 6): v[n] - v[m]


def _deepest_in_box(c, u, half_length, half):
    """Parameter t in [-half_length, half_length] minimising the box SDF along c + t u (box frame).

    The SDF of a convex box is convex, so along a segment its minimum is at an end or at a
    critical point of one of its pieces: outside, the closest approach to an edge line (12) or the
    foot of a vertex (8); inside, where two of the six face planes are equally deep (15). All 37
    candidates are evaluated exactly; ties go to the first (ends first).
    """
    vertices = jnp.asarray(_CORNER_SIGNS, c.dtype) * half
    t_vertex = _dot(vertices - c, u)
    midpoints = jnp.asarray(_EDGE_MIDPOINT_SIGNS, c.dtype) * half
    w = c - midpoints
    edge_select = jnp.asarray(_EDGE_SELECT, c.dtype)
    b = _dot(edge_select, u)
    w_along = _dot(edge_select, w)
    w_dot_u = _dot(w, u)
    t_edge = jnp.where(
        1.0 - b * b > _PARALLEL_SIN2, _safe_divide(b * w_along - w_dot_u, 1.0 - b * b, _PARALLEL_SIN2), -w_dot_u
    )
    # face plane m: side_m * (c + t u)[axis_m] - half[axis_m]; kink where two of them are equal
    face_select, face_side = jnp.asarray(_FACE_SELECT, c.dtype), jnp.asarray(_FACE_SIDE, c.dtype)
    offsets = face_side * _dot(face_select, c) - _dot(face_select, half)
    slopes = face_side * _dot(face_select, u)
    difference = jnp.asarray(_PAIR_DIFFERENCE, c.dtype)
    t_kink = _safe_divide(jnp.sum(difference * offsets, -1), -jnp.sum(difference * slopes, -1), _PARALLEL_COMPONENT)
    ends = jnp.stack([-half_length, half_length]).astype(c.dtype)
    candidates = jnp.clip(jnp.concatenate([ends, t_edge, t_vertex, t_kink]), -half_length, half_length)
    depth = _box_sdf(c + candidates[:, None] * u, half)
    return _select(candidates, _first_max(-depth))


def _slab_interval(c, u, half, half_length):
    """Per axis (3,): the parameters [lo, hi] of c + t u, t in [-half_length, half_length], with |x_i| <= half_i."""
    moving = jnp.abs(u) > _PARALLEL_COMPONENT
    inverse = 1.0 / jnp.where(moving, u, 1.0)
    t1 = (-half - c) * inverse
    t2 = (half - c) * inverse
    within = jnp.abs(c) <= half
    lo = jnp.where(moving, jnp.minimum(t1, t2), jnp.where(within, -half_length, half_length))
    hi = jnp.where(moving, jnp.maximum(t1, t2), jnp.where(within, half_length, -half_length))
    return jnp.maximum(lo, -half_length), jnp.minimum(hi, half_length)


def capsule_box(pos_a, quat_a, radius_a, half_length_a, pos_b, quat_b, half_extents_b, margin) -> Contacts:
    """Capsule a against box b. P = 2.

    Every slot is the sphere of the capsule at one axis point against the box (exact closest
    points). t* is the deepest axis point (exact box SDF along the axis); [lo, hi] is the part of
    the axis over the reference face (the face the normal at t* leaves through; shrunk by the depth
    of t* when the axis is inside the box, so those spheres still leave through that face). An axis
    parallel to that face within |sin| < 0.02, with [lo, hi] longer than 0.1 radius, makes a line
    contact: slots 0 and 1 hold lo and hi (the deepest of a linear depth profile is one of them).
    Otherwise the slot of the half of [lo, hi] holding t* holds t* and the other is invalid. Edge
    and corner contacts are single points; a capsule parallel to a box edge it lies on is a single
    point too (it balances on a ridge).

    pos_a (3,), quat_a (4,), radius_a, half_length_a m, pos_b (3,), quat_b (4,),
    half_extents_b (3,) m, margin m.
    """
    axes = _axes(quat_b)
    u = _matvec(axes, _z_axis(quat_a))
    c = _matvec(axes, pos_a - pos_b)
    half = half_extents_b
    star = _deepest_in_box(c, u, half_length_a, half)
    _, outward, star_depth = _point_box(c + star * u, half)
    on_k = _first_max3(jnp.abs(outward))
    shrink = jnp.where(star_depth < 0.0, _CLIP_TOLERANCE * jnp.mean(half) - star_depth, 0.0)
    lo3, hi3 = _slab_interval(c, u, half - shrink, half_length_a)
    lo = jnp.max(jnp.where(on_k, -half_length_a, lo3))
    hi = jnp.min(jnp.where(on_k, half_length_a, hi3))
    wide = (hi - lo) > _MIN_SPREAD * radius_a
    points = c + jnp.stack([star, lo, hi])[:, None] * u
    on_capsule, on_box, normal, distance = _sphere_box_local(points, radius_a, half)
    # parallel to the face: both ends, unless the deepest point lies elsewhere (overhang)
    tilt = jnp.abs(jnp.sum(jnp.where(on_k, u, 0.0)))
    ends_deepest = jnp.minimum(distance[1], distance[2]) <= distance[0] + 1e-5 * (radius_a + half_length_a)
    face_mode = tilt < _TWO_POINT_SIN
    star_in_0, valid = _two_slots(star, lo, hi, wide, face_mode & ends_deepest)
    # a line contact along the face uses the two ends (its deepest point is one of them)
    face_mode = face_mode & ends_deepest & wide
    first = jnp.stack([star_in_0 & ~face_mode, ~star_in_0 | face_mode, jnp.zeros_like(wide)])  # of (t*, lo, hi)
    second = jnp.stack([~(star_in_0 | face_mode), jnp.zeros_like(wide), star_in_0 | face_mode])

    def pick(values):
        return jnp.stack([_select(values, first), _select(values, second)])

    return _make(
        pos_b + _to_world(axes, pick(on_capsule)),
        pos_b + _to_world(axes, pick(on_box)),
        _to_world(axes, pick(normal)),
        pick(distance),
        valid,
        margin,
    )


# ----------------------------------------------------------------------------------------------
# Box-box
# ----------------------------------------------------------------------------------------------

_QUAD_SIGNS = np.array([(1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0)])  # cyclic face corners


def _face_manifold(n, centre_r, axes_r, half_r, k, centre_i, axes_i, half_i, tolerance):
    """Clip the incident face of box I against the reference face k (one-hot (3,)) of box R (outward normal n).

    Candidates (12): for each of the 4 incident edges, the start and the exit point of the edge
    clipped to the reference rectangle (grown by `tolerance`), then the 4 reference corners that
    lie inside the incident face (by `tolerance`). The valid ones are the vertices of the contact
    polygon (at most 8). Returns (point on R, point on I, separation along n, valid), each (12, ...).
    """
    ku, kv = jnp.roll(k, 1), jnp.roll(k, 2)  # one-hot of (k + 1) % 3 and (k + 2) % 3
    u_r, v_r, a, b = _select(axes_r, ku), _select(axes_r, kv), _select(half_r, ku), _select(half_r, kv)
    face_r = centre_r + _select(half_r, k) * n
    along = _matvec(axes_i, n)
    j = _first_max3(jnp.abs(along))
    side_i = jnp.where(_select(along, j) > 0.0, -1.0, 1.0)  # the incident face looks back at R
    normal_i = side_i * _select(axes_i, j)
    ju, jv = jnp.roll(j, 1), jnp.roll(j, 2)
    u_i, v_i, half_u, half_v = _select(axes_i, ju), _select(axes_i, jv), _select(half_i, ju), _select(half_i, jv)
    face_i = centre_i + _select(half_i, j) * normal_i
    signs = jnp.asarray(_QUAD_SIGNS, n.dtype)
    vertices = face_i + signs[:, :1] * half_u * u_i + signs[:, 1:] * half_v * v_i  # (4, 3)
    following = jnp.roll(vertices, -1, axis=0)
    x0, y0 = _dot(vertices - face_r, u_r), _dot(vertices - face_r, v_r)
    dx, dy = _dot(following - vertices, u_r), _dot(following - vertices, v_r)
    a_grown, b_grown = a + tolerance, b + tolerance
    # Liang-Barsky: p t <= q for the four sides of the reference rectangle
    p = jnp.stack([-dx, dx, -dy, dy], axis=-1)
    q = jnp.stack([x0 + a_grown, a_grown - x0, y0 + b_grown, b_grown - y0], axis=-1)
    moving = jnp.abs(p) > 1e-6 * tolerance
    ratio = q / jnp.where(moving, p, 1.0)
    t0 = jnp.maximum(jnp.max(jnp.where(moving & (p < 0.0), ratio, 0.0), axis=-1), 0.0)
    t1 = jnp.minimum(jnp.min(jnp.where(moving & (p > 0.0), ratio, 1.0), axis=-1), 1.0)
    blocked = jnp.any(~moving & (q < 0.0), axis=-1)
    nonempty = (t0 <= t1) & ~blocked
    starts = vertices + t0[:, None] * (following - vertices)
    exits = vertices + t1[:, None] * (following - vertices)
    clipped = jnp.stack([starts, exits], axis=1).reshape(8, 3)
    clipped_valid = jnp.stack([nonempty, nonempty & (t1 < 1.0) & (t1 > t0)], axis=1).reshape(8)
    clipped_separation = _dot(clipped - face_r, n)
    # reference corners projected along n onto the incident face plane (|normal_i . n| >= 1/sqrt 3)
    corners = face_r + signs[:, :1] * a * u_r + signs[:, 1:] * b * v_r
    corner_separation = _dot(face_i - corners, normal_i) / _dot(normal_i, n)
    corners_on_i = corners + corner_separation[:, None] * n
    local = corners_on_i - face_i
    corner_valid = (jnp.abs(_dot(local, u_i)) < half_u - tolerance) & (jnp.abs(_dot(local, v_i)) < half_v - tolerance)
    on_r = jnp.concatenate([clipped - clipped_separation[:, None] * n, corners])
    on_i = jnp.concatenate([clipped, corners_on_i])
    separation = jnp.concatenate([clipped_separation, corner_separation])
    valid = jnp.concatenate([clipped_valid, corner_valid])
    return on_r, on_i, separation, valid


def _closest_corner_pair(d, axes_a, half_a, axes_b, half_b):
    """The corner of either box nearest to the other box (16 exact point-box distances).

    Coordinates relative to a's centre; b's centre is d. Returns (point on a, point on b, unit
    normal a -> b, distance). Exact box-box distance whenever a closest pair has a corner in it.
    """
    signs = jnp.asarray(_CORNER_SIGNS, d.dtype)
    corners_a = _to_world(axes_a, signs * half_a)
    corners_b = d + _to_world(axes_b, signs * half_b)
    on_b, out_b, distance_a = _point_box(_matvec(axes_b[None], corners_a - d), half_b)  # a's corners vs b
    on_a, out_a, distance_b = _point_box(_matvec(axes_a[None], corners_b), half_a)  # b's corners vs a
    points_a = jnp.concatenate([corners_a, _to_world(axes_a, on_a)])
    points_b = jnp.concatenate([d + _to_world(axes_b, on_b), corners_b])
    normals = jnp.concatenate([-_to_world(axes_b, out_b), _to_world(axes_a, out_a)])
    distance = jnp.concatenate([distance_a, distance_b])
    best = _first_max(-distance)
    return _select(points_a, best), _select(points_b, best), _select(normals, best), _select(distance, best)


def box_box(pos_a, quat_a, half_extents_a, pos_b, quat_b, half_extents_b, margin) -> Contacts:
    """Box a against box b. P = 8.

    Separating axes: the 3 + 3 face normals and the 9 edge cross products (parallel edges
    skipped); the axis of largest separation wins, with a bias toward a's faces, then b's faces,
    then edges (`_SAT_*`). Face axis: the incident face of the other box is clipped against the
    reference face; the polygon vertices (<= 8) fill the slots in a fixed order (incident edge by
    edge: start, exit; then reference corners), each with the reference normal. Edge axis: slot 0
    holds the closest points of the two edges, normal along the edge cross product (when apart:
    along the gap between the two points). Apart across a corner, the closest pair has a corner
    in it and the separating axes miss it: the corner nearest to the other box (16 exact
    point-box distances) then takes the first free slot, so the gap is exact in every regime.

    pos_* (3,), quat_* (4,), half_extents_* (3,) m, margin m.
    """
    axes_a, axes_b = _axes(quat_a), _axes(quat_b)
    half_a, half_b = half_extents_a, half_extents_b
    d = pos_b - pos_a  # all geometry relative to a's centre
    scale = (jnp.sum(half_a) + jnp.sum(half_b)) / 6.0
    overlap = jnp.abs(_dot(axes_a[:, None, :], axes_b[None, :, :]))  # |A_i . B_j|
    separation_a = jnp.abs(_dot(axes_a, d)) - half_a - jnp.sum(overlap * half_b, axis=1)
    separation_b = jnp.abs(_dot(axes_b, d)) - half_b - jnp.sum(overlap * half_a[:, None], axis=0)
    edge_axes, edge_length = safe_normalize(cross(axes_a[:, None, :], axes_b[None, :, :]).reshape(9, 3))
    edge_ok = edge_length * edge_length > _EDGE_AXIS_SIN2
    radius_a = jnp.sum(jnp.abs(_dot(edge_axes[:, None, :], axes_a[None])) * half_a, axis=1)
    radius_b = jnp.sum(jnp.abs(_dot(edge_axes[:, None, :], axes_b[None])) * half_b, axis=1)
    separation_e = jnp.where(edge_ok, jnp.abs(_dot(edge_axes, d)) - radius_a - radius_b, -jnp.inf)
    ia, ib, ie = _first_max3(separation_a), _first_max3(separation_b), _first_max(separation_e)
    best_a, best_b, best_e = jnp.max(separation_a), jnp.max(separation_b), jnp.max(separation_e)
    use_b = best_b > best_a + _SAT_RELATIVE * jnp.abs(best_a) + _SAT_FACE_ABSOLUTE * scale
    best_face = jnp.where(use_b, best_b, best_a)
    use_edge = best_e > best_face + _SAT_RELATIVE * jnp.abs(best_face) + _SAT_EDGE_ABSOLUTE * scale

    # face contact: reference box R, incident box I (coordinates relative to a's centre)
    zero = jnp.zeros_like(d)
    centre_r, centre_i = jnp.where(use_b, d, zero), jnp.where(use_b, zero, d)
    axes_r, axes_i = jnp.where(use_b, axes_b, axes_a), jnp.where(use_b, axes_a, axes_b)
    half_r, half_i = jnp.where(use_b, half_b, half_a), jnp.where(use_b, half_a, half_b)
    k = jnp.where(use_b, ib, ia)
    n = _select(axes_r, k)
    n = n * jnp.where(_dot(n, centre_i - centre_r) >= 0.0, 1.0, -1.0)
    tolerance = _CLIP_TOLERANCE * scale
    on_r, on_i, separation, valid = _face_manifold(n, centre_r, axes_r, half_r, k, centre_i, axes_i, half_i, tolerance)
    # compact: the valid candidates fill slots 0, 1, ... in their fixed order (at most 8 are valid)
    rank = jnp.cumsum(valid) - 1
    select = valid[None, :] & (rank[None, :] == jnp.arange(8)[:, None])  # (8 slots, 12 candidates)
    on_r = jnp.sum(jnp.where(select[..., None], on_r[None], 0.0), axis=1)
    on_i = jnp.sum(jnp.where(select[..., None], on_i[None], 0.0), axis=1)
    separation = jnp.sum(jnp.where(select, separation[None], 0.0), axis=1)
    valid = jnp.any(select, axis=1)
    face_a = jnp.where(use_b, on_i, on_r)
    face_b = jnp.where(use_b, on_r, on_i)
    face_normal = jnp.broadcast_to(jnp.where(use_b, -n, n), face_a.shape)

    # edge contact: closest points of the supporting edges of a (along A_i) and b (along B_j)
    i_edge, j_edge = jnp.any(ie.reshape(3, 3), axis=1), jnp.any(ie.reshape(3, 3), axis=0)  # ie = 3 i + j
    axis = _select(edge_axes, ie)
    axis = axis * jnp.where(_dot(axis, d) >= 0.0, 1.0, -1.0)
    towards_b = jnp.where(_dot(axes_a, axis) >= 0.0, 1.0, -1.0) * ~i_edge
    towards_a = jnp.where(_dot(axes_b, axis) >= 0.0, -1.0, 1.0) * ~j_edge
    edge_centre_a = _to_world(axes_a, towards_b * half_a)
    edge_centre_b = d + _to_world(axes_b, towards_a * half_b)
    u_a, u_b = _select(axes_a, i_edge), _select(axes_b, j_edge)
    length_a, length_b = _select(half_a, i_edge), _select(half_b, j_edge)
    s, b_dot, _, f, _, _ = _closest_on_segments(edge_centre_b - edge_centre_a, u_a, length_a, u_b, length_b)
    t = jnp.clip(b_dot * s + f, -length_b, length_b)
    edge_a = edge_centre_a + s * u_a
    edge_b = edge_centre_b + t * u_b
    # penetrating: depth along the axis; apart: the true gap of the two edge points (clamped ends
    # are not aligned with the axis, and a corner pair below may then be nearer)
    edge_distance = _dot(edge_b - edge_a, axis)
    gap_normal, gap = _normalize_or(edge_b - edge_a, axis)
    apart = edge_distance > 0.0
    edge_normal = jnp.where(apart, gap_normal, axis)
    edge_distance = jnp.where(apart, gap, edge_distance)

    first = jnp.arange(8) == 0
    point_a = jnp.where(use_edge & first[:, None], edge_a, face_a)
    point_b = jnp.where(use_edge & first[:, None], edge_b, face_b)
    normal = jnp.where(use_edge & first[:, None], edge_normal, face_normal)
    distance = jnp.where(use_edge & first, edge_distance, separation)
    valid = jnp.where(use_edge, first, valid)

    # The axes' points are exact where a face or edge interior holds a closest pair. When the boxes
    # are apart across a corner (or clipping found nothing) the nearest corner pair is closer:
    # it takes the first free slot (or the slot of largest distance).
    corner_a, corner_b, corner_normal, corner_distance = _closest_corner_pair(d, axes_a, half_a, axes_b, half_b)
    slot_distance = jnp.where(valid, distance, jnp.inf)
    empty = ~jnp.any(valid)
    closer = (corner_distance > 0.0) & (corner_distance < jnp.min(slot_distance) - tolerance)
    target = _first_max(slot_distance) & (empty | closer)
    point_a = jnp.where(target[:, None], corner_a, point_a)
    point_b = jnp.where(target[:, None], corner_b, point_b)
    normal = jnp.where(target[:, None], corner_normal, normal)
    distance = jnp.where(target, corner_distance, distance)
    valid = valid | target
    return _make(pos_a + point_a, pos_a + point_b, normal, distance, valid, margin)


# ----------------------------------------------------------------------------------------------
# Dispatch with one uniform signature
# ----------------------------------------------------------------------------------------------


def plane_pose(normal, offset) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(position (3,), quaternion (4,)) of a plane pose whose local z axis is `normal` (unit) and
    whose origin is offset * normal: the form in which `collide` reads planes."""
    normal = jnp.asarray(normal)
    # shortest arc from +z to n: (1 + n_z, -n_y, n_x, 0) normalised; n = -z turns half a turn about x
    raw = jnp.stack([1.0 + normal[2], -normal[1], normal[0], 0.0 * normal[0]])
    squared = jnp.sum(raw * raw)
    flipped = squared <= 1e-12
    quat = raw / jnp.sqrt(jnp.where(flipped, 1.0, squared))
    quat = jnp.where(flipped, jnp.array([0.0, 1.0, 0.0, 0.0], raw.dtype), quat)
    return offset * normal, quat


def _plane_of(pos, quat):
    normal = _z_axis(quat)
    return normal, _dot(normal, pos)


Collider = Callable[..., Contacts]

# uniform signature: (size_a, pos_a, quat_a, size_b, pos_b, quat_b, margin) -> Contacts
_COLLIDERS: dict[tuple[int, int], tuple[Collider, int]] = {
    (PLANE, SPHERE): (lambda sa, pa, qa, sb, pb, qb, margin: plane_sphere(*_plane_of(pa, qa), pb, sb[0], margin), 1),
    (PLANE, CAPSULE): (
        lambda sa, pa, qa, sb, pb, qb, margin: plane_capsule(*_plane_of(pa, qa), pb, qb, sb[0], sb[1], margin),
        2,
    ),
    (PLANE, BOX): (lambda sa, pa, qa, sb, pb, qb, margin: plane_box(*_plane_of(pa, qa), pb, qb, sb, margin), 8),
    (SPHERE, SPHERE): (lambda sa, pa, qa, sb, pb, qb, margin: sphere_sphere(pa, sa[0], pb, sb[0], margin), 1),
    (SPHERE, CAPSULE): (
        lambda sa, pa, qa, sb, pb, qb, margin: sphere_capsule(pa, sa[0], pb, qb, sb[0], sb[1], margin),
        1,
    ),
    (SPHERE, BOX): (lambda sa, pa, qa, sb, pb, qb, margin: sphere_box(pa, sa[0], pb, qb, sb, margin), 1),
    (CAPSULE, CAPSULE): (
        lambda sa, pa, qa, sb, pb, qb, margin: capsule_capsule(pa, qa, sa[0], sa[1], pb, qb, sb[0], sb[1], margin),
        2,
    ),
    (CAPSULE, BOX): (
        lambda sa, pa, qa, sb, pb, qb, margin: capsule_box(pa, qa, sa[0], sa[1], pb, qb, sb, margin),
        2,
    ),
    (BOX, BOX): (lambda sa, pa, qa, sb, pb, qb, margin: box_box(pa, qa, sa, pb, qb, sb, margin), 8),
}


def num_points(kind_a: int, kind_b: int) -> int:
    """Static number of contact slots P of a pair of shape kinds (either order); 0 for plane-plane."""
    if (kind_a, kind_b) == (PLANE, PLANE):
        return 0
    key = (kind_a, kind_b) if (kind_a, kind_b) in _COLLIDERS else (kind_b, kind_a)
    if key not in _COLLIDERS:
        raise ValueError(f"unknown shape kinds {kind_a}, {kind_b}")
    return _COLLIDERS[key][1]


def flip(contacts: Contacts) -> Contacts:
    """The same contacts seen with a and b exchanged (points swapped, normal negated)."""
    return Contacts(contacts.point_b, contacts.point_a, -contacts.normal, contacts.distance, contacts.active)


def collide(kind_a: int, kind_b: int, size_a, pos_a, quat_a, size_b, pos_b, quat_b, margin) -> Contacts:
    """Contacts of shape a against shape b for static kinds (PLANE, SPHERE, CAPSULE, BOX), any order.

    size_* (3,): sphere (radius, -, -), capsule (radius, half_length, -), box half extents, plane
    ignored (its normal is the local z axis of quat, offset = normal . pos). pos_* (3,),
    quat_* (4,) world poses, margin m. Returns `num_points(kind_a, kind_b)` slots with the
    conventions of this module (normal from a to b).
    """
    if (kind_a, kind_b) in _COLLIDERS:
        function, _ = _COLLIDERS[(kind_a, kind_b)]
        return function(size_a, pos_a, quat_a, size_b, pos_b, quat_b, margin)
    if (kind_b, kind_a) in _COLLIDERS:
        function, _ = _COLLIDERS[(kind_b, kind_a)]
        return flip(function(size_b, pos_b, quat_b, size_a, pos_a, quat_a, margin))
    raise ValueError(f"no collision between {KIND_NAMES.get(kind_a, kind_a)} and {KIND_NAMES.get(kind_b, kind_b)}")


# ----------------------------------------------------------------------------------------------
# Detection over a model's contact groups (once per substep, at the predicted poses X*)
# ----------------------------------------------------------------------------------------------


class ContactSlots(NamedTuple):
    """The contacts of one contact group for one substep: C pairs x P points, fixed shapes.

    local_a, local_b: (C, P, 3) the contact points fixed in the bodies' frames (world
      coordinates for a world side), found at the predicted pose X*.
    normal: (C, P, 3) unit, from a to b, world frame, kept fixed over the substep.
    offset: (C, P, 3) p_b - p_a of those body points at the start of the substep: friction holds
      p_b - p_a at this value in the contact plane (no sliding over the substep, DBD (89)).
    approach: (C, P) normal speed (v_b - v_a) . n of the points before the solve (the predicted
      velocities V*, gravity included), m/s, negative when closing: what restitution reverses.
    sliding: (C, P) bool, the points were sliding over each other at the start of the substep
      (tangential speed above g h, the speed one substep of gravity gives): their friction is
      bounded by mu_d, otherwise by mu_s (DBD 7.1).
    active: (C, P) bool, a slot whose points are closer than the contact margin at X* or at the
      start of the substep (the solve can move a body far from its prediction: a body resting on
      the floor that a joint drags down).
    friction, dynamic_friction, restitution: (C,) the pair's combined material:
      sqrt(mu_1 mu_2) for both frictions and max(e_1, e_2), as Box2D combines them.
    allowed_depth: (C, P) m, how deep the point may still be at the end of the substep: what is
      left of the penetration it began the substep in after pushing it out by
      `Options.depenetration_speed` h (0 for a point that began outside).
    pushout_speed: (C, P) m/s, the normal speed that pushing it out of that penetration gives it
      (its depth at the start, at most depenetration_speed h, over h): what the restitution pass
      may take back.
    """

    local_a: jnp.ndarray
    local_b: jnp.ndarray
    normal: jnp.ndarray
    offset: jnp.ndarray
    approach: jnp.ndarray
    sliding: jnp.ndarray
    active: jnp.ndarray
    friction: jnp.ndarray
    dynamic_friction: jnp.ndarray
    restitution: jnp.ndarray
    allowed_depth: jnp.ndarray
    pushout_speed: jnp.ndarray


def detect(model, start, predicted, h: float) -> tuple[ContactSlots, ...]:
    """Contact slots of every contact group of `model` at the predicted poses.

    start: the `State` at the start of the substep; predicted: X*, V* (integrator.predict);
    h: the substep, s.
    Returns one `ContactSlots` per `model.structure.contact_groups` entry.
    """
    structure, shapes = model.structure, model.shapes
    dtype = predicted.pos.dtype
    identity = jnp.array([1.0, 0.0, 0.0, 0.0], dtype)
    # row N is the world: shapes on it are posed in world coordinates
    pos = with_world_row(predicted.pos, 0.0)
    quat = with_world_row(predicted.quat, identity)
    start_pos = with_world_row(start.pos, 0.0)
    start_quat = with_world_row(start.quat, identity)
    vel = with_world_row(predicted.vel, 0.0)
    ang_vel = with_world_row(predicted.ang_vel, 0.0)
    start_vel = with_world_row(start.vel, 0.0)
    start_ang_vel = with_world_row(start.ang_vel, 0.0)
    creep = safe_norm(model.gravity) * h  # below this tangential speed a contact is sticking
    result = []
    for group in structure.contact_groups:
        shape = group.shapes.array  # (C, 2)
        body = group.bodies.array  # (C, 2)
        side = [{"body": body[:, k], "shape": shape[:, k]} for k in (0, 1)]
        for s in side:
            local_quat = shapes.local_quat[s["shape"]]
            s["size"] = shapes.size[s["shape"]]
            body_quat = take(quat, s["body"])
            s["pos"] = take(pos, s["body"]) + quat_rotate(body_quat, shapes.local_pos[s["shape"]])
            s["quat"] = quat_multiply(body_quat, local_quat)

        a, b = side
        one_pair = functools.partial(collide, group.kind_a, group.kind_b)
        # margin inf: `active` is every slot that holds a point; the margin is applied below
        contacts = jax.vmap(one_pair, in_axes=(0, 0, 0, 0, 0, 0, None))(
            a["size"], a["pos"], a["quat"], b["size"], b["pos"], b["quat"], jnp.inf
        )

        def body_point(s, point):
            """The world point (C, P, 3) as a point fixed in the body: local coordinates, its arm
            at the start of the substep, its predicted velocity and its velocity at the start."""
            body = s["body"]
            origin, orientation = take(pos, body)[:, None], take(quat, body)[:, None]
            local = quat_rotate_inverse(orientation, point - origin)
            start_arm = quat_rotate(take(start_quat, body)[:, None], local)
            speed = take(vel, body)[:, None] + cross(take(ang_vel, body)[:, None], point - origin)
            start_speed = take(start_vel, body)[:, None] + cross(take(start_ang_vel, body)[:, None], start_arm)
            return local, start_arm, speed, start_speed

        local_a, start_arm_a, speed_a, start_speed_a = body_point(a, contacts.point_a)
        local_b, start_arm_b, speed_b, start_speed_b = body_point(b, contacts.point_b)
        offset = (take(start_pos, b["body"]) - take(start_pos, a["body"]))[:, None] + (start_arm_b - start_arm_a)
        # Speculative slots: a point closer than the margin at X* or where it began the substep. The
        # solve moves bodies away from X* (joints drag them), and a point found at X* alone missed
        # what it was dragged into: over 10,000 pushed ragdoll steps (tests/test_ragdoll.py) an
        # upper arm went 41.5 mm into the floor (the deepest now: 12.8 mm); a case that replays: an
        # upper arm 4.8 mm above the floor, out of the margin at X*, dragged 32 mm into it.
        start_gap = _dot(offset, contacts.normal)
        active = contacts.active & (jnp.minimum(contacts.distance, start_gap) < model.options.contact_margin)
        relative = start_speed_b - start_speed_a
        tangential = relative - _dot(relative, contacts.normal)[..., None] * contacts.normal
        friction = safe_sqrt(shapes.friction[shape[:, 0]] * shapes.friction[shape[:, 1]])
        dynamic = safe_sqrt(shapes.dynamic_friction[shape[:, 0]] * shapes.dynamic_friction[shape[:, 1]])
        restitution = jnp.maximum(shapes.restitution[shape[:, 0]], shapes.restitution[shape[:, 1]])
        # Penetration recovery at a bounded speed (as Box2D's contact push speed and PhysX's
        # depenetration velocity): pushed out in one substep, a point that began it inside the other
        # shape leaves at depth / h, and at large depths or small h that is a kick. (Brax's ant
        # landing with a foot 47 mm in the floor: at 4 substeps the whole tree solve threw its
        # torso up at 10 m/s; MuJoCo's soft contacts, from the same state: 4.2 m/s.)
        depth = jnp.maximum(-start_gap, 0.0)  # (C, P) at the start of the substep
        pushout = jnp.minimum(depth, model.options.depenetration_speed * h)
        result.append(
            ContactSlots(
                local_a=local_a,
                local_b=local_b,
                normal=contacts.normal,
                offset=offset,
                approach=_dot(speed_b - speed_a, contacts.normal),
                sliding=safe_norm(tangential) > creep,
                active=active,
                friction=friction,
                dynamic_friction=dynamic,
                restitution=restitution,
                allowed_depth=depth - pushout,
                pushout_speed=pushout / h,
            )  # fmt: skip
        )
    return tuple(result)
