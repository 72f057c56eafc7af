"""Pictures of a state: a ray caster in JAX that draws every shape of a model as RGB frames.

    camera = camera_looking_at(target=(0, 0, 0.5), distance=4.0, azimuth=-90.0, elevation=20.0)
    frame = render(model, state, camera)                  # (240, 320, 3) uint8
    frames = render_rollout(model, trajectory, camera)    # (T, 240, 320, 3) uint8

One primary ray per pixel (pinhole camera, pixel centres) is intersected analytically with every
shape of the model (planes, spheres, capsules, boxes, on bodies or on `WORLD`); the nearest hit is
shaded with ambient + Lambert light from one directional light, optionally with a hard shadow
(one more intersection pass from the hit points toward the light). Planes are drawn as a
checkerboard (in the plane's own axes, so motion over the ground is visible) that fades to its mean
colour where a square shrinks below a few pixels (no moire at the horizon); rays that hit nothing
see a sky gradient. Bodies get colours from a fixed palette by body index (`body_colors`), world
shapes a grey, unless `colors=` says otherwise.

Everything is a pure JAX function of (model, state, camera): it jits, vmaps over a batch of
states, and runs on any backend. Screen orientation: row 0 is the top of the image; the camera's
`up` points up on screen and forward x up points right (a right-handed view, not mirrored).

Cost: every pixel is tested against every shape, twice with shadows (primary + shadow ray):
O(H W K) work for K shapes, with no acceleration structure. The tests run on components
(structure of arrays) and one kind of shape at a time, so memory is a few (G, H, W) arrays for the
largest group of G shapes of one kind. Measured on this project's 2-core CPU (examples/
render_demo.py, 13 shapes, 320x240, float32): 64 ms of CPU time per frame with shadows, 36 ms
without, linear in the pixel count (270 ms at 640x480); compiling takes seconds. For hundreds
of shapes or large images use a GPU. `render_rollout` renders frames in batches sized to a memory
budget (`lax.map` with `batch_size`).

No NaN: rays parallel to a plane or a box face, rays along a capsule's axis, capsules of zero
length, a camera on a plane or inside a shape all go through masked (double-where) divisions and
`dbdjax.math`'s safe square roots and normalisations, so values (and gradients, though nothing
here is meant to be differentiated: hits are discrete) stay finite.
"""

from __future__ import annotations

import dataclasses
import functools
import math as _math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dbdjax.collision import BOX, CAPSULE, PLANE, SPHERE
from dbdjax.math import (
    any_perpendicular,
    cross,
    dot,
    quat_multiply,
    quat_rotate,
    quat_to_matrix,
    safe_norm,
    safe_normalize,
    safe_sqrt,
)
from dbdjax.model import Model, State, with_world_row

# A miss is a hit this far away (m): finite, so min/argmin and arithmetic never meet inf.
_FAR = 1e30
# Below this a ray direction component (or squared length) counts as parallel.
_PARALLEL = 1e-12
# Hits closer than this along a ray are ignored (m): the ray's own start point.
_NEAR = 1e-6

# Default colours, (R, G, B) in [0, 1]: body i gets _PALETTE[i % len(_PALETTE)].
_PALETTE = np.array(
    [
        (0.90, 0.30, 0.25),  # red
        (0.25, 0.50, 0.88),  # blue
        (0.95, 0.70, 0.20),  # amber
        (0.30, 0.72, 0.40),  # green
        (0.62, 0.40, 0.82),  # violet
        (0.20, 0.75, 0.80),  # teal
        (0.92, 0.50, 0.70),  # pink
        (0.60, 0.44, 0.28),  # brown
    ]
)
WORLD_COLOR = (0.62, 0.62, 0.66)
"""Colour of static (WORLD) shapes other than planes."""
CHECKER_COLORS = ((0.86, 0.86, 0.84), (0.52, 0.56, 0.60))
"""The two squares of a plane's checkerboard."""
_SKY_HORIZON = np.array([0.88, 0.91, 0.95])
_SKY_ZENITH = np.array([0.45, 0.62, 0.88])
_SKY_NADIR = np.array([0.35, 0.36, 0.40])
DEFAULT_LIGHT = (-0.35, -0.55, 1.0)
"""Direction toward the light (world, normalised on use): high up, on the left of the default
views and on the camera's side, so shadows fall behind the bodies and to the right."""


# ------------------------------------------------------------------------------------------------
# Camera
# ------------------------------------------------------------------------------------------------


@jax.tree_util.register_pytree_node_class
@dataclasses.dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera. A pytree: position, look_at, up and fov are leaves (so a camera can be
    computed inside jit, follow a body, or be batched); width and height are static.

    position: (3,) m, the eye. look_at: (3,) m, the point at the centre of the image.
    up: (3,) world direction that points up on screen (need not be perpendicular to the view;
      if parallel to it, any perpendicular is used). fov: vertical field of view, degrees.
    width, height: image size in pixels.
    """

    position: jnp.ndarray
    look_at: jnp.ndarray
    up: jnp.ndarray = (0.0, 0.0, 1.0)
    fov: jnp.ndarray = 45.0
    width: int = 320
    height: int = 240

    def __post_init__(self):
        dtype = jnp.result_type(float)
        for name in ("position", "look_at", "up", "fov"):
            value = getattr(self, name)
            if not isinstance(value, jax.Array):
                value = jnp.asarray(value, dtype)
            object.__setattr__(self, name, value)
        for name in ("width", "height"):
            size = getattr(self, name)
            if not isinstance(size, (int, np.integer)) or isinstance(size, bool) or size <= 0:
                raise ValueError(f"Camera: {name} must be a positive int (pixels), got {size!r}")
            object.__setattr__(self, name, int(size))

    def tree_flatten(self):
        return (self.position, self.look_at, self.up, self.fov), (self.width, self.height)

    @classmethod
    def tree_unflatten(cls, aux, leaves):
        # bypass __post_init__: transformations pass tracers, None or sentinels as leaves
        camera = object.__new__(cls)
        for name, value in zip(("position", "look_at", "up", "fov"), leaves, strict=True):
            object.__setattr__(camera, name, value)
        object.__setattr__(camera, "width", aux[0])
        object.__setattr__(camera, "height", aux[1])
        return camera

    def replace(self, **changes) -> Camera:
        """A copy with some fields changed (e.g. `camera.replace(width=64, height=48)`)."""
        return dataclasses.replace(self, **changes)


def camera_looking_at(
    target: Sequence[float] | jnp.ndarray,
    distance: float = 4.0,
    azimuth: float = -90.0,
    elevation: float = 20.0,
    *,
    fov: float = 45.0,
    width: int = 320,
    height: int = 240,
) -> Camera:
    """A camera on a sphere around `target` (3,), looking at it.

    distance: m from the target. azimuth: degrees, the direction of the camera from the target in
    the xy-plane, counter-clockwise from +x (-90: the camera is on the -y side looking along +y,
    so +x points right on screen). elevation: degrees above the xy-plane (positive looks down;
    90 looks straight down with the azimuth direction pointing down on screen).
    World z is up on screen (up to the tilt of the view). Works on traced values (inside jit).
    """
    target = jnp.asarray(target, jnp.result_type(float))
    az, el = jnp.deg2rad(azimuth), jnp.deg2rad(elevation)
    away = jnp.stack([jnp.cos(el) * jnp.cos(az), jnp.cos(el) * jnp.sin(az), jnp.sin(el)])
    # the screen's up direction, perpendicular to the view and well defined even at +-90 degrees
    up = jnp.stack([-jnp.sin(el) * jnp.cos(az), -jnp.sin(el) * jnp.sin(az), jnp.cos(el)])
    return Camera(target + distance * away, target, up, fov, width, height)


def follow(camera: Camera, state: State, body: int, axes: Sequence[bool] = (True, True, True)) -> Camera:
    """The camera moved (not turned) so that it looks at `body`'s centre of mass: a tracking camera.

    The offset position - look_at is kept. axes: which world axes to follow (e.g. (True, True,
    False) keeps the height, so a bouncing body does not shake the view). state: one state
    (N, 3) positions; for a batch, vmap.
    """
    shift = jnp.where(jnp.asarray(axes), state.pos[body] - camera.look_at, 0.0)
    return dataclasses.replace(camera, position=camera.position + shift, look_at=camera.look_at + shift)


def _shape_poses(model: Model, state: State) -> tuple[jnp.ndarray, jnp.ndarray]:
    """World position (K, 3) and orientation (K, 4) of every shape."""
    dtype = state.pos.dtype
    body = model.structure.shape_body.array
    pos = with_world_row(state.pos, 0.0)[body]
    quat = with_world_row(state.quat, jnp.array([1.0, 0.0, 0.0, 0.0], dtype))[body]
    shapes = model.shapes
    return pos + quat_rotate(quat, shapes.local_pos.astype(dtype)), quat_multiply(quat, shapes.local_quat.astype(dtype))


def _bounding_radius(model: Model) -> jnp.ndarray:
    """(K,) radius of a ball around each shape's centre holding it (planes: 0)."""
    size, kind = model.shapes.size, model.structure.shape_kind.array
    box = safe_norm(size)
    radius = jnp.where(kind == SPHERE, size[:, 0], 0.0)
    radius = jnp.where(kind == CAPSULE, size[:, 0] + size[:, 1], radius)
    return jnp.where(kind == BOX, box, radius)


@functools.partial(jax.jit, static_argnames=("width", "height", "fov", "azimuth", "elevation"))
def default_camera(
    model: Model, state: State, *, width: int = 320, height: int = 240, fov: float = 45.0,
    azimuth: float = -70.0, elevation: float = 20.0,
) -> Camera:  # fmt: skip
    """A camera that frames every non-plane shape of `state` (any leading batch axes, e.g. a whole
    trajectory (T, N, 3): then the framing holds for all its frames) from `azimuth`/`elevation`
    (degrees, see `camera_looking_at`). Bodies without shapes count as points. Empty scenes get a
    view of the origin from 5 m."""
    kind = model.structure.shape_kind.array
    solid = np.flatnonzero(kind != PLANE)
    lead = state.pos.shape[:-2]
    flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[len(lead) :]), state)
    centres, radii = [], []
    if solid.size:
        pos, _ = jax.vmap(lambda s: _shape_poses(model, s))(flat)
        centres.append(pos[:, solid].reshape(-1, 3))
        radii.append(jnp.broadcast_to(_bounding_radius(model)[solid], pos[:, solid].shape[:2]).reshape(-1))
    if model.num_bodies:
        centres.append(flat.pos.reshape(-1, 3))
        radii.append(jnp.zeros(flat.pos.shape[0] * flat.pos.shape[1], flat.pos.dtype))
    if not centres:
        return camera_looking_at(
            jnp.zeros(3, state.pos.dtype), 5.0, azimuth, elevation, fov=fov, width=width, height=height
        )
    centres, radii = jnp.concatenate(centres), jnp.concatenate(radii)
    low = jnp.min(centres - radii[:, None], axis=0)
    high = jnp.max(centres + radii[:, None], axis=0)
    target = 0.5 * (low + high)
    # a ball around the box, seen through the narrower of the two fields of view, with 15% margin
    radius = jnp.maximum(0.5 * safe_norm(high - low), 0.1)
    half = _math.radians(fov) / 2
    half = min(half, _math.atan(_math.tan(half) * width / height))
    distance = 1.15 * radius / _math.sin(half)
    return camera_looking_at(target, distance, azimuth, elevation, fov=fov, width=width, height=height)


def _camera_frame(camera: Camera) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """(forward, right, up) unit vectors of the camera: right = forward x up."""
    forward, length = safe_normalize(camera.look_at - camera.position)
    forward = jnp.where(length > 0.0, forward, jnp.array([1.0, 0.0, 0.0], forward.dtype))
    right, size = safe_normalize(cross(forward, camera.up))
    right = jnp.where(size > 1e-6, right, any_perpendicular(forward))
    return forward, right, cross(right, forward)


def _camera_rays(camera: Camera, supersample: int, dtype) -> Vec:
    """Unit ray directions through the pixel centres as (x, y, z) components, each (H s, W s)."""
    forward, right, up = (v.astype(dtype) for v in _camera_frame(camera))
    width, height = camera.width * supersample, camera.height * supersample
    tan_half = jnp.tan(jnp.deg2rad(camera.fov.astype(dtype)) / 2)
    x = ((jnp.arange(width, dtype=dtype) + 0.5) / width * 2.0 - 1.0) * tan_half * (width / height)
    y = (1.0 - (jnp.arange(height, dtype=dtype) + 0.5) / height * 2.0) * tan_half
    x, y = x[None, :], y[:, None]
    rays = tuple(forward[i] + x * right[i] + y * up[i] for i in range(3))
    # forward, right and up are orthonormal, so the length is at least 1: a plain division
    length = jnp.sqrt(_dot3(rays, rays))
    return tuple(r / length for r in rays)


def camera_rays(camera: Camera, supersample: int = 1) -> jnp.ndarray:
    """Unit ray directions (H s, W s, 3) through the pixel centres (row 0 at the top), world frame;
    they all start at camera.position. s = supersample: s x s rays per pixel."""
    return jnp.stack(_camera_rays(camera, supersample, camera.position.dtype), axis=-1)


def project(camera: Camera, points: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Where world points (..., 3) appear in the picture: ((..., 2) continuous (column, row) image
    coordinates, in which pixel [i, j] covers columns [j, j + 1) and rows [i, i + 1) (its centre
    is (j + 0.5, i + 0.5)); (...,) depth along the view axis, m, negative behind the camera, where
    the coordinates mean nothing)."""
    forward, right, up = _camera_frame(camera)
    offset = points - camera.position
    depth = dot(offset, forward)
    safe_depth = jnp.where(jnp.abs(depth) > _PARALLEL, depth, 1.0)
    tan_half = jnp.tan(jnp.deg2rad(camera.fov) / 2)
    x = dot(offset, right) / (safe_depth * tan_half * camera.width / camera.height)
    y = dot(offset, up) / (safe_depth * tan_half)
    column = (x + 1.0) / 2.0 * camera.width
    row = (1.0 - y) / 2.0 * camera.height
    return jnp.stack([column, row], axis=-1), depth


# ------------------------------------------------------------------------------------------------
# Ray-shape intersection. Vectors are (x, y, z) tuples of arrays that broadcast against each other
# (structure of arrays: XLA on CPU vectorises over pixels instead of over a minor axis of 3), in
# the shape's frame. o: ray origins, d: unit directions. Each returns the nearest distance
# t > _NEAR along the ray, _FAR where it misses.
# ------------------------------------------------------------------------------------------------

Vec = tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]


def _dot3(a: Vec, b: Vec) -> jnp.ndarray:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _nearest(*candidates: tuple[jnp.ndarray, jnp.ndarray]) -> jnp.ndarray:
    """Smallest t among (t, valid) candidates that are valid and beyond _NEAR; _FAR if none."""
    best = None
    for t, valid in candidates:
        t = jnp.where(valid & (t > _NEAR), t, _FAR)
        best = t if best is None else jnp.minimum(best, t)
    return best


def _sphere_roots(o: Vec, d: Vec, radius: jnp.ndarray):
    """Both crossings of a ray with the sphere |x| = radius: ((t_in, t_out), hit).

    Uses the perpendicular offset f = o - (o.d) d rather than b^2 - c (no cancellation for
    small spheres far away; Haines et al., Ray Tracing Gems ch. 7)."""
    b = _dot3(o, d)
    f = tuple(o[i] - b * d[i] for i in range(3))
    disc = radius * radius - _dot3(f, f)
    half = safe_sqrt(jnp.maximum(disc, 0.0))
    return (-b - half, -b + half), disc >= 0.0


def _plane_distance(height: jnp.ndarray, along: jnp.ndarray) -> jnp.ndarray:
    """t where a ray at signed `height` above a plane, moving `along` its normal, crosses it (both
    sides). A ray parallel to the plane misses."""
    parallel = jnp.abs(along) <= _PARALLEL
    return _nearest((-height / jnp.where(parallel, 1.0, along), ~parallel))


def _hit_sphere(o: Vec, d: Vec, radius: jnp.ndarray) -> jnp.ndarray:
    """The sphere |x| = radius (a ray starting inside sees its far side)."""
    (t_in, t_out), hit = _sphere_roots(o, d, radius)
    return _nearest((t_in, hit), (t_out, hit))


def _hit_capsule(o: Vec, d: Vec, radius: jnp.ndarray, half_length: jnp.ndarray) -> jnp.ndarray:
    """The capsule around the segment z in [-half_length, half_length] of the z axis: the side of
    the cylinder of `radius` where it lies between the ends, and the two end spheres (which alone
    make the capsule when half_length = 0 or the ray runs along the axis)."""
    a = d[0] * d[0] + d[1] * d[1]
    along_axis = a <= _PARALLEL
    safe_a = jnp.where(along_axis, 1.0, a)
    closest = -(o[0] * d[0] + o[1] * d[1]) / safe_a  # t of the ray point nearest the axis
    fx, fy = o[0] + closest * d[0], o[1] + closest * d[1]
    disc = radius * radius - (fx * fx + fy * fy)
    half = safe_sqrt(jnp.maximum(disc, 0.0) / safe_a)
    side = (disc >= 0.0) & ~along_axis
    candidates = []
    for t in (closest - half, closest + half):
        candidates.append((t, side & (jnp.abs(o[2] + t * d[2]) <= half_length)))
    for sign in (-1.0, 1.0):
        (t_in, t_out), hit = _sphere_roots((o[0], o[1], o[2] - sign * half_length), d, radius)
        candidates += [(t_in, hit), (t_out, hit)]
    return _nearest(*candidates)


def _hit_box(o: Vec, d: Vec, half_extents: jnp.ndarray) -> jnp.ndarray:
    """The box |x_i| <= half_extents_i by the slab method (Kay and Kajiya): the ray is inside all
    three slabs between t_enter = max of the entries and t_exit = min of the exits. A direction
    component of zero means the ray is always (or never) inside that slab."""
    t_enter, t_exit = None, None
    for i in range(3):
        parallel = jnp.abs(d[i]) <= _PARALLEL
        inverse = 1.0 / jnp.where(parallel, 1.0, d[i])
        t1 = (-half_extents[i] - o[i]) * inverse
        t2 = (half_extents[i] - o[i]) * inverse
        inside = jnp.abs(o[i]) <= half_extents[i]
        enter = jnp.where(parallel, jnp.where(inside, -_FAR, _FAR), jnp.minimum(t1, t2))
        leave = jnp.where(parallel, jnp.where(inside, _FAR, -_FAR), jnp.maximum(t1, t2))
        t_enter = enter if t_enter is None else jnp.maximum(t_enter, enter)
        t_exit = leave if t_exit is None else jnp.minimum(t_exit, leave)
    hit = t_enter <= t_exit
    return _nearest((t_enter, hit), (t_exit, hit))


def _split(v: jnp.ndarray) -> Vec:
    return v[..., 0], v[..., 1], v[..., 2]


def _shape_distance(kind: int, size: jnp.ndarray, pos: jnp.ndarray, rotation: jnp.ndarray, origin: Vec, rays: Vec):
    """t along world rays to one shape of static `kind`; rotation (3, 3) takes local to world."""
    offset = tuple(origin[i] - pos[i] for i in range(3))
    if kind == PLANE:  # only the components along the normal (local z) matter
        normal = rotation[:, 2]
        return _plane_distance(_dot3(offset, normal), _dot3(rays, normal))
    if kind == SPHERE:  # rotation-invariant: no change of frame
        return _hit_sphere(offset, rays, size[0])
    # world -> local: x_local_i = sum_j R_ji x_j (R^T x)
    o = tuple(_dot3(offset, rotation[:, i]) for i in range(3))
    d = tuple(_dot3(rays, rotation[:, i]) for i in range(3))
    if kind == CAPSULE:
        return _hit_capsule(o, d, size[0], size[1])
    return _hit_box(o, d, size)


def _normalized(v: Vec) -> Vec:
    """v / |v| by components; the zero vector stays zero (double where: finite gradients)."""
    squared = _dot3(v, v)
    is_zero = squared <= 1e-24
    inverse = jnp.where(is_zero, 0.0, 1.0 / jnp.sqrt(jnp.where(is_zero, 1.0, squared)))
    return tuple(c * inverse for c in v)


def _local_normal(kind: jnp.ndarray, size: Vec, x: Vec, kinds: frozenset) -> Vec:
    """Outward unit normal at the local surface point x of a shape of `kind` (arrays per pixel);
    only the formulas of the shape kinds in `kinds` (static: those of the model) are built."""
    normals = {PLANE: (jnp.zeros_like(x[0]), jnp.zeros_like(x[0]), jnp.ones_like(x[0]))}
    if SPHERE in kinds:
        normals[SPHERE] = _normalized(x)
    if CAPSULE in kinds:
        normals[CAPSULE] = _normalized((x[0], x[1], x[2] - jnp.clip(x[2], -size[1], size[1])))
    if BOX in kinds:
        # the face the point lies on: the axis where |x_i| - h_i is largest (first on ties)
        excess = [jnp.abs(x[i]) - size[i] for i in range(3)]
        first = (excess[0] >= excess[1]) & (excess[0] >= excess[2])
        second = ~first & (excess[1] >= excess[2])
        faces = (first, second, ~first & ~second)
        normals[BOX] = tuple(jnp.where(faces[i], jnp.where(x[i] >= 0.0, 1.0, -1.0), 0.0) for i in range(3))
    normal = normals[PLANE]
    for shape_kind in (SPHERE, CAPSULE, BOX):
        if shape_kind in normals:
            normal = tuple(jnp.where(kind == shape_kind, normals[shape_kind][i], normal[i]) for i in range(3))
    return normal


def _trace(model: Model, pos: jnp.ndarray, quat: jnp.ndarray, origin: Vec, rays: Vec) -> tuple[jnp.ndarray, ...]:
    """(nearest distance, index of the shape hit) along world rays over every shape; _FAR and an
    arbitrary index where nothing is hit. origin and rays broadcast together: the primary pass
    shares one origin, the shadow pass one direction. Shapes are grouped by kind (static index
    sets), each group vmapped over its shapes and reduced before the next: memory is one group's
    (G, H, W) distances at a time."""
    kind = model.structure.shape_kind.array
    size = model.shapes.size.astype(pos.dtype)
    rotation = quat_to_matrix(quat)
    best, index = None, None
    for shape_kind in (PLANE, SPHERE, CAPSULE, BOX):
        group = np.flatnonzero(kind == shape_kind)
        if group.size == 0:
            continue
        test = functools.partial(_shape_distance, shape_kind, origin=origin, rays=rays)
        t = jax.vmap(lambda s, p, r, test=test: test(s, p, r))(size[group], pos[group], rotation[group])
        nearest, which = jnp.min(t, axis=0), jnp.asarray(group, jnp.int32)[jnp.argmin(t, axis=0)]
        if best is None:
            best, index = nearest, which
        else:
            closer = nearest < best
            best, index = jnp.where(closer, nearest, best), jnp.where(closer, which, index)
    # materialise: without the barrier XLA may fuse (and so recompute) the whole pass into each
    # of its consumers
    return jax.lax.optimization_barrier((best, index))


class Hits(NamedTuple):
    """What each primary ray hit. hit: (H, W) bool. distance: (H, W) m along the ray (inf where
    nothing). point: (H, W, 3) world hit point (the camera position where nothing). normal:
    (H, W, 3) unit world normal facing the camera (0 where nothing). shape: (H, W) int shape index
    (-1 where nothing). rays: (H, W, 3) the unit ray directions."""

    hit: jnp.ndarray
    distance: jnp.ndarray
    point: jnp.ndarray
    normal: jnp.ndarray
    shape: jnp.ndarray
    rays: jnp.ndarray


class _Cast(NamedTuple):
    """`Hits` by components, plus what shading needs: t (0 where nothing), the hit shape's index
    (clamped to 0 where nothing) and kind, and the hit point in that shape's frame."""

    hit: jnp.ndarray
    t: jnp.ndarray
    index: jnp.ndarray
    kind: jnp.ndarray
    local: Vec
    point: Vec
    normal: Vec
    rays: Vec


def _cast(model: Model, state: State, camera: Camera, supersample: int, pos, quat) -> _Cast:
    """Primary rays against every shape: nearest hit, its point and its normal."""
    dtype = state.pos.dtype
    rays = _camera_rays(camera, supersample, dtype)
    origin = _split(camera.position.astype(dtype))
    shape = rays[0].shape
    if model.structure.shape_kind.array.size == 0:
        zero = jnp.zeros(shape, dtype)
        index = jnp.zeros(shape, jnp.int32)
        return _Cast(zero > 0.0, zero, index, index, (zero,) * 3, tuple(zero + o for o in origin), (zero,) * 3, rays)
    nearest, index = _trace(model, pos, quat, origin, rays)
    hit = nearest < _FAR
    t = jnp.where(hit, nearest, 0.0)
    # one gather of the hit shape's pose and size per pixel: (H, W, 3 + 9 + 3)
    rotation = quat_to_matrix(quat)
    table = jnp.concatenate([pos, rotation.reshape(-1, 9), model.shapes.size.astype(dtype)], axis=-1)
    row = table[index]
    p, m, size = _split(row[..., 0:3]), row[..., 3:12], _split(row[..., 12:15])
    column = [(m[..., i], m[..., 3 + i], m[..., 6 + i]) for i in range(3)]  # R[:, i]: local axis i in world
    # the hit point in the hit shape's frame, R^T (o - p) + t R^T d (precise near the shape)
    offset = tuple(origin[i] - p[i] for i in range(3))
    local = tuple(_dot3(offset, column[i]) + t * _dot3(rays, column[i]) for i in range(3))
    kind = jnp.asarray(model.structure.shape_kind.array, jnp.int32)[index]
    n = _local_normal(kind, size, local, frozenset(model.structure.shape_kind.array.tolist()))
    normal = tuple(column[0][i] * n[0] + column[1][i] * n[1] + column[2][i] * n[2] for i in range(3))
    facing = jnp.where(_dot3(normal, rays) > 0.0, -1.0, 1.0)  # seen from behind: planes, from inside
    normal = tuple(jnp.where(hit, facing * c, 0.0) for c in normal)
    point = tuple(origin[i] + t * rays[i] for i in range(3))
    return jax.lax.optimization_barrier(_Cast(hit, t, index, kind, local, point, normal, rays))


@functools.partial(jax.jit, static_argnames="supersample")
def cast_rays(model: Model, state: State, camera: Camera, supersample: int = 1) -> Hits:
    """Intersect the camera's primary rays with every shape of `model` in `state` (one state; vmap
    for a batch). Images are (H s, W s) for supersample s. Depth images and segmentation masks
    come from here (`Hits.distance`, `Hits.shape`)."""
    pos, quat = _shape_poses(model, state)
    cast = _cast(model, state, camera, supersample, pos, quat)
    return Hits(
        hit=cast.hit,
        distance=jnp.where(cast.hit, cast.t, jnp.inf),
        point=jnp.stack(cast.point, axis=-1),
        normal=jnp.stack(cast.normal, axis=-1),
        shape=jnp.where(cast.hit, cast.index, -1),
        rays=jnp.stack(cast.rays, axis=-1),
    )


# ------------------------------------------------------------------------------------------------
# Shading
# ------------------------------------------------------------------------------------------------


def body_colors(num_bodies: int) -> np.ndarray:
    """The default colours (num_bodies, 3) in [0, 1]: a fixed palette of 8 by body index."""
    return _PALETTE[np.arange(num_bodies) % len(_PALETTE)]


def _sky(z: jnp.ndarray) -> jnp.ndarray:
    """Background (..., 3) for rays with vertical component z (...,) that hit nothing: horizon to
    zenith above, darker below."""
    horizon, zenith, nadir = (jnp.asarray(c, z.dtype) for c in (_SKY_HORIZON, _SKY_ZENITH, _SKY_NADIR))
    z = z[..., None]
    up = horizon + (zenith - horizon) * jnp.clip(z, 0.0, 1.0)
    down = horizon + (nadir - horizon) * jnp.clip(-4.0 * z, 0.0, 1.0)
    return jnp.where(z >= 0.0, up, down)


_STATIC = ("width", "height", "shadows", "track", "supersample", "quantise")


@functools.partial(jax.jit, static_argnames=_STATIC)
def _image(
    model: Model, state: State, camera: Camera | None, colors: jnp.ndarray | None, light: jnp.ndarray,
    ambient: jnp.ndarray, checker_size: jnp.ndarray, *, width: int | None, height: int | None, shadows: bool,
    track: int | None, supersample: int, quantise: bool,
) -> jnp.ndarray:  # fmt: skip
    """One picture of one state (the work of `render`, compiled once per model structure, camera
    size and static option)."""
    if camera is None:
        camera = default_camera(model, state, width=width or 320, height=height or 240)
    elif width is not None or height is not None:
        camera = camera.replace(width=width or camera.width, height=height or camera.height)
    if track is not None:
        camera = follow(camera, state, track)
    dtype = state.pos.dtype
    structure = model.structure
    pos, quat = _shape_poses(model, state)
    cast = _cast(model, state, camera, supersample, pos, quat)
    if colors is None:
        colors = body_colors(structure.num_bodies)
    table = jnp.concatenate([jnp.asarray(colors, dtype), jnp.asarray(WORLD_COLOR, dtype)[None]])  # row N: world
    if structure.shape_kind.array.size:
        # one (H, W, 3) gather: gathering per channel and stacking makes XLA on CPU 20x slower
        base = table[structure.shape_body.array][cast.index]
    else:
        base = jnp.zeros(cast.t.shape + (3,), dtype)

    # checkerboard on planes, in the plane's local x, y; faded to the mean where a square spans
    # fewer than ~6 pixels (the footprint of a pixel on the plane grows as t / |cos|)
    checker_size = jnp.asarray(checker_size, dtype)
    cells = jnp.floor(cast.local[0] / checker_size) + jnp.floor(cast.local[1] / checker_size)
    odd = jnp.mod(cells, 2.0)[..., None]
    pixel_angle = 2.0 * jnp.tan(jnp.deg2rad(camera.fov.astype(dtype)) / 2) / (camera.height * supersample)
    grazing = jnp.maximum(jnp.abs(_dot3(cast.normal, cast.rays)), 0.05)
    footprint = cast.t * pixel_angle / grazing / checker_size
    fade = jnp.clip((footprint - 1.0 / 6.0) * 3.0, 0.0, 1.0)[..., None]
    light_square, dark_square = (jnp.asarray(c, dtype) for c in CHECKER_COLORS)
    checker = light_square + (dark_square - light_square) * odd
    checker = checker + (0.5 * (light_square + dark_square) - checker) * fade
    base = jnp.where((cast.hit & (cast.kind == PLANE))[..., None], checker, base)

    towards_light = safe_normalize(jnp.asarray(light, dtype))[0]
    lambert = jnp.maximum(_dot3(cast.normal, _split(towards_light)), 0.0)
    if shadows and structure.shape_kind.array.size:
        # a shadow ray from just off the surface (the offset grows with distance: float precision)
        offset = 1e-4 + 1e-5 * cast.t
        start = tuple(cast.point[i] + offset * cast.normal[i] for i in range(3))
        blocked, _ = _trace(model, pos, quat, start, _split(towards_light))
        lambert = jnp.where(blocked < _FAR, 0.0, lambert)
    ambient = jnp.asarray(ambient, dtype)
    shade = ambient + (1.0 - ambient) * lambert
    image = jnp.where(cast.hit[..., None], base * shade[..., None], _sky(cast.rays[2]))
    if supersample > 1:
        s = supersample
        image = image.reshape(camera.height, s, camera.width, s, 3).mean(axis=(1, 3))
    image = jnp.clip(image, 0.0, 1.0)
    return to_uint8(image) if quantise else image


def _arguments(model: Model, colors, light, ambient, checker_size, supersample) -> tuple:
    """Check and convert the non-static options of `render` (errors outside of jit)."""
    if not isinstance(supersample, (int, np.integer)) or isinstance(supersample, bool) or supersample < 1:
        raise ValueError(f"render: supersample must be a positive int, got {supersample!r}")
    if colors is not None:
        colors = jnp.asarray(colors)
        if colors.shape != (model.num_bodies, 3):
            raise ValueError(f"render: colors must be ({model.num_bodies}, 3) RGB in [0, 1], got {colors.shape}")
    if np.shape(light) != (3,):
        raise ValueError(f"render: light must be a direction (3,), got {light!r}")
    return colors, jnp.asarray(light, float), jnp.asarray(ambient, float), jnp.asarray(checker_size, float)


def render_float(
    model: Model,
    state: State,
    camera: Camera | None = None,
    *,
    width: int | None = None,
    height: int | None = None,
    colors: jnp.ndarray | Sequence | None = None,
    shadows: bool = True,
    light: Sequence[float] = DEFAULT_LIGHT,
    ambient: float = 0.35,
    checker_size: float = 0.5,
    track: int | None = None,
    supersample: int = 1,
) -> jnp.ndarray:
    """`render` before quantisation: (..., H, W, 3) floats in [0, 1] (linear, no gamma). Same arguments."""
    return _draw(model, state, camera, width, height, colors, shadows, light, ambient, checker_size, track,
                 supersample, quantise=False)  # fmt: skip


def _draw(model, state, camera, width, height, colors, shadows, light, ambient, checker_size, track, supersample,
          quantise):  # fmt: skip
    arguments = _arguments(model, colors, light, ambient, checker_size, supersample)
    static = dict(width=width, height=height, shadows=bool(shadows), track=track, supersample=int(supersample),
                  quantise=quantise)  # fmt: skip
    if state.pos.ndim == 2:
        return _image(model, state, camera, *arguments, **static)
    # leading batch axes: one picture per state
    lead = state.pos.shape[:-2]
    flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[len(lead) :]), state)
    images = jax.vmap(lambda one: _image(model, one, camera, *arguments, **static))(flat)
    return images.reshape(lead + images.shape[1:])


def render(
    model: Model,
    state: State,
    camera: Camera | None = None,
    *,
    width: int | None = None,
    height: int | None = None,
    colors: jnp.ndarray | Sequence | None = None,
    shadows: bool = True,
    light: Sequence[float] = DEFAULT_LIGHT,
    ambient: float = 0.35,
    checker_size: float = 0.5,
    track: int | None = None,
    supersample: int = 1,
) -> jnp.ndarray:
    """An RGB picture (H, W, 3) uint8 of `state` seen by `camera`.

    model, state: what to draw (every shape, on bodies and on WORLD). A state with leading batch
      axes (..., N, 3) gives (..., H, W, 3), vmapped (all frames in memory at once: for long
      trajectories use `render_rollout`).
    camera: a `Camera`; None frames the shapes of each state (`default_camera`).
    width, height: pixels, overriding the camera's (or sizing the default camera; 320 x 240).
    colors: (N, 3) RGB in [0, 1] per body (default `body_colors`); WORLD shapes are WORLD_COLOR,
      planes a checkerboard of CHECKER_COLORS with squares of `checker_size` m.
    shadows: cast a hard shadow ray per pixel (twice the cost; shows where bodies touch the ground).
    light: (3,) world direction toward the directional light. ambient: light level in the shadow,
      in [0, 1]; a face toward the light gets 1: colour = base colour x (ambient + (1 - ambient)
      max(n . light, 0)).
    track: a body index to follow (`follow`): the camera is moved to look at it.
    supersample: s x s rays per pixel, averaged (anti-aliasing, s^2 the cost).
    Pure: compiled on first use (per model structure, image size and static option: width,
    height, shadows, track, supersample), and usable inside jit, vmap and lax.map.
    """
    return _draw(model, state, camera, width, height, colors, shadows, light, ambient, checker_size, track,
                 supersample, quantise=True)  # fmt: skip


def to_uint8(image: jnp.ndarray) -> jnp.ndarray:
    """Floats in [0, 1] -> uint8 (rounded, clipped)."""
    return jnp.round(jnp.clip(image, 0.0, 1.0) * 255.0).astype(jnp.uint8)


def render_rollout(
    model: Model,
    states: State,
    camera: Camera | None = None,
    *,
    batch_size: int | None = None,
    memory_budget: float = 256e6,
    width: int | None = None,
    height: int | None = None,
    colors: jnp.ndarray | Sequence | None = None,
    shadows: bool = True,
    light: Sequence[float] = DEFAULT_LIGHT,
    ambient: float = 0.35,
    checker_size: float = 0.5,
    track: int | None = None,
    supersample: int = 1,
) -> jnp.ndarray:
    """Frames (T, H, W, 3) uint8 of a trajectory `states` (leading axis T, e.g. from `dbd.rollout`).

    camera: one camera for every frame; None frames the whole trajectory once (`default_camera`
    over all T states: the view does not jump from frame to frame). track=body follows a body.
    batch_size: frames rendered at once (`lax.map`); None picks the largest that keeps the
    intersection buffers under memory_budget bytes (about 16 floats per pixel and shape).
    Other options: as for `render`.
    """
    if states.pos.ndim != 3:
        raise ValueError(f"render_rollout: states must have one leading time axis (T, N, 3), got {states.pos.shape}")
    steps = states.pos.shape[0]
    if camera is None:
        camera = default_camera(model, states, width=width or 320, height=height or 240)
        width = height = None
    if batch_size is None:
        pixels = (width or camera.width) * (height or camera.height) * supersample**2
        per_frame = 16 * 4 * pixels * (model.structure.shape_kind.array.size + 1)
        batch_size = int(max(1, min(steps, memory_budget // per_frame)))
    arguments = _arguments(model, colors, light, ambient, checker_size, supersample)
    static = dict(width=width, height=height, shadows=bool(shadows), track=track, supersample=int(supersample))
    return _frames(model, states, camera, *arguments, batch_size=batch_size, **static)


@functools.partial(jax.jit, static_argnames=_STATIC[:-1] + ("batch_size",))
def _frames(
    model, states, camera, colors, light, ambient, checker_size, *, batch_size, width, height, shadows, track,
    supersample,
) -> jnp.ndarray:  # fmt: skip
    static = dict(width=width, height=height, shadows=shadows, track=track, supersample=supersample, quantise=True)
    return jax.lax.map(
        lambda state: _image(model, state, camera, colors, light, ambient, checker_size, **static),
        states,
        batch_size=batch_size,
    )
