import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dbdjax import math


def random_quats(count, seed=0):
    q = np.random.default_rng(seed).normal(size=(count, 4))
    return jnp.asarray(q / np.linalg.norm(q, axis=-1, keepdims=True))


def test_quat_rotate_matches_rotation_matrix():
    q = random_quats(16)
    v = jnp.asarray(np.random.default_rng(1).normal(size=(16, 3)))
    np.testing.assert_allclose(math.quat_rotate(q, v), jnp.einsum("nij,nj->ni", math.quat_to_matrix(q), v), atol=1e-5)


def test_quat_multiply_composes_rotations():
    p, q = random_quats(8, 2), random_quats(8, 3)
    v = jnp.ones((8, 3))
    np.testing.assert_allclose(
        math.quat_rotate(math.quat_multiply(p, q), v), math.quat_rotate(p, math.quat_rotate(q, v)), atol=1e-5
    )


def test_exp_and_log_are_inverse():
    rotation = jnp.asarray(np.random.default_rng(4).uniform(-1.5, 1.5, size=(32, 3)))
    np.testing.assert_allclose(math.quat_log(math.quat_exp(rotation)), rotation, atol=1e-5)
    q = random_quats(32, 5)
    same = math.quat_exp(math.quat_log(q))
    np.testing.assert_allclose(
        jnp.abs(math.dot(jnp.asarray(same[:, 1:]), q[:, 1:]) + same[:, 0] * q[:, 0]), 1.0, atol=1e-5
    )


def test_skew_is_the_cross_product():
    a, b = jnp.array([1.0, 2.0, 3.0]), jnp.array([-0.5, 0.1, 2.0])
    np.testing.assert_allclose(math.skew(a) @ b, jnp.cross(a, b), atol=1e-6)


def test_twist_angle_of_a_pure_twist_is_its_angle():
    axis = jnp.array([0.0, 0.0, 1.0])
    for angle in (-3.0, -1.0, 0.0, 0.5, 3.1):
        assert float(math.quat_twist_angle(math.quat_exp(angle * axis), axis)) == pytest.approx(angle, abs=1e-5)


@pytest.mark.parametrize(
    "function, argument",
    [
        (lambda v: math.safe_norm(v), jnp.zeros(3)),
        (lambda v: jnp.sum(math.safe_normalize(v)[0]), jnp.zeros(3)),
        (lambda v: math.safe_normalize(v)[1], jnp.zeros(3)),
        (lambda v: jnp.sum(math.quat_exp(v)), jnp.zeros(3)),
        (lambda v: jnp.sum(math.quat_log(math.quat_exp(v))), jnp.zeros(3)),
        (
            lambda v: math.angle_between(
                jnp.array([0.0, 0.0, 1.0]), math.safe_normalize(v + jnp.array([0.0, 0.0, 1.0]))[0]
            )[0],
            jnp.zeros(3),
        ),
        (lambda x: math.safe_asin(x[0]), jnp.ones(3)),
        (lambda v: jnp.sum(math.shortest_rotation(v)), jnp.zeros(3)),
        (lambda v: jnp.sum(math.shortest_rotation(v)), jnp.array([0.0, jnp.pi, 0.0])),
        (lambda x: math.safe_atan2(x[0], x[1]), jnp.zeros(3)),
    ],
)
def test_gradients_are_finite_at_singular_points(function, argument):
    value = function(argument)
    gradient = jax.grad(function)(argument)
    assert np.all(np.isfinite(value)) and np.all(np.isfinite(gradient))


def test_safe_norm_gradient_is_exact_away_from_zero():
    v = jnp.array([3.0, 4.0, 0.0])
    np.testing.assert_allclose(jax.grad(math.safe_norm)(v), v / 5.0, atol=1e-6)


def test_inverse3_inverts():
    m = jnp.asarray(np.random.default_rng(6).normal(size=(5, 3, 3))) + 3.0 * jnp.eye(3)
    np.testing.assert_allclose(math.inverse3(m) @ m, jnp.broadcast_to(jnp.eye(3), (5, 3, 3)), atol=1e-5)


def test_shortest_rotation_turns_as_the_vector_does_by_at_most_pi():
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    angles = rng.uniform(0.0, 40.0, size=200)
    vectors = jnp.asarray(axes * angles[:, None])
    shortest = math.shortest_rotation(vectors)
    assert np.all(np.linalg.norm(np.asarray(shortest), axis=-1) <= np.pi + 1e-5)
    same = np.abs(np.sum(np.asarray(math.quat_exp(shortest) * math.quat_exp(vectors)), axis=-1))
    np.testing.assert_allclose(same, 1.0, atol=1e-5)  # q and -q: the same rotation
    below = angles <= np.pi
    np.testing.assert_array_equal(np.asarray(shortest)[below], np.asarray(vectors)[below])
