"""The ray-cast renderer (dbdjax/render.py) and the video writer (dbdjax/video.py).

Geometry is checked against an independent pinhole projection written out here and against brute
force: marching each pixel's ray through the shape's signed distance function in numpy.
"""

from __future__ import annotations

import functools
import sys
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dbdjax as dbd
from dbdjax import render as R
from dbdjax import video

W, H = 64, 48
RED, BLUE, GREEN = (0.8, 0.4, 0.2), (0.2, 0.4, 0.8), (0.3, 0.7, 0.3)
INERTIA = (0.01, 0.01, 0.01)  # explicit mass properties: the body frame stays where it is given


def _quat(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def _matrix(q):
    """Rotation matrix of a unit quaternion (w, x, y, z), written independently of dbdjax.math."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _pixel(position, look_at, fov, point, width=W, height=H):
    """(row, column) of the pixel that `point` falls in, for a pinhole camera with z up on screen.

    The view frame: forward f toward look_at, right r = f x z (looking along +y, +x is on the
    right), up u = r x f. Image plane at unit distance spans tan(fov/2) vertically and
    tan(fov/2) * width / height horizontally; row 0 is the top."""
    position, look_at, point = (np.asarray(v, float) for v in (position, look_at, point))
    f = (look_at - position) / np.linalg.norm(look_at - position)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    v = point - position
    tan_half = np.tan(np.radians(fov) / 2)
    x = (v @ r) / (v @ f) / (tan_half * width / height)
    y = (v @ u) / (v @ f) / tan_half
    return int(np.floor((1 - y) / 2 * height)), int(np.floor((x + 1) / 2 * width))


def _shade(pixel, color):
    """The shading factor s of a pixel = round(255 s color), one estimate per channel."""
    return np.asarray(pixel, float) / 255.0 / np.asarray(color)


@pytest.fixture(scope="module")
def two_bodies():
    """A sphere (body 0, RED) and a larger box (body 1, BLUE), no plane; camera on -y looking +y."""
    b = dbd.ModelBuilder(gravity=(0, 0, 0))
    ball = b.add_body(pos=(0.0, 0.0, 0.5), mass=1.0, inertia=INERTIA)
    b.add_sphere(ball, radius=0.3)
    crate = b.add_body(pos=(0.0, 3.0, 0.5), mass=1.0, inertia=INERTIA)
    b.add_box(crate, half_extents=(0.8, 0.3, 0.6))
    model = b.finalize(dt=0.01)
    camera = R.Camera(position=(0.0, -4.0, 0.5), look_at=(0.0, 0.0, 0.5), fov=60.0, width=W, height=H)
    colors = np.array([RED, BLUE])
    # top-level calls share one compiled function per model, image size and static option
    draw = functools.partial(R.render, model, camera=camera, colors=colors)
    return model, camera, colors, draw


def _moved(state, body, pos):
    return dbd.State(state.pos.at[body].set(jnp.asarray(pos, state.pos.dtype)), state.quat, state.vel, state.ang_vel)


def test_render_returns_height_width_rgb_uint8(two_bodies):
    model, camera, _, draw = two_bodies
    image = draw(dbd.init(model))
    assert image.shape == (H, W, 3) and image.dtype == jnp.uint8
    small = R.render(model, dbd.init(model), camera, width=20, height=10)
    assert small.shape == (10, 20, 3)


def test_sphere_shows_at_its_projected_pixel_in_its_body_colour(two_bodies):
    model, camera, _, draw = two_bodies
    centre = (0.6, 0.0, 0.9)
    state = _moved(dbd.init(model), 1, (0.0, 50.0, 0.0))  # the box out of the way
    image = np.asarray(draw(_moved(state, 0, centre)))
    empty = np.asarray(draw(_moved(state, 0, (0.0, -50.0, 0.0))))  # the sphere behind the camera
    row, column = _pixel((0.0, -4.0, 0.5), (0.0, 0.0, 0.5), 60.0, centre)
    assert (row, column) != (H // 2, W // 2)  # off-centre, so a wrong projection would miss it
    where, depth = R.project(camera, jnp.asarray(centre))
    assert (int(np.floor(where[1])), int(np.floor(where[0]))) == (row, column) and float(depth) > 0.0
    assert np.abs(image[row, column].astype(int) - empty[row, column]).sum() > 30  # not the background
    shade = _shade(image[row, column], RED)
    # one shading factor for all three channels (up to rounding), between ambient and full light
    np.testing.assert_allclose(shade, shade.mean(), atol=0.5 / 255 / min(RED) + 1e-6)
    assert 0.35 - 0.01 <= shade.mean() <= 1.0 + 0.01
    # z is up on screen and +x (to the right of a camera looking along +y) is on the right
    assert row < H // 2 and column > W // 2


def test_box_behind_sphere_is_occluded_where_they_overlap(two_bodies):
    model, _, _, draw = two_bodies
    image = np.asarray(draw(dbd.init(model)))
    eye, target = (0.0, -4.0, 0.5), (0.0, 0.0, 0.5)
    row, column = _pixel(eye, target, 60.0, (0.0, 0.0, 0.5))  # the sphere's centre, in front of the box
    shade = _shade(image[row, column], RED)
    np.testing.assert_allclose(shade, shade.mean(), atol=0.5 / 255 / min(RED) + 1e-6)
    row, column = _pixel(eye, target, 60.0, (0.6, 2.7, 0.5))  # the box's front face beside the sphere
    shade = _shade(image[row, column], BLUE)
    np.testing.assert_allclose(shade, shade.mean(), atol=0.5 / 255 / min(BLUE) + 1e-6)


def test_moving_a_body_moves_its_image(two_bodies):
    model, _, _, _ = two_bodies
    state = _moved(dbd.init(model), 1, (0.0, 50.0, 0.0))

    def segment(s):
        return R.cast_rays(model, s, two_bodies[1]).shape

    rows, columns = np.mgrid[0:H, 0:W]

    def centroid(pos):
        mask = np.asarray(segment(_moved(state, 0, pos))) == 0
        assert mask.sum() > 20
        return rows[mask].mean(), columns[mask].mean()

    row0, column0 = centroid((0.0, 0.0, 0.5))
    row1, column1 = centroid((0.5, 0.0, 0.5))  # +x: right on screen
    assert column1 - column0 > 3 and abs(row1 - row0) < 0.5
    row2, column2 = centroid((0.0, 0.0, 0.9))  # +z: up on screen
    assert row0 - row2 > 3 and abs(column2 - column0) < 0.5
    mask_far = np.asarray(segment(_moved(state, 0, (0.0, 1.0, 0.5)))) == 0
    mask_near = np.asarray(segment(_moved(state, 0, (0.0, 0.0, 0.5)))) == 0
    assert mask_far.sum() < mask_near.sum()


@pytest.fixture(scope="module")
def ground():
    b = dbd.ModelBuilder()
    ball = b.add_body(pos=(0.0, 0.0, 1.0), mass=1.0, inertia=INERTIA)
    b.add_sphere(ball, radius=0.3)
    b.add_plane()
    return b.finalize(dt=0.01)


def test_plane_shows_a_checkerboard_with_the_parity_of_the_hit_point(ground):
    state = _moved(dbd.init(ground), 0, (0.0, 0.0, -50.0))  # only the plane in view
    camera = R.camera_looking_at((0.3, 0.2, 0.0), 2.0, azimuth=-90.0, elevation=90.0, fov=60.0, width=W, height=H)
    image = np.asarray(R.render(ground, state, camera, checker_size=0.5))
    hits = R.cast_rays(ground, state, camera)
    assert bool(jnp.all(hits.hit))
    point = np.asarray(hits.point, float)
    np.testing.assert_allclose(point[..., 2], 0.0, atol=1e-5)
    # parity of the square holding each pixel's ground point, away from the square edges
    scaled = point[..., :2] / 0.5
    odd = (np.floor(scaled).sum(-1) % 2).astype(bool)
    clear = np.all(np.abs(scaled - np.round(scaled)) > 1e-3, axis=-1)
    brightness = image.astype(int).sum(-1)
    light, dark = brightness[clear & ~odd], brightness[clear & odd]
    assert light.size > 300 and dark.size > 300
    assert light.min() > dark.max()  # every light square brighter than every dark one
    assert np.ptp(light) <= 3 and np.ptp(dark) <= 3  # two flat colours (straight down: no fading)


def test_shadow_falls_below_a_body_along_the_light(ground):
    eye, target = (0.0, -4.0, 3.0), (0.0, 0.0, 0.0)
    camera = R.Camera(position=eye, look_at=target, fov=45.0, width=W, height=H)
    state = dbd.init(ground)
    lit = np.asarray(R.render(ground, state, camera, shadows=False, light=(0, 0, 1)), float)
    shaded = np.asarray(R.render(ground, state, camera, shadows=True, light=(0, 0, 1), ambient=0.35), float)
    row, column = _pixel(eye, target, 45.0, (0.0, 0.0, 0.0))  # straight below the sphere
    np.testing.assert_allclose(shaded[row, column] / lit[row, column], 0.35, atol=1.0 / lit[row, column].min())
    row, column = _pixel(eye, target, 45.0, (1.2, 0.0, 0.0))  # open ground
    np.testing.assert_array_equal(shaded[row, column], lit[row, column])


def test_supersampling_averages_the_picture_of_a_finer_camera(ground):
    camera = R.camera_looking_at((0.0, 0.0, 0.5), 4.0, fov=45.0, width=W // 2, height=H // 2)
    state = dbd.init(ground)
    smooth = np.asarray(R.render_float(ground, state, camera, supersample=2))
    fine = np.asarray(R.render_float(ground, state, camera.replace(width=W, height=H)))
    assert smooth.shape == (H // 2, W // 2, 3)
    blocks = fine.reshape(H // 2, 2, W // 2, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(smooth, blocks, atol=1e-6)
    assert np.abs(fine[::2, ::2] - fine[1::2, 1::2]).max() > 0.1  # edges inside pixels: the mean matters


def test_batched_render_equals_per_state_render(ground):
    camera = R.camera_looking_at((0.0, 0.0, 0.5), 4.0, fov=45.0, width=W, height=H)
    state = dbd.init(ground)
    states = jax.tree.map(lambda x: jnp.stack([x, x, x]), state)
    states = dbd.State(states.pos + jnp.array([[[0.0, 0.0, 0.0]], [[0.3, 0.0, 0.1]], [[-0.4, 0.2, -0.3]]]),
                       states.quat, states.vel, states.ang_vel)  # fmt: skip
    batched = np.asarray(R.render(ground, states, camera))  # leading batch axis
    each = np.stack([np.asarray(R.render(ground, jax.tree.map(lambda x, i=i: x[i], states), camera)) for i in range(3)])
    assert batched.shape == (3, H, W, 3)
    np.testing.assert_array_equal(batched, each)
    mapped = jax.jit(jax.vmap(lambda s: R.render(ground, s, camera)))(states)  # inside the user's jit and vmap
    np.testing.assert_array_equal(mapped, each)
    assert not np.array_equal(each[0], each[1])  # the states differ, so do the pictures
    rolled = np.asarray(R.render_rollout(ground, states, camera, batch_size=2))  # 3 frames in batches of 2
    np.testing.assert_array_equal(rolled, each)
    # without a camera the whole trajectory is framed once: every frame from the same viewpoint
    framed = R.default_camera(ground, states, width=W, height=H)
    rolled = np.asarray(R.render_rollout(ground, states, width=W, height=H, batch_size=2))
    np.testing.assert_array_equal(rolled[2], R.render(ground, jax.tree.map(lambda x: x[2], states), framed))


@pytest.fixture(scope="module")
def parallel_scene():
    """A camera on the plane z = 0 looking along +y at a capsule whose axis is the view axis, a
    box and a zero-length capsule. Odd image sizes: the centre row's rays are exactly horizontal
    and the centre pixel's ray runs exactly along +y (parallel to the plane, to four box faces and
    to the capsule's axis)."""
    b = dbd.ModelBuilder()
    rod = b.add_body(pos=(0.0, 2.0, 0.0), mass=1.0, inertia=INERTIA)
    b.add_capsule(rod, radius=0.2, half_length=0.5, quat=_quat((1, 0, 0), np.pi / 2))  # axis along y
    crate = b.add_body(pos=(0.0, 4.0, 0.0), mass=1.0, inertia=INERTIA)
    b.add_box(crate, half_extents=(0.3, 0.3, 0.3))
    b.add_capsule(crate, radius=0.1, half_length=0.0, pos=(0.5, 0.0, 0.0))  # a zero-length capsule
    b.add_plane()
    model = b.finalize(dt=0.01)
    camera = R.Camera(position=(0.0, -1.0, 0.0), look_at=(0.0, 0.0, 0.0), fov=50.0, width=33, height=25)
    return model, camera


def test_camera_on_the_plane_with_rays_parallel_to_it_gives_finite_pictures(parallel_scene):
    model, camera = parallel_scene
    rays = np.asarray(R.camera_rays(camera))
    assert rays[12, 16, 2] == 0.0 and rays[12, 16, 0] == 0.0  # parallel to the plane, to box faces, to the axis
    state = dbd.init(model)
    picture = R.render_float(model, state, camera)
    assert picture.dtype == jnp.float32 and float(picture.min()) >= 0.0 and float(picture.max()) <= 1.0
    hits = R.cast_rays(model, state, camera)
    assert bool(jnp.all(jnp.isfinite(picture)))
    assert bool(jnp.all(jnp.isfinite(hits.normal))) and bool(jnp.all(jnp.isfinite(hits.point)))
    assert int(hits.shape[12, 16]) == 0  # the centre ray runs along the capsule's axis into its end
    np.testing.assert_allclose(float(hits.distance[12, 16]), 3.0 - 0.5 - 0.2, rtol=1e-6)
    # a camera that looks straight down its own up vector still has a frame
    down = R.Camera(position=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), width=33, height=25)
    picture = R.render_float(model, state, down)
    assert bool(jnp.all(jnp.isfinite(picture)))
    assert float(picture.max() - picture.min()) > 0.1  # rays spread over the checkerboard, not one point
    # a camera inside the box sees its walls from within
    inside = R.Camera(position=(0.0, 4.0, 0.1), look_at=(1.0, 4.0, 0.1), fov=50.0, width=33, height=25)
    assert bool(jnp.all(jnp.isfinite(R.render_float(model, state, inside))))
    hits = R.cast_rays(model, state, inside)
    assert bool(jnp.all(hits.hit)) and int(hits.shape[12, 16]) == 1
    np.testing.assert_allclose(float(hits.distance[12, 16]), 0.3, rtol=1e-6)
    np.testing.assert_allclose(hits.normal[12, 16], [-1.0, 0.0, 0.0], atol=1e-6)  # facing the camera


@pytest.mark.slow
def test_gradient_of_a_picture_is_finite_with_rays_parallel_to_the_plane(parallel_scene):
    model, camera = parallel_scene
    state = dbd.init(model)

    def brightness(pos):
        return R.render_float(model, dbd.State(pos, state.quat, state.vel, state.ang_vel), camera).sum()

    gradient = jax.jit(jax.grad(brightness))(state.pos)
    assert bool(jnp.all(jnp.isfinite(gradient))) and bool(jnp.any(gradient != 0.0))


# ------------------------------------------------------------------------------------------------
# Brute force: march each ray through the shape's signed distance function
# ------------------------------------------------------------------------------------------------


def _sdf(kind, size, x):
    """Signed distance (...,) of local points x (..., 3) to a shape."""
    if kind == "sphere":
        return np.linalg.norm(x, axis=-1) - size[0]
    if kind == "capsule":
        axis = np.zeros_like(x)
        axis[..., 2] = np.clip(x[..., 2], -size[1], size[1])
        return np.linalg.norm(x - axis, axis=-1) - size[0]
    if kind == "box":
        q = np.abs(x) - size
        return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)
    return x[..., 2]  # plane: local z


def test_every_kind_matches_marching_the_signed_distance_hit_shape_depth_and_normal(float64):
    """Four bodies with a sphere, a capsule, a zero-length capsule and a box (each off-centre and
    turned in its body, the bodies turned too) above a tilted plane: which shape each pixel's ray
    meets first, how far, and the normal there, against marching the ray through every shape's
    signed distance in numpy."""
    kinds = ["sphere", "capsule", "capsule", "box", "plane"]
    sizes = np.array([(0.35, 0.0, 0.0), (0.2, 0.4, 0.0), (0.3, 0.0, 0.0), (0.4, 0.25, 0.15), (0.0, 0.0, 0.0)])
    body_pos = np.array([(-0.6, -0.5, 0.6), (0.7, -0.4, 0.5), (-0.6, 0.7, 0.5), (0.6, 0.7, 0.6)])
    body_quat = [
        _quat((1.0, 2.0, 0.5), 0.7),
        _quat((0.0, 1.0, 1.0), -0.5),
        _quat((1, 0, 0), 0.3),
        _quat((1, 1, 1), 0.9),
    ]
    local_pos, local_quat = np.array([0.05, -0.1, 0.1]), _quat((0.3, -1.0, 0.2), 1.1)
    normal = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    b = dbd.ModelBuilder()
    poses = []  # (world position, world rotation matrix) of each shape
    for i, kind in enumerate(kinds[:4]):
        body = b.add_body(pos=body_pos[i], quat=body_quat[i], mass=1.0, inertia=INERTIA)
        if kind == "sphere":
            b.add_sphere(body, sizes[i, 0], pos=local_pos)
        elif kind == "capsule":
            b.add_capsule(body, sizes[i, 0], sizes[i, 1], pos=local_pos, quat=local_quat)
        else:
            b.add_box(body, sizes[i], pos=local_pos, quat=local_quat)
        poses.append((body_pos[i] + _matrix(body_quat[i]) @ local_pos, _matrix(body_quat[i]) @ _matrix(local_quat)))
    b.add_plane(normal=normal, offset=-0.3)
    tangent = np.cross(normal, [1.0, 0.0, 0.0])
    tangent /= np.linalg.norm(tangent)
    poses.append((-0.3 * normal, np.stack([tangent, np.cross(normal, tangent), normal], axis=1)))  # z: the normal
    model = b.finalize(dt=0.01)
    camera = R.Camera(position=(1.2, -3.4, 3.3), look_at=(0.0, 0.1, 0.3), fov=40.0, width=W, height=H)
    hits = R.cast_rays(model, dbd.init(model), camera)
    assert hits.distance.dtype == jnp.float64

    rays = np.asarray(hits.rays)
    step = 2e-3
    lowest = np.full((len(kinds),) + rays.shape[:2], np.inf)  # smallest signed distance along each ray
    first = np.full(rays.shape[:2], np.inf)  # first sample inside any shape
    which = np.full(rays.shape[:2], -1)  # and that shape
    for chunk in np.array_split(np.arange(2.5, 12.0, step), 40):
        points = np.asarray(camera.position) + chunk[:, None, None, None] * rays  # (S, H, W, 3)
        # world -> local: R^T (x - p), on row vectors (x - p) @ R
        sdf = np.stack(
            [_sdf(kind, size, (points - p) @ m) for kind, size, (p, m) in zip(kinds, sizes, poses, strict=True)]
        )
        lowest = np.minimum(lowest, sdf.min(axis=1))
        entered = (sdf < 0.0).any(axis=0)  # (S, H, W)
        new = np.isinf(first) & entered.any(axis=0)
        sample = np.argmax(entered, axis=0)
        first = np.where(new, chunk[sample], first)
        at_entry = np.take_along_axis(sdf, sample[None, None], axis=1)[:, 0]  # (K, H, W)
        which = np.where(new, np.argmin(at_entry, axis=0), which)
    # rays whose samples cannot misjudge them: every shape either clearly missed or clearly entered
    clear = np.all(np.abs(lowest) > step, axis=0)
    inside = which >= 0
    assert clear.mean() > 0.9
    for k in range(len(kinds)):
        assert (clear & (which == k)).sum() > 30  # every shape seen on many pixels
    np.testing.assert_array_equal(np.asarray(hits.hit)[clear], inside[clear])
    np.testing.assert_array_equal(np.asarray(hits.shape)[clear], which[clear])
    # the surface lies within one step before the first sample inside
    seen = clear & inside
    distance = np.asarray(hits.distance)[seen]
    assert np.all(distance <= first[seen] + 1e-9) and np.all(distance >= first[seen] - step - 1e-9)
    # normals: the gradient of the hit shape's distance function at the hit point, where smooth
    eps = 1e-6
    for k, (kind, size, (p, m)) in enumerate(zip(kinds, sizes, poses, strict=True)):
        mask = seen & (which == k)
        x = (np.asarray(hits.point)[mask] - p) @ m
        gradient = np.stack(
            [(_sdf(kind, size, x + eps * e) - _sdf(kind, size, x - eps * e)) / (2 * eps) for e in np.eye(3)], -1
        )
        smooth = np.abs(np.linalg.norm(gradient, axis=-1) - 1.0) < 1e-4
        if kind == "box":  # the face is ambiguous within a hair of an edge
            smooth &= np.sort(np.abs(x) - size, axis=-1)[:, 1] < -1e-3
        assert smooth.mean() > 0.8
        expected = gradient[smooth] @ m.T
        toward = -np.sign(np.sum(expected * rays[mask][smooth], axis=-1, keepdims=True))  # face the camera
        np.testing.assert_allclose(np.asarray(hits.normal)[mask][smooth], toward * expected, atol=1e-5)


def test_zero_length_capsule_renders_like_a_sphere(float64):
    pictures = []
    for add in ("sphere", "capsule"):
        b = dbd.ModelBuilder()
        body = b.add_body(pos=(0.0, 0.0, 0.5), quat=_quat((1, 1, 0), 0.4), mass=1.0, inertia=INERTIA)
        if add == "sphere":
            b.add_sphere(body, 0.4)
        else:
            b.add_capsule(body, 0.4, 0.0)
        b.add_plane()
        model = b.finalize(dt=0.01)
        camera = R.camera_looking_at((0.0, 0.0, 0.4), 3.0, fov=45.0, width=W, height=H)
        pictures.append(np.asarray(R.render(model, dbd.init(model), camera), int))
    assert np.abs(pictures[0] - pictures[1]).max() <= 1


def test_tracking_camera_keeps_the_body_at_the_image_centre(two_bodies):
    model, camera, _, _ = two_bodies
    state = _moved(_moved(dbd.init(model), 1, (0.0, 50.0, 0.0)), 0, (2.0, 1.0, 1.5))
    followed = R.follow(camera, state, 0)
    np.testing.assert_allclose(followed.look_at, [2.0, 1.0, 1.5])
    np.testing.assert_allclose(followed.position - followed.look_at, camera.position - camera.look_at, atol=1e-6)
    level = R.follow(camera, state, 0, axes=(True, True, False))
    np.testing.assert_allclose(level.look_at, [2.0, 1.0, 0.5])
    shapes = np.asarray(R.cast_rays(model, state, followed).shape)
    rows, columns = np.mgrid[0:H, 0:W]
    mask = shapes == 0
    assert mask.sum() > 20
    np.testing.assert_allclose([rows[mask].mean(), columns[mask].mean()], [(H - 1) / 2, (W - 1) / 2], atol=0.5)
    tracked = R.render(model, state, camera, track=0, colors=two_bodies[2])
    np.testing.assert_array_equal(tracked, R.render(model, state, followed, colors=two_bodies[2]))


def test_default_camera_frames_every_body(two_bodies):
    model, _, colors, _ = two_bodies
    state = _moved(dbd.init(model), 1, (2.0, 1.0, -1.0))
    camera = R.default_camera(model, state, width=W, height=H)
    shapes = np.asarray(R.cast_rays(model, state, camera).shape)
    for body in (0, 1):
        assert (shapes == body).sum() > 10
    border = np.concatenate([shapes[0], shapes[-1], shapes[:, 0], shapes[:, -1]])
    assert np.all(border == -1)  # nothing cut off at the edges
    image = R.render(model, state, width=W, height=H, colors=colors)
    np.testing.assert_array_equal(image, R.render(model, state, camera, colors=colors))


def test_colors_override_the_palette(two_bodies):
    model, camera, _, _ = two_bodies
    state = dbd.init(model)
    row, column = _pixel((0.0, -4.0, 0.5), (0.0, 0.0, 0.5), 60.0, (0.0, 0.0, 0.5))
    default = np.asarray(R.render(model, state, camera))[row, column]
    shade = _shade(default, R.body_colors(2)[0])
    np.testing.assert_allclose(shade, shade.mean(), atol=0.5 / 255 / R.body_colors(2)[0].min() + 1e-6)
    green = np.asarray(R.render(model, state, camera, colors=[GREEN, BLUE]))[row, column]
    np.testing.assert_allclose(_shade(green, GREEN), shade.mean(), atol=0.5 / 255 / min(GREEN) + 1e-6)
    with pytest.raises(ValueError, match="colors must be"):
        R.render(model, state, camera, colors=[GREEN])


# ------------------------------------------------------------------------------------------------
# Video files
# ------------------------------------------------------------------------------------------------


def test_gif_is_written_and_reads_back_with_every_frame(two_bodies, tmp_path):
    from PIL import Image

    model, camera, colors, draw = two_bodies
    state = dbd.init(model)
    frames = np.stack([np.asarray(draw(_moved(state, 0, (0.2 * i - 0.4, 0.0, 0.5)))) for i in range(5)])
    path = video.save_video(frames, tmp_path / "clip.gif", fps=20)
    with Image.open(path) as gif:
        assert gif.n_frames == 5 and gif.size == (W, H)
        assert gif.info["duration"] == 50 and gif.info["loop"] == 0
        for i in range(5):
            gif.seek(i)
            back = np.asarray(gif.convert("RGB"), int)
            assert np.abs(back - frames[i]).mean() < 2.0  # palette quantisation only
    png = video.save_image(frames[2], tmp_path / "frame.png")
    with Image.open(png) as picture:
        np.testing.assert_array_equal(np.asarray(picture.convert("RGB")), frames[2])


def test_mp4_without_its_dependencies_names_what_is_missing(tmp_path, monkeypatch):
    frames = np.zeros((2, 8, 8, 3), np.uint8)
    monkeypatch.setitem(sys.modules, "mediapy", None)  # import mediapy raises ImportError
    with pytest.raises(ImportError, match="mediapy"):
        video.save_video(frames, tmp_path / "clip.mp4")
    monkeypatch.setitem(sys.modules, "mediapy", types.ModuleType("mediapy"))
    monkeypatch.setattr(video.shutil, "which", lambda name: None)
    with pytest.raises(RuntimeError, match="ffmpeg"):
        video.save_video(frames, tmp_path / "clip.mp4")
    with pytest.raises(ValueError, match="unknown video format"):
        video.save_video(frames, tmp_path / "clip.xyz")
    with pytest.raises(ValueError, match="uint8"):
        video.save_video(frames.astype(float), tmp_path / "clip.gif")


def test_video_module_is_not_imported_by_the_package():
    import subprocess

    code = "import sys, dbdjax; print('dbdjax.video' in sys.modules, 'PIL' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]
