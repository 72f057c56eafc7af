"""Narrow phase (dbdjax.collision) against brute-force geometry.

The reference is the exact signed distance of the two shapes (the gap when apart, minus the
penetration depth, the minimum translation distance, when overlapping), computed in numpy
float64 by code that shares nothing with the engine: planes and spheres analytically; capsules by
sampling the axis densely (coarse, then fine around the best sample: the distance is convex along
it) against the other shape's analytic distance; boxes by the 15 separating axes when they
overlap and by corner-to-box distances and edge-pair closest approaches when apart. For
capsule-box the depth is that of the deepest axis point (the contact definition), the same as the
penetration depth while the axis is outside the box.

Every pair type is compiled once per dtype: the cases are stacked into one vmapped call of a
fixed batch.
"""

from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dbdjax import collision as C

MARGIN = 0.03
SEED = 0
BATCH = 64  # every call is padded to this batch, so each pair type compiles once per dtype
SPHERE_SIZE = np.array([0.3, 0.0, 0.0])
CAPSULE_SIZE = np.array([0.15, 0.4, 0.0])
BOX_SIZE = np.array([0.4, 0.3, 0.2])
BOX_SIZE_B = np.array([0.25, 0.35, 0.15])
SIZES = {"sphere": SPHERE_SIZE, "capsule": CAPSULE_SIZE, "box": BOX_SIZE}
KINDS = {"plane": C.PLANE, "sphere": C.SPHERE, "capsule": C.CAPSULE, "box": C.BOX}
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


# ------------------------------------------------------------------------------------------------
# numpy reference geometry
# ------------------------------------------------------------------------------------------------


def quat_about(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def quat_product(p, q):
    pw, pv, qw, qv = p[0], p[1:], q[0], q[1:]
    return np.concatenate([[pw * qw - pv @ qv], pw * qv + qw * pv + np.cross(pv, qv)])


def quat_between(u, v):
    """Shortest rotation taking unit u to unit v."""
    u, v = np.asarray(u, float) / np.linalg.norm(u), np.asarray(v, float) / np.linalg.norm(v)
    q = np.concatenate([[1.0 + u @ v], np.cross(u, v)])
    return q / np.linalg.norm(q)


def random_quat(rng):
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def matrices(quats):
    """(..., 4) unit quaternions -> (..., 3, 3) rotation matrices (columns = local axes)."""
    w, x, y, z = np.moveaxis(np.asarray(quats, float), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def support_radius(kind, size, rotation, n):
    """Support half-width of a centred shape along unit directions n (..., 3)."""
    if kind == "sphere":
        return np.full(n.shape[:-1], size[0])
    if kind == "capsule":
        return size[0] + size[1] * np.abs(n @ rotation[:, 2])
    return np.abs(n @ rotation) @ size


def box_sdf(local, half):
    q = np.abs(local) - half
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)


def segment_distance(points, centre, axis, half_length):
    t = np.clip((points - centre) @ axis, -half_length, half_length)
    return np.linalg.norm(points - centre - t[..., None] * axis, axis=-1)


def corners_of(pos, rotation, half):
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))
    return pos + (signs * half) @ rotation.T


def edges_of(pos, rotation, half):
    """The 12 edges as (start (12, 3), end (12, 3))."""
    starts, ends = [], []
    for axis in range(3):
        for s1, s2 in itertools.product((-1.0, 1.0), repeat=2):
            local = np.zeros(3)
            local[(axis + 1) % 3], local[(axis + 2) % 3] = s1 * half[(axis + 1) % 3], s2 * half[(axis + 2) % 3]
            for sign, out in ((-1.0, starts), (1.0, ends)):
                point = local.copy()
                point[axis] = sign * half[axis]
                out.append(pos + rotation @ point)
    return np.array(starts), np.array(ends)


def box_box_distance(c):
    """Exact signed distance of two boxes.

    Overlapping (no separating axis): minus the smallest overlap over the 15 axes of the
    separating-axis theorem. Apart: the nearest of the 16 corner-to-box distances and the
    interior line-line closest approaches of the 144 edge pairs.
    """
    rot_a, rot_b = matrices(c["quat_a"]), matrices(c["quat_b"])
    d = c["pos_b"] - c["pos_a"]
    axes = list(rot_a.T) + list(rot_b.T)
    for i, j in itertools.product(range(3), repeat=2):
        cross = np.cross(rot_a[:, i], rot_b[:, j])
        if np.linalg.norm(cross) > 1e-9:
            axes.append(cross / np.linalg.norm(cross))
    axes = np.array(axes)
    separation = np.abs(axes @ d) - support_radius("box", c["size_a"], rot_a, axes)
    separation -= support_radius("box", c["size_b"], rot_b, axes)
    if separation.max() <= 0.0:
        return separation.max()
    corners_a = corners_of(c["pos_a"], rot_a, c["size_a"])
    corners_b = corners_of(c["pos_b"], rot_b, c["size_b"])
    best = min(
        box_sdf((corners_a - c["pos_b"]) @ rot_b, c["size_b"]).min(),
        box_sdf((corners_b - c["pos_a"]) @ rot_a, c["size_a"]).min(),
    )
    start_a, end_a = edges_of(c["pos_a"], rot_a, c["size_a"])
    start_b, end_b = edges_of(c["pos_b"], rot_b, c["size_b"])
    u, v = (end_a - start_a)[:, None], (end_b - start_b)[None]  # (12, 1, 3), (1, 12, 3)
    w = start_a[:, None] - start_b[None]
    uu, uv, vv, uw, vw = (np.sum(x * y, axis=-1) for x, y in ((u, u), (u, v), (v, v), (u, w), (v, w)))
    det = uu * vv - uv**2
    skew = det > 1e-12
    det = np.where(skew, det, 1.0)
    s, t = (uv * vw - vv * uw) / det, (uu * vw - uv * uw) / det
    interior = skew & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
    gaps = np.linalg.norm(w + s[..., None] * u - t[..., None] * v, axis=-1)
    return min(best, np.where(interior, gaps, np.inf).min())


def reference_distance(case_list):
    """Exact signed distance (C,) of each case's shapes, numpy float64: the gap when apart, minus
    the penetration depth (minimum translation distance) when overlapping. For capsule-box it is
    the deepest point of the capsule axis in the box minus the radius (the contact definition),
    which equals the penetration depth as long as the axis stays outside the box."""
    distances = []
    for c in case_list:
        kind_a, kind_b = c["kinds"]
        rot_a, rot_b = matrices(c["quat_a"]), matrices(c["quat_b"])
        if kind_a == "plane":
            normal = rot_a[:, 2]
            rho = support_radius(kind_b, c["size_b"], rot_b, -normal)
            distances.append(normal @ (c["pos_b"] - c["pos_a"]) - rho)
        elif kind_a == "box":
            distances.append(box_box_distance(c))
        elif kind_a == "sphere" and kind_b != "capsule":
            centre = c["pos_a"][None]
            if kind_b == "sphere":
                gap = np.linalg.norm(centre - c["pos_b"], axis=-1) - c["size_b"][0]
            else:
                gap = box_sdf((centre - c["pos_b"]) @ rot_b, c["size_b"])
            distances.append(gap[0] - c["size_a"][0])
        else:  # capsule b or capsule a: densely sampled axis of a against b's analytic distance

            def gap(t, c=c, rot_a=rot_a, rot_b=rot_b):
                samples = c["pos_a"] + t[:, None] * rot_a[:, 2]
                if c["kinds"][1] == "capsule":
                    return segment_distance(samples, c["pos_b"], rot_b[:, 2], c["size_b"][1]) - c["size_b"][0]
                return box_sdf((samples - c["pos_b"]) @ rot_b, c["size_b"])

            half_length = c["size_a"][1] if kind_a == "capsule" else 0.0
            # the gap is convex along the axis: sample coarsely, then finely around the best sample
            coarse = np.linspace(-half_length, half_length, 2001)
            best = coarse[np.argmin(gap(coarse))]
            step = coarse[1] - coarse[0]
            fine = np.clip(np.linspace(best - step, best + step, 2001), -half_length, half_length)
            distances.append(gap(fine).min() - c["size_a"][0])
    return np.array(distances)


def surface_distance(kind, size, pos, quat, points):
    """Signed distance of world points (P, 3) to one shape's surface (analytic SDF)."""
    rotation = matrices(quat)
    if kind == "plane":
        return (points - pos) @ rotation[:, 2]
    if kind == "sphere":
        return np.linalg.norm(points - pos, axis=-1) - size[0]
    if kind == "capsule":
        return segment_distance(points, pos, rotation[:, 2], size[1]) - size[0]
    return box_sdf((points - pos) @ rotation, size)


# ------------------------------------------------------------------------------------------------
# running the engine on stacked cases
# ------------------------------------------------------------------------------------------------


def case(kinds, pos_a, quat_a, pos_b, quat_b, size_a=None, size_b=None, label=""):
    kind_a, kind_b = kinds
    size_a = SIZES.get(kind_a, np.zeros(3)) if size_a is None else size_a
    size_b = SIZES.get(kind_b, np.zeros(3)) if size_b is None else size_b
    return {
        "kinds": kinds,
        "size_a": np.asarray(size_a, float),
        "pos_a": np.asarray(pos_a, float),
        "quat_a": np.asarray(quat_a, float),
        "size_b": np.asarray(size_b, float),
        "pos_b": np.asarray(pos_b, float),
        "quat_b": np.asarray(quat_b, float),
        "label": label,
    }


def stacked(case_list, dtype):
    names = ["size_a", "pos_a", "quat_a", "size_b", "pos_b", "quat_b"]
    assert len(case_list) <= BATCH
    padded = case_list + [case_list[-1]] * (BATCH - len(case_list))
    return [jnp.asarray(np.array([c[name] for c in padded]), dtype) for name in names]


@functools.cache
def compiled_contacts(kind_a, kind_b):
    return jax.jit(jax.vmap(lambda *args: C.collide(kind_a, kind_b, *args, MARGIN)))


def contacts_of(case_list):
    """Contacts (numpy, float32 engine) for cases of one pair type: fields (C, P, ...)."""
    kind_a, kind_b = case_list[0]["kinds"]
    result = compiled_contacts(KINDS[kind_a], KINDS[kind_b])(*stacked(case_list, jnp.float32))
    return C.Contacts(*(np.asarray(field)[: len(case_list)] for field in result))


@functools.cache
def compiled_loss_gradients(kind_a, kind_b):
    """float64, one compile per pair type: weights . (loss_all, loss_distance) and its gradient
    w.r.t. (pos_a, quat_a, pos_b, quat_b).

    loss_all touches every output of every slot, active or not (the NaN checks); loss_distance
    is the sum of the active distances (the finite-difference checks).
    """

    def loss(pos_a, quat_a, pos_b, quat_b, size_a, size_b, weights):
        c = C.collide(kind_a, kind_b, size_a, pos_a, quat_a, size_b, pos_b, quat_b, MARGIN)
        everything = jnp.sum(c.distance) + jnp.sum(c.point_a) + jnp.sum(c.point_b) + jnp.sum(c.normal)
        return weights[0] * everything + weights[1] * jnp.sum(jnp.where(c.active, c.distance, 0.0))

    def value_and_gradient(size_a, pos_a, quat_a, size_b, pos_b, quat_b, weights):
        gradient = jax.value_and_grad(loss, argnums=(0, 1, 2, 3))
        return gradient(pos_a, quat_a, pos_b, quat_b, size_a, size_b, weights)

    # LLVM optimisation level 0 halves this compile (the backward pass of box-box is large); it
    # changes speed, not IEEE semantics, and these checks are about finite values and slopes.
    return jax.jit(jax.vmap(value_and_gradient), compiler_options={"xla_backend_optimization_level": 0})


def loss_and_gradients(case_list, weights):
    """(loss (C,), [d/d pos_a (C, 3), d/d quat_a (C, 4), d/d pos_b, d/d quat_b]) in float64."""
    with jax.enable_x64(True):
        kind_a, kind_b = case_list[0]["kinds"]
        weights = jnp.broadcast_to(jnp.asarray(weights, jnp.float64), (BATCH, 2))
        value, gradient = compiled_loss_gradients(KINDS[kind_a], KINDS[kind_b])(
            *stacked(case_list, jnp.float64), weights
        )
        count = len(case_list)
        return np.asarray(value)[:count], [np.asarray(g)[:count] for g in gradient]


# ------------------------------------------------------------------------------------------------
# the case grid: each pair type at faces, edges, corners, at several depths and gaps
# ------------------------------------------------------------------------------------------------

TARGETS = (-0.06, -0.015, 0.0, 0.012)  # signed distances inside the margin
FAR = 0.1  # beyond the margin
CORNER_DOWN = quat_between(np.array([1.0, 1.0, 1.0]), np.array([0.0, 0.0, -1.0]))
EDGE_X = quat_about([1, 0, 0], np.pi / 4)  # box edge along x on top and bottom
EDGE_Y = quat_about([0, 1, 0], np.pi / 4)
ALONG_X = quat_about([0, 1, 0], np.pi / 2)  # capsule axis along x
ALONG_Y = quat_about([1, 0, 0], np.pi / 2)
DOWN = np.array([0.0, 0.0, -1.0])
UP = np.array([0.0, 0.0, 1.0])


def orientations(pair, rng):
    """(label, quat_a, quat_b, direction from a's centre to b's centre) for one pair type."""
    r = lambda: random_quat(rng)  # noqa: E731
    unit = lambda v: np.asarray(v, float) / np.linalg.norm(v)  # noqa: E731
    if pair == "sphere-sphere":
        return [("random", r(), r(), unit(rng.normal(size=3))) for _ in range(2)]
    if pair == "sphere-capsule":
        return [
            ("capsule side", IDENTITY, IDENTITY, unit([-1, 0, 0])),
            ("capsule end", IDENTITY, IDENTITY, DOWN),
            ("capsule end rim", IDENTITY, quat_about([0, 1, 0], 0.3), unit([-0.6, 0, -1])),
            ("random", r(), r(), unit(rng.normal(size=3))),
        ]
    if pair == "sphere-box":
        return [
            ("box face", IDENTITY, IDENTITY, DOWN),
            ("box edge", IDENTITY, IDENTITY, unit([-1, 0, -1])),
            ("box corner", IDENTITY, IDENTITY, unit([-1, -1, -1])),
            ("rotated box face", IDENTITY, r(), DOWN),
            ("random", r(), r(), unit(rng.normal(size=3))),
        ]
    if pair == "capsule-capsule":
        return [
            ("parallel", ALONG_X, ALONG_X, DOWN),
            ("parallel offset", ALONG_X, ALONG_X, unit([0.5, 0, -1])),
            ("crossing", ALONG_X, ALONG_Y, DOWN),
            ("skew 30 degrees", ALONG_X, quat_product(quat_about(UP, np.pi / 6), ALONG_X), DOWN),
            ("end to end", IDENTITY, IDENTITY, DOWN),
            ("end on side", ALONG_X, IDENTITY, DOWN),
            ("random", r(), r(), unit(rng.normal(size=3))),
        ]
    if pair == "capsule-box":
        return [
            ("lying on face", ALONG_X, IDENTITY, DOWN),
            ("standing on face", IDENTITY, IDENTITY, DOWN),
            ("tilted on face", quat_about([0, 1, 0], np.pi / 2 - 0.4), IDENTITY, DOWN),
            ("across an edge", ALONG_X, EDGE_Y, DOWN),
            ("along an edge", ALONG_X, EDGE_X, DOWN),
            ("on a corner", ALONG_X, CORNER_DOWN, DOWN),
            ("end on a side face", ALONG_X, IDENTITY, unit([1, 0, 0])),
            ("random", r(), r(), unit(rng.normal(size=3))),
        ]
    if pair == "box-box":
        return [
            ("face on face", IDENTITY, IDENTITY, UP),
            ("face on face, twisted", IDENTITY, quat_about(UP, np.pi / 6), UP),
            ("face on face, offset", IDENTITY, quat_about(UP, 0.2), unit([0.6, 0.3, 1])),
            ("edge on face", IDENTITY, EDGE_X, UP),
            ("corner on face", IDENTITY, CORNER_DOWN, UP),
            ("edge on edge", EDGE_X, EDGE_Y, UP),
            ("random", r(), r(), unit(rng.normal(size=3))),
            ("random", r(), r(), unit(rng.normal(size=3))),
        ]
    raise ValueError(pair)


def place(case_list, targets):
    """Move each b along its direction from a so the reference signed distance equals its target.

    Along a ray the signed distance of two convex shapes is convex, negative at t = 0 and positive
    far out, so bisection finds the one crossing.
    """
    directions = np.array([c.pop("direction") for c in case_list])
    origins = np.array([c["pos_a"] for c in case_list])
    low, high = np.zeros(len(case_list)), np.full(len(case_list), 3.0)
    for _ in range(40):
        middle = 0.5 * (low + high)
        for c, origin, direction, t in zip(case_list, origins, directions, middle, strict=True):
            c["pos_b"] = origin + t * direction
        below = reference_distance(case_list) < targets
        low, high = np.where(below, middle, low), np.where(below, high, middle)
    for c, origin, direction, t in zip(case_list, origins, directions, high, strict=True):
        c["pos_b"] = origin + t * direction
    return case_list


@functools.cache
def grid(pair):
    """Cases of a pair type: every orientation at every target distance, plus one beyond the margin."""
    rng = np.random.default_rng(SEED + PAIRS.index(pair))
    kinds = tuple(pair.split("-"))
    if kind_is_plane := kinds[0] == "plane":
        plane_normal = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
        plane_pos, plane_quat = (np.asarray(v, float) for v in C.plane_pose(plane_normal, 0.3))
        shape_quats = {
            "sphere": [("any", random_quat(rng))],
            "capsule": [
                ("lying", quat_between([0, 0, 1], np.cross(plane_normal, [1, 0, 0]))),
                ("standing", quat_between([0, 0, 1], plane_normal)),
                ("tilted", random_quat(rng)),
            ],
            "box": [
                ("face down", quat_between([0, 0, 1], plane_normal)),
                ("edge down", quat_product(quat_between([0, 0, 1], plane_normal), EDGE_X)),
                ("corner down", quat_between([1, 1, 1], -plane_normal)),
                ("random", random_quat(rng)),
            ],
        }[kinds[1]]
    cases, targets = [], []
    for target in TARGETS + (FAR,):
        if kind_is_plane:
            for label, quat in shape_quats:
                c = case(kinds, plane_pos, plane_quat, np.zeros(3), quat, label=label)
                rho = support_radius(kinds[1], c["size_b"], matrices(quat), -plane_normal)
                lateral = np.array([0.3, -0.2, 0.1]) - (np.array([0.3, -0.2, 0.1]) @ plane_normal) * plane_normal
                c["pos_b"] = (0.3 + rho + target) * plane_normal + lateral
                cases.append(c)
                targets.append(target)
            continue
        for label, quat_a, quat_b, direction in orientations(pair, rng):
            size_b = BOX_SIZE_B if pair == "box-box" else None
            c = case(kinds, rng.normal(size=3), quat_a, np.zeros(3), quat_b, size_b=size_b, label=label)
            c["pos_b"] = c["pos_a"] + 2.0 * direction
            c["direction"] = direction
            cases.append(c)
            targets.append(target)
    if not kind_is_plane:
        place(cases, np.array(targets))
    return cases, np.array(targets)


PAIRS = [
    "plane-sphere",
    "plane-capsule",
    "plane-box",
    "sphere-sphere",
    "sphere-capsule",
    "sphere-box",
    "capsule-capsule",
    "capsule-box",
    "box-box",
]


def shifted(case_list, shifts):
    """Copies of the cases with b translated by shifts (C, 3)."""
    moved = []
    for c, shift in zip(case_list, shifts, strict=True):
        c = dict(c)
        c["pos_b"] = c["pos_b"] + shift
        moved.append(c)
    return moved


@pytest.mark.parametrize("pair", PAIRS)
def test_deepest_point_matches_brute_force_at_faces_edges_and_corners(pair):
    cases, targets = grid(pair)
    reference = reference_distance(cases)
    np.testing.assert_allclose(reference, targets, atol=1e-6)  # the placement itself
    contacts = contacts_of(cases)
    deepest = np.where(contacts.active, contacts.distance, np.inf).min(axis=1)
    near = targets < MARGIN
    labels = [f"{c['label']} at {t:+.3f}" for c, t in zip(cases, targets, strict=True)]
    for label, value, expected in zip(np.array(labels)[near], deepest[near], reference[near], strict=True):
        assert abs(value - expected) < 1e-3, (pair, label, value, expected)
    assert not contacts.active[~near].any(), "points beyond the margin must be inactive"


@pytest.mark.parametrize("pair", PAIRS)
def test_points_lie_on_the_surfaces_and_normals_separate(pair):
    cases, targets = grid(pair)
    contacts = contacts_of(cases)
    kind_a, kind_b = cases[0]["kinds"]
    for index, c in enumerate(cases):
        active = contacts.active[index]
        if not active.any():
            continue
        normal = contacts.normal[index][active]
        np.testing.assert_allclose(np.linalg.norm(normal, axis=-1), 1.0, atol=1e-5)
        point_a, point_b = contacts.point_a[index][active], contacts.point_b[index][active]
        distance = contacts.distance[index][active]
        np.testing.assert_allclose(point_b, point_a + distance[:, None] * normal, atol=2e-5)
        on_a = surface_distance(kind_a, c["size_a"], c["pos_a"], c["quat_a"], point_a)
        on_b = surface_distance(kind_b, c["size_b"], c["pos_b"], c["quat_b"], point_b)
        assert np.abs(on_a).max() < 1e-4 and np.abs(on_b).max() < 1e-4, (pair, c["label"], on_a, on_b)
    # Moving b along the deepest point's normal by -distance +- 2 mm just separates / just touches:
    # the normal is the direction b must move to separate and the distance how far.
    has = contacts.active.any(axis=1)
    deepest = np.argmin(np.where(contacts.active, contacts.distance, np.inf), axis=1)
    rows = np.arange(len(cases))[has]
    normal = contacts.normal[rows, deepest[rows]].astype(float)
    distance = contacts.distance[rows, deepest[rows]].astype(float)
    subset = [cases[i] for i in rows]
    apart = reference_distance(shifted(subset, (0.002 - distance)[:, None] * normal))
    into = reference_distance(shifted(subset, (-0.002 - distance)[:, None] * normal))
    assert (apart > 0.0).all(), [(c["label"], v) for c, v in zip(subset, apart, strict=True) if v <= 0]
    assert (into < 0.0).all(), [(c["label"], v) for c, v in zip(subset, into, strict=True) if v >= 0]


def test_collide_accepts_either_order_and_num_points_is_symmetric():
    cases, _ = grid("sphere-box")
    swapped = [dict(c, kinds=("box", "sphere")) for c in cases]
    for c in swapped:
        for first, second in (("size_a", "size_b"), ("pos_a", "pos_b"), ("quat_a", "quat_b")):
            c[first], c[second] = c[second], c[first]
    forward, backward = contacts_of(cases), contacts_of(swapped)
    np.testing.assert_allclose(backward.point_a, forward.point_b, atol=1e-6)
    np.testing.assert_allclose(backward.point_b, forward.point_a, atol=1e-6)
    np.testing.assert_allclose(backward.normal, -forward.normal, atol=1e-6)
    np.testing.assert_array_equal(backward.distance, forward.distance)
    np.testing.assert_array_equal(backward.active, forward.active)
    expected = {
        ("plane", "sphere"): 1,
        ("plane", "capsule"): 2,
        ("plane", "box"): 8,
        ("sphere", "sphere"): 1,
        ("sphere", "capsule"): 1,
        ("sphere", "box"): 1,
        ("capsule", "capsule"): 2,
        ("capsule", "box"): 2,
        ("box", "box"): 8,
    }
    for (a, b), count in expected.items():
        assert C.num_points(KINDS[a], KINDS[b]) == C.num_points(KINDS[b], KINDS[a]) == count
    assert C.num_points(C.PLANE, C.PLANE) == 0
    with pytest.raises(ValueError, match="plane and plane"):
        C.collide(C.PLANE, C.PLANE, *([jnp.zeros(3), jnp.zeros(3), jnp.array(IDENTITY)] * 2), MARGIN)


def test_plane_pose_puts_the_local_z_axis_on_the_normal():
    for normal in ([0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.6, 0.0, 0.8], [0.0, -1.0, 0.0]):
        pos, quat = C.plane_pose(jnp.asarray(normal), 0.7)
        np.testing.assert_allclose(matrices(np.asarray(quat))[:, 2], normal, atol=1e-6)
        np.testing.assert_allclose(pos, 0.7 * np.asarray(normal), atol=1e-6)


# ------------------------------------------------------------------------------------------------
# manifolds: how many points, and where
# ------------------------------------------------------------------------------------------------


def active_points(contacts, index):
    active = contacts.active[index]
    return (
        contacts.point_a[index][active],
        contacts.point_b[index][active],
        contacts.normal[index][active],
        contacts.distance[index][active],
    )


def same_point_sets(actual, expected, atol=1e-5):
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape, (actual, expected)
    gaps = np.linalg.norm(actual[:, None] - expected[None], axis=-1)
    assert (gaps.min(axis=1) < atol).all() and (gaps.min(axis=0) < atol).all(), (actual, expected)


def test_box_manifolds_at_faces_edges_and_corners():
    big = np.array([1.0, 0.8, 0.5])
    small = BOX_SIZE_B
    depth = 0.002
    twist = quat_about(UP, np.pi / 6)
    edge_drop = (small[1] + small[2]) / np.sqrt(2)  # centre height above the lowest edge of EDGE_X
    corner_drop = np.abs(matrices(CORNER_DOWN) @ np.diag(small)).sum(axis=1)[2]
    ridge = np.array([0.4, 0.4, 0.4])  # a cube turned 45 degrees has its ridge over its centre
    cases = [
        # small box resting on a big one: its four bottom corners
        case(("box", "box"), [0, 0, 0], IDENTITY, [0.2, -0.1, 0.5 + small[2] - depth], twist, big, small),
        # big box resting on a small one: the small box's four top corners (reference corners)
        case(("box", "box"), [0, 0, 0], IDENTITY, [0.1, 0.05, small[2] + 0.5 - depth], twist, small, big),
        # on an edge: its two ends
        case(("box", "box"), [0, 0, 0], IDENTITY, [0.1, 0.2, 0.5 + edge_drop - depth], EDGE_X, big, small),
        # on a corner: one point
        case(("box", "box"), [0, 0, 0], IDENTITY, [-0.2, 0.1, 0.5 + corner_drop - depth], CORNER_DOWN, big, small),
        # edge across edge: one point at the crossing
        case(("box", "box"), [0, 0, 0], EDGE_X, [0, 0, 0.8 * np.sqrt(2) - depth], EDGE_Y, ridge, ridge),
    ]
    contacts = contacts_of(cases)
    corners = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))

    # 1. the small box's bottom corners, each 2 mm deep along +z
    point_a, point_b, normal, distance = active_points(contacts, 0)
    bottom = cases[0]["pos_b"] + (corners[corners[:, 2] < 0] * small) @ matrices(twist).T
    same_point_sets(point_b, bottom)
    np.testing.assert_allclose(distance, -depth, atol=1e-5)
    np.testing.assert_allclose(normal, np.tile(UP, (4, 1)), atol=1e-6)
    np.testing.assert_allclose(point_a[:, 2], 0.5, atol=1e-6)
    # 2. the small (lower) box's top corners
    point_a, point_b, normal, distance = active_points(contacts, 1)
    same_point_sets(point_a, corners[corners[:, 2] > 0] * small)
    np.testing.assert_allclose(distance, -depth, atol=1e-5)
    np.testing.assert_allclose(normal, np.tile(UP, (4, 1)), atol=1e-6)
    # 3. both ends of the lowest edge
    point_a, point_b, normal, distance = active_points(contacts, 2)
    corners_b = cases[2]["pos_b"] + (corners * small) @ matrices(EDGE_X).T
    ends = corners_b[np.isclose(corners_b[:, 2], corners_b[:, 2].min())]
    assert len(ends) == 2
    same_point_sets(point_b, ends)
    np.testing.assert_allclose(distance, -depth, atol=1e-5)
    # 4. the lowest corner
    point_a, point_b, normal, distance = active_points(contacts, 3)
    corners_b = cases[3]["pos_b"] + (corners * small) @ matrices(CORNER_DOWN).T
    same_point_sets(point_b, corners_b[np.argmin(corners_b[:, 2])][None])
    np.testing.assert_allclose(distance, -depth, atol=1e-5)
    # 5. the ridges cross at one point, normal straight up
    point_a, point_b, normal, distance = active_points(contacts, 4)
    same_point_sets(point_a, [[0, 0, 0.4 * np.sqrt(2)]])
    np.testing.assert_allclose(normal, [UP], atol=1e-5)
    np.testing.assert_allclose(distance, -depth, atol=1e-5)


def test_capsule_line_contacts_use_both_ends_and_crossings_one_point():
    r, h = CAPSULE_SIZE[0], CAPSULE_SIZE[1]
    depth = 0.002
    slight = quat_product(quat_about(UP, 0.01), ALONG_X)  # within the two-point tolerance
    clear = quat_product(quat_about(UP, 0.1), ALONG_X)
    cases = [
        case(("capsule", "capsule"), [0, 0, 0], ALONG_X, [0.3, 0, 2 * r - depth], ALONG_X),
        case(("capsule", "capsule"), [0, 0, 0], ALONG_X, [0.0, 0, 2 * r - depth], ALONG_Y),
        case(("capsule", "capsule"), [0, 0, 0], ALONG_X, [0.3, 0, 2 * r - depth], slight),
        case(("capsule", "capsule"), [0, 0, 0], ALONG_X, [0.3, 0, 2 * r - depth], clear),
    ]
    contacts = contacts_of(cases)
    # parallel: both ends of the overlap [-0.1, 0.4] of the two axes
    point_a, point_b, normal, distance = active_points(contacts, 0)
    same_point_sets(point_a, [[-0.1, 0, r], [h, 0, r]])
    np.testing.assert_allclose(distance, -depth, atol=1e-5)
    np.testing.assert_allclose(normal, np.tile(UP, (2, 1)), atol=1e-6)
    # crossing: one point
    assert contacts.active[1].sum() == 1
    np.testing.assert_allclose(active_points(contacts, 1)[3], [-depth], atol=1e-5)
    assert contacts.active[2].sum() == 2
    assert contacts.active[3].sum() == 1


def test_capsule_on_a_box_face_touches_at_its_ends_or_the_face_border():
    r, h = CAPSULE_SIZE[0], CAPSULE_SIZE[1]
    depth = 0.002
    wide_box = np.array([0.6, 0.5, 0.3])
    cases = [
        case(("capsule", "box"), [0.05, 0.1, 0.3 + r - depth], ALONG_X, [0, 0, 0], IDENTITY, size_b=wide_box),
        case(("capsule", "box"), [0.3, 0.0, BOX_SIZE[2] + r - depth], ALONG_X, [0, 0, 0], IDENTITY),
        case(("capsule", "box"), [0.1, 0.1, BOX_SIZE[2] + h + r - depth], IDENTITY, [0, 0, 0], IDENTITY),
    ]
    contacts = contacts_of(cases)
    point_a, point_b, normal, distance = active_points(contacts, 0)
    same_point_sets(point_b, [[0.05 - h, 0.1, 0.3], [0.05 + h, 0.1, 0.3]])
    np.testing.assert_allclose(distance, -depth, atol=1e-5)
    np.testing.assert_allclose(normal, np.tile(-UP, (2, 1)), atol=1e-6)  # from the capsule into the box
    # overhanging the +x border: the far end and the face border
    point_a, point_b, normal, distance = active_points(contacts, 1)
    same_point_sets(point_b, [[0.3 - h, 0.0, BOX_SIZE[2]], [BOX_SIZE[0], 0.0, BOX_SIZE[2]]])
    np.testing.assert_allclose(distance, -depth, atol=1e-5)
    # standing: its lower end only
    point_a, point_b, normal, distance = active_points(contacts, 2)
    same_point_sets(point_b, [[0.1, 0.1, BOX_SIZE[2]]])


def test_sphere_centre_inside_a_box_leaves_through_the_nearest_face():
    r = SPHERE_SIZE[0]
    cases = [case(("sphere", "box"), [0.1, 0.05, 0.12], IDENTITY, [0, 0, 0], IDENTITY)]
    contacts = contacts_of(cases)
    point_a, point_b, normal, distance = active_points(contacts, 0)
    np.testing.assert_allclose(normal, [[0, 0, -1]], atol=1e-6)  # the box must move down
    np.testing.assert_allclose(distance, [-(BOX_SIZE[2] - 0.12) - r], atol=1e-6)
    np.testing.assert_allclose(point_b, [[0.1, 0.05, BOX_SIZE[2]]], atol=1e-6)
    np.testing.assert_allclose(point_a, [[0.1, 0.05, 0.12 - r]], atol=1e-6)


@pytest.mark.parametrize(
    "pair", ["sphere-sphere", "sphere-capsule", "sphere-box", "capsule-capsule", "capsule-box", "box-box"]
)
def test_deep_penetration_matches_brute_force(pair):
    rng = np.random.default_rng(5)
    kinds = tuple(pair.split("-"))
    size_b = BOX_SIZE_B if pair == "box-box" else None
    cases = [
        case(kinds, [0.2, -0.1, 0.3], random_quat(rng), [0.2, -0.1, 0.3] + offset, random_quat(rng), size_b=size_b)
        for offset in 0.12 * rng.normal(size=(12, 3))
    ]
    cases.append(case(kinds, [0, 0, 0], IDENTITY, [0, 0, 0], IDENTITY, size_b=size_b))  # concentric
    reference = reference_distance(cases)
    assert (reference < -0.1).all()
    contacts = contacts_of(cases)
    deepest = np.where(contacts.active, contacts.distance, np.inf).min(axis=1)
    np.testing.assert_allclose(deepest, reference, atol=1e-3)


# ------------------------------------------------------------------------------------------------
# frame-to-frame stability of resting manifolds (float32)
# ------------------------------------------------------------------------------------------------


def perturbed(base, rng, count, size=1e-6):
    """base and `count` copies with b's pose jittered by ~size (m and rad)."""
    copies = [base]
    for _ in range(count):
        c = dict(base)
        c["pos_b"] = base["pos_b"] + size * rng.normal(size=3)
        c["quat_b"] = quat_product(quat_about(rng.normal(size=3), size * rng.uniform()), base["quat_b"])
        copies.append(c)
    return copies


def whole_scene_rotated(c, rotation):
    c = dict(c)
    matrix = matrices(rotation)
    c["pos_a"], c["pos_b"] = matrix @ c["pos_a"], matrix @ c["pos_b"]
    c["quat_a"], c["quat_b"] = quat_product(rotation, c["quat_a"]), quat_product(rotation, c["quat_b"])
    return c


@pytest.mark.parametrize(
    "scene", ["equal boxes stacked", "small box on a big box", "stack seen at an angle", "box on a plane"]
)
def test_resting_manifold_keeps_its_slots_under_rounding_noise(scene):
    rng = np.random.default_rng(11)
    depth = 1e-3
    if scene == "box on a plane":
        pos, quat = (np.asarray(v, float) for v in C.plane_pose(jnp.array([0.0, 0.0, 1.0]), 0.0))
        base = case(("plane", "box"), pos, quat, [0.3, 0.2, BOX_SIZE[2] - depth], quat_about(UP, 0.4))
    elif scene == "small box on a big box":
        big = np.array([1.0, 0.8, 0.5])
        position = [0.1, 0.2, big[2] + BOX_SIZE_B[2] - depth]
        base = case(("box", "box"), [0, 0, 0], IDENTITY, position, quat_about(UP, 0.4), size_a=big, size_b=BOX_SIZE_B)
    else:
        base = case(("box", "box"), [0, 0, 0], IDENTITY, [0, 0, 2 * BOX_SIZE[2] - depth], IDENTITY, size_b=BOX_SIZE)
        if scene == "stack seen at an angle":
            base = whole_scene_rotated(base, random_quat(rng))
    contacts = contacts_of(perturbed(base, rng, 40))
    assert contacts.active[0].sum() == 4
    assert (contacts.active == contacts.active[0]).all(), "the active slots changed"
    active = contacts.active[0]
    drift = np.linalg.norm(contacts.point_b[:, active] - contacts.point_b[0, active], axis=-1)
    assert drift.max() < 1e-5, "a slot's point jumped"
    np.testing.assert_allclose(contacts.distance[:, active], -depth, atol=2e-5)


# ------------------------------------------------------------------------------------------------
# gradients (float64)
# ------------------------------------------------------------------------------------------------


def degenerate_cases(pair):
    """Configurations where a norm, a normalisation or a division meets zero."""
    r, h = CAPSULE_SIZE[:2]
    cube = np.array([0.3, 0.3, 0.3])
    up = quat_between([0, 0, 1], [0, 0, 1])
    plane = tuple(np.asarray(v, float) for v in C.plane_pose(jnp.array([0.0, 0.0, 1.0]), 0.0))
    sets = {
        "plane-sphere": [(plane, ([0, 0, 0], IDENTITY)), (plane, ([0, 0, 0.3], IDENTITY))],
        "plane-capsule": [(plane, ([0, 0, r], ALONG_X)), (plane, ([0, 0, 0], up)), (plane, ([0, 0, 0], IDENTITY))],
        "plane-box": [(plane, ([0, 0, 0.2], IDENTITY)), (plane, ([0, 0, 0], EDGE_X)), (plane, ([0, 0, 0], IDENTITY))],
        "sphere-sphere": [(([0, 0, 0], IDENTITY), ([0, 0, 0], IDENTITY))],
        "sphere-capsule": [
            (([0, 0, 0.1], IDENTITY), ([0, 0, 0], IDENTITY)),  # centre on the axis
            (([0, 0, h], IDENTITY), ([0, 0, 0], IDENTITY)),  # centre at an end of the axis
            (([0, 0, 0], IDENTITY), ([0, 0, 0], IDENTITY)),
        ],
        "sphere-box": [
            (([0, 0, 0], IDENTITY), ([0, 0, 0], IDENTITY), cube),  # centre at the centre of a cube
            (([0, 0, 0.3], IDENTITY), ([0, 0, 0], IDENTITY), cube),  # on a face
            (([0.3, 0, 0.3], IDENTITY), ([0, 0, 0], IDENTITY), cube),  # on an edge
            (([0.3, 0.3, 0.3], IDENTITY), ([0, 0, 0], IDENTITY), cube),  # on a corner
        ],
        "capsule-capsule": [
            (([0, 0, 0], ALONG_X), ([0.2, 0, 2 * r], ALONG_X)),  # parallel, touching
            (([0, 0, 0], IDENTITY), ([0, 0, 0.2], IDENTITY)),  # coaxial
            (([0, 0, 0], ALONG_X), ([0, 0, 0], ALONG_Y)),  # axes crossing at a point
            (([0, 0, 0], ALONG_X), ([0, 0, 0], ALONG_X)),  # identical
        ],
        "capsule-box": [
            (([0, 0, 0], IDENTITY), ([0, 0, 0], IDENTITY), cube),  # axis through the centre of a cube
            (([0, 0, 0.3 + r], ALONG_X), ([0, 0, 0], IDENTITY), cube),  # lying on a face, touching
            (([0, 0, 0.3 + h + r], IDENTITY), ([0, 0, 0], IDENTITY), cube),  # standing on a face
            (([0.3, 0, 0.3], ALONG_Y), ([0, 0, 0], IDENTITY), cube),  # axis along an edge
            (([0.3, 0.3, 0.3], quat_between([0, 0, 1], [1, 1, 1])), ([0, 0, 0], IDENTITY), cube),  # through a corner
        ],
        "box-box": [
            (([0, 0, 0], IDENTITY), ([0, 0, 0], IDENTITY), cube, cube),  # identical boxes, identical poses
            (([0, 0, 0], IDENTITY), ([0, 0, 0.6], IDENTITY), cube, cube),  # aligned face to face, touching
            (([0, 0, 0], IDENTITY), ([0.6, 0, 0], IDENTITY), cube, cube),  # aligned, touching along x
            (([0, 0, 0], IDENTITY), ([0, 0, 0.5], IDENTITY), cube, cube),  # aligned, overlapping
            (([0, 0, 0], IDENTITY), ([0, 0, 0.3 + 0.3 * np.sqrt(2)], EDGE_X), cube, cube),  # edge on face
            (([0, 0, 0], EDGE_X), ([0, 0, 0.6 * np.sqrt(2)], EDGE_Y), cube, cube),  # edge on edge, touching
            (([0, 0, 0], IDENTITY), ([0.6, 0.6, 0.6], IDENTITY), cube, cube),  # corner on corner
        ],
    }[pair]
    kinds = tuple(pair.split("-"))
    cases = []
    for entry in sets:
        (pos_a, quat_a), (pos_b, quat_b), sizes = entry[0], entry[1], entry[2:]
        size_a = sizes[0] if len(sizes) == 2 else None
        size_b = sizes[-1] if sizes else None
        cases.append(case(kinds, pos_a, quat_a, pos_b, quat_b, size_a=size_a, size_b=size_b))
    return cases


@pytest.mark.parametrize("pair", PAIRS)
def test_gradients_are_finite_at_degenerate_configurations(pair):
    cases = degenerate_cases(pair)
    loss, gradients = loss_and_gradients(cases, (1.0, 1.0))
    assert np.isfinite(loss).all()
    for gradient in gradients:
        assert np.isfinite(gradient).all(), gradient


@pytest.mark.parametrize("pair", PAIRS)
def test_distance_gradient_matches_finite_differences(pair):
    cases, targets = grid(pair)
    label = {"plane-capsule": "tilted", "plane-box": "random", "plane-sphere": "any"}.get(pair, "random")
    base = next(c for c, t in zip(cases, targets, strict=True) if c["label"] == label and t == TARGETS[1])
    epsilon = 1e-6
    probes = [base]
    for name, axis, sign in itertools.product(("pos_a", "pos_b"), range(3), (1.0, -1.0)):
        moved = dict(base)
        moved[name] = base[name] + sign * epsilon * np.eye(3)[axis]
        probes.append(moved)
    loss, gradients = loss_and_gradients(probes, (0.0, 1.0))
    numeric = (loss[1::2] - loss[2::2]) / (2 * epsilon)
    analytic = np.concatenate([gradients[0][0], gradients[2][0]])
    assert np.abs(numeric).max() > 0.1  # the configuration is not flat
    np.testing.assert_allclose(analytic, numeric, atol=1e-6)
