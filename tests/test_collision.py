"""Narrow phase (dbdjax.collision) against brute-force geometry.

The reference signed distance of two convex shapes is max over unit directions n of their
separation along n, n . (c_b - c_a) - rho_a(n) - rho_b(n) (rho = support half-width): the gap
when apart, minus the penetration depth (minimum translation distance) when overlapping. It is
found by a dense direction search refined by random local search, in numpy float64, and shares
no code with the engine. Capsule-box contacts are defined by the deepest point of the capsule
axis, checked against the box SDF sampled densely along the axis.

Every pair type is compiled once per dtype: the cases are stacked into one vmapped call.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dbdjax import collision as C

MARGIN = 0.03
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
    """Support half-width of centred shapes (C configs) along directions n (C, M, 3) -> (C, M)."""
    if kind == "sphere":
        return np.broadcast_to(size[:, None, 0], n.shape[:2])
    if kind == "capsule":
        return size[:, None, 0] + size[:, None, 1] * np.abs(np.einsum("cmi,ci->cm", n, rotation[:, :, 2]))
    return np.einsum("cmk,ck->cm", np.abs(np.einsum("cmi,cik->cmk", n, rotation)), size)


def fibonacci_sphere(count):
    i = np.arange(count) + 0.5
    polar, azimuth = np.arccos(1 - 2 * i / count), np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], -1)


_DIRECTIONS = fibonacci_sphere(6000)


def reference_distance(case_list):
    """(signed distance (C,), optimal unit direction a -> b (C, 3)) for a list of cases, float64."""
    kind_a, kind_b = case_list[0]["kinds"]
    size_a = np.array([c["size_a"] for c in case_list])
    size_b = np.array([c["size_b"] for c in case_list])
    pos_a = np.array([c["pos_a"] for c in case_list])
    pos_b = np.array([c["pos_b"] for c in case_list])
    if kind_a == "plane":
        normal = matrices(np.array([c["quat_a"] for c in case_list]))[:, :, 2]
        offset = np.einsum("ci,ci->c", normal, pos_a)
        rho = support_radius(kind_b, size_b, matrices(np.array([c["quat_b"] for c in case_list])), normal[:, None])
        return np.einsum("ci,ci->c", normal, pos_b) - rho[:, 0] - offset, normal
    rot_a = matrices(np.array([c["quat_a"] for c in case_list]))
    rot_b = matrices(np.array([c["quat_b"] for c in case_list]))
    d = pos_b - pos_a

    def separation(n):  # (C, M, 3) -> (C, M)
        return (
            np.einsum("cmi,ci->cm", n, d)
            - support_radius(kind_a, size_a, rot_a, n)
            - support_radius(kind_b, size_b, rot_b, n)
        )

    count = len(case_list)
    coarse = separation(np.broadcast_to(_DIRECTIONS, (count,) + _DIRECTIONS.shape))
    starts = 6
    best_n = _DIRECTIONS[np.argsort(-coarse, axis=1)[:, :starts]]  # (C, S, 3)
    chains_n = best_n.reshape(count * starts, 3)
    index = np.repeat(np.arange(count), starts)

    def chain_separation(n):  # (C*S, K, 3)
        flat_d = d[index]
        radius_a = support_radius(kind_a, size_a[index], rot_a[index], n)
        radius_b = support_radius(kind_b, size_b[index], rot_b[index], n)
        return np.einsum("cmi,ci->cm", n, flat_d) - radius_a - radius_b

    value = chain_separation(chains_n[:, None])[:, 0]
    sigma = np.full(count * starts, 0.03)
    rng = np.random.default_rng(0)
    for _ in range(250):
        trial = chains_n[:, None] + sigma[:, None, None] * rng.normal(size=(count * starts, 24, 3))
        trial /= np.linalg.norm(trial, axis=-1, keepdims=True)
        trial_value = chain_separation(trial)
        pick = np.argmax(trial_value, axis=1)
        better = trial_value[np.arange(count * starts), pick] > value
        chains_n = np.where(better[:, None], trial[np.arange(count * starts), pick], chains_n)
        value = np.where(better, trial_value[np.arange(count * starts), pick], value)
        sigma = np.where(better, sigma, 0.7 * sigma)
    value = value.reshape(count, starts)
    winner = np.argmax(value, axis=1)
    return value[np.arange(count), winner], chains_n.reshape(count, starts, 3)[np.arange(count), winner]


def box_sdf(local, half):
    q = np.abs(local) - half
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)


def segment_distance(points, centre, axis, half_length):
    t = np.clip((points - centre) @ axis, -half_length, half_length)
    return np.linalg.norm(points - centre - t[..., None] * axis, axis=-1)


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


def capsule_axis_depth(case):
    """Deepest point of a capsule (a) in a box (b): min over 200k axis samples of box SDF, minus the radius."""
    axis = matrices(case["quat_a"])[:, 2]
    t = np.linspace(-case["size_a"][1], case["size_a"][1], 200001)
    local = (case["pos_a"] + t[:, None] * axis - case["pos_b"]) @ matrices(case["quat_b"])
    return box_sdf(local, case["size_b"]).min() - case["size_a"][0]


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
def compiled_losses_and_gradients(kind_a, kind_b):
    """float64: two losses and their gradients w.r.t. (pos_a, quat_a, pos_b, quat_b).

    loss 0 touches every output of every slot (for the NaN checks), loss 1 is the sum of the
    active distances (for finite differences).
    """

    def losses(pos_a, quat_a, pos_b, quat_b, size_a, size_b):
        c = C.collide(kind_a, kind_b, size_a, pos_a, quat_a, size_b, pos_b, quat_b, MARGIN)
        everything = jnp.sum(c.distance) + jnp.sum(c.point_a) + jnp.sum(c.point_b) + jnp.sum(c.normal)
        return jnp.stack([everything, jnp.sum(jnp.where(c.active, c.distance, 0.0))])

    def value_and_jacobian(size_a, pos_a, quat_a, size_b, pos_b, quat_b):
        value = losses(pos_a, quat_a, pos_b, quat_b, size_a, size_b)
        jacobian = jax.jacrev(losses, argnums=(0, 1, 2, 3))(pos_a, quat_a, pos_b, quat_b, size_a, size_b)
        return value, jacobian

    return jax.jit(jax.vmap(value_and_jacobian))


def losses_and_gradients(case_list):
    with jax.enable_x64(True):
        kind_a, kind_b = case_list[0]["kinds"]
        value, jacobian = compiled_losses_and_gradients(KINDS[kind_a], KINDS[kind_b])(*stacked(case_list, jnp.float64))
        count = len(case_list)
        return np.asarray(value)[:count], [np.asarray(j)[:count] for j in jacobian]


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
    """Move each b along its direction so the reference signed distance equals its target (Newton)."""
    directions = [c.pop("direction") for c in case_list]
    for _ in range(8):
        distance, normal = reference_distance(case_list)
        for c, target, direction, now, n in zip(case_list, targets, directions, distance, normal, strict=True):
            slope = max(float(n @ direction), 0.2)  # d distance / d t along the direction (envelope theorem)
            c["pos_b"] = c["pos_b"] + (target - now) / slope * direction
    return case_list


@functools.cache
def grid(pair):
    """Cases of a pair type: every orientation at every target distance, plus one beyond the margin."""
    rng = np.random.default_rng(abs(hash(pair)) % 2**32)
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
                rho = support_radius(kinds[1], c["size_b"][None], matrices(quat)[None], -plane_normal[None, None])[0, 0]
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
        place(cases, targets)
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
    reference, _ = reference_distance(cases)
    np.testing.assert_allclose(reference, targets, atol=2e-6)  # the placement itself
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
    apart, _ = reference_distance(shifted(subset, (0.002 - distance)[:, None] * normal))
    into, _ = reference_distance(shifted(subset, (-0.002 - distance)[:, None] * normal))
    assert (apart > 0.0).all(), [(c["label"], v) for c, v in zip(subset, apart, strict=True) if v <= 0]
    assert (into < 0.0).all(), [(c["label"], v) for c, v in zip(subset, into, strict=True) if v >= 0]


def test_collide_accepts_either_order_and_num_points_is_symmetric():
    cases, _ = grid("capsule-box")
    c = cases[3]
    a = [jnp.asarray(c[k], jnp.float32) for k in ("size_a", "pos_a", "quat_a")]
    b = [jnp.asarray(c[k], jnp.float32) for k in ("size_b", "pos_b", "quat_b")]
    forward = C.collide(C.CAPSULE, C.BOX, *a, *b, MARGIN)
    backward = C.collide(C.BOX, C.CAPSULE, *b, *a, MARGIN)
    np.testing.assert_allclose(backward.point_a, forward.point_b, atol=1e-6)
    np.testing.assert_allclose(backward.point_b, forward.point_a, atol=1e-6)
    np.testing.assert_allclose(backward.normal, -forward.normal, atol=1e-6)
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
