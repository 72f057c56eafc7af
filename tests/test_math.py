import functools

import jax
import jax.numpy as jnp
import jaxprs
import numpy as np
import pytest
from jax.sharding import PartitionSpec as P

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


def test_adjugate3_is_the_determinant_times_the_inverse():
    m = np.random.default_rng(7).normal(size=(5, 3, 3)) + 3.0 * np.eye(3)
    adjugate, determinant = math.adjugate3(jnp.asarray(m))
    np.testing.assert_allclose(determinant, np.linalg.det(m), rtol=1e-5)
    np.testing.assert_allclose(adjugate, np.linalg.det(m)[:, None, None] * np.linalg.inv(m), rtol=1e-4, atol=1e-5)


def test_definite_inverse_is_zero_with_finite_gradients_where_nothing_can_move():
    """A zero effective mass (two static bodies) and an inactive row: no inverse, and reverse mode
    through the guarded division stays finite; a positive definite one: its inverse."""
    from dbdjax.constraints import rows

    a = np.random.default_rng(8).normal(size=(3, 3))
    matrices = jnp.stack([jnp.zeros((3, 3)), jnp.asarray(a @ a.T + 0.1 * np.eye(3)), jnp.eye(3)])
    active = jnp.array([True, True, False])
    inverse, invertible = jax.vmap(rows.definite_inverse)(matrices, active)
    np.testing.assert_array_equal(invertible, [False, True, False])
    np.testing.assert_array_equal(inverse[0], 0.0)
    np.testing.assert_array_equal(inverse[2], 0.0)
    np.testing.assert_allclose(inverse[1] @ matrices[1], np.eye(3), atol=1e-4)
    gradient = jax.grad(lambda m: jnp.sum(jnp.sin(jax.vmap(rows.definite_inverse)(m, active)[0])))(matrices)
    assert np.all(np.isfinite(gradient))
    np.testing.assert_array_equal(gradient[0], 0.0)


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


# The written-out products as JAX differentiates them by itself (the references for their custom
# JVPs), and the shapes each is called with in the engine (broadcasts included).
def _plain_dot(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _plain_rotate(q, v):
    t = 2.0 * jnp.cross(q[..., 1:], v)
    return v + q[..., :1] * t + jnp.cross(q[..., 1:], t)


def _plain_multiply(p, q):
    return jnp.concatenate([p[..., :1] * q[..., :1] - jnp.sum(p[..., 1:] * q[..., 1:], -1, keepdims=True),
                            p[..., :1] * q[..., 1:] + q[..., :1] * p[..., 1:] + jnp.cross(p[..., 1:], q[..., 1:])],
                           axis=-1)  # fmt: skip


def _plain_normalize(q):
    squared = jnp.sum(q * q, axis=-1, keepdims=True)
    is_zero = squared <= 1e-24
    return jnp.where(is_zero, jnp.array([1.0, 0.0, 0.0, 0.0]), q / jnp.sqrt(jnp.where(is_zero, 1.0, squared)))


PRODUCTS = [
    (math.dot, _plain_dot, [((5, 3), (5, 3)), ((5, 3), (3,)), ((4, 1, 3), (4, 3, 3))]),
    (math.cross, jnp.cross, [((5, 3), (5, 3)), ((3,), (5, 3)), ((4, 1, 3), (4, 2, 3))]),
    (math.matvec, lambda m, v: jnp.einsum("...ij,...j->...i", m, v), [((5, 3, 3), (5, 3)), ((3, 3), (5, 3))]),
    (math.quat_rotate, _plain_rotate, [((5, 4), (5, 3)), ((5, 4), (3,)), ((5, 1, 4), (5, 3, 3)), ((4,), (5, 3))]),
    (math.quat_multiply, _plain_multiply, [((5, 4), (5, 4)), ((4,), (5, 4))]),
]


@pytest.mark.parametrize("function, plain, shapes", PRODUCTS, ids=lambda x: getattr(x, "__name__", ""))
def test_products_have_the_derivatives_of_their_written_out_formulas(function, plain, shapes, float64):
    rng = np.random.default_rng(5)
    for shape_a, shape_b in shapes:  # not unit quaternions: the derivatives hold for any q
        a, b = jnp.asarray(rng.normal(size=shape_a)), jnp.asarray(rng.normal(size=shape_b))
        np.testing.assert_allclose(function(a, b), plain(a, b), rtol=1e-13, atol=1e-13)
        for argnums in (0, 1, (0, 1)):
            expected = jax.tree.leaves(jax.jit(jax.jacrev(lambda a, b: jnp.sin(plain(a, b)), argnums))(a, b))
            for mode in (jax.jacrev, jax.jacfwd):
                got = jax.tree.leaves(jax.jit(mode(lambda a, b: jnp.sin(function(a, b)), argnums))(a, b))
                for g, e in zip(got, expected, strict=True):
                    np.testing.assert_allclose(g, e, rtol=1e-12, atol=1e-12)


def test_quat_normalize_has_the_derivative_of_its_formula_and_zero_at_the_zero_quaternion(float64):
    q = jnp.asarray(np.random.default_rng(6).normal(size=(5, 4))).at[2].set(0.0)
    for mode in (jax.jacrev, jax.jacfwd):
        np.testing.assert_allclose(
            mode(math.quat_normalize)(q), jax.jacrev(_plain_normalize)(q), rtol=1e-13, atol=1e-13
        )
    assert np.all(np.asarray(jax.jacrev(math.quat_normalize)(q))[2, :, 2] == 0.0)


def test_gradients_of_the_products_slice_no_vector():
    """Reverse mode pads the cotangent of every slice of a vector back to the vector (on XLA:CPU a kernel each):
    the products' custom JVPs keep the gradient of a rotation free of them."""
    q, v = random_quats(4), jnp.ones((4, 3))
    loss = lambda q, v: jnp.sum(math.cross(math.quat_rotate(math.quat_multiply(q, q), v), v))  # noqa: E731
    plain = lambda q, v: jnp.sum(jnp.cross(_plain_rotate(_plain_multiply(q, q), v), v))  # noqa: E731
    text = jax.jit(jax.grad(loss, (0, 1))).lower(q, v).as_text()
    assert "pad" not in text and "pad" in jax.jit(jax.grad(plain, (0, 1))).lower(q, v).as_text()


@pytest.mark.parametrize("axis", [0, 1, -1])
def test_sum_small_is_the_sum_with_no_reduce_and_its_gradient_pads_nothing(axis):
    """Additions of slices (no reduce op, which XLA:CPU runs as a kernel or library call of its own),
    whose derivative is the sum: reverse mode pads no slice back."""
    x = jnp.asarray(np.random.default_rng(0).normal(size=(4, 3, 5)), jnp.float32)
    np.testing.assert_allclose(math.sum_small(x, axis=axis), jnp.sum(x, axis=axis), rtol=1e-6, atol=1e-6)
    loss = lambda x: jnp.sum(jnp.sin(math.sum_small(x, axis=axis)))  # noqa: E731
    np.testing.assert_allclose(jax.grad(loss)(x), jax.grad(lambda x: jnp.sum(jnp.sin(jnp.sum(x, axis=axis))))(x),
                               rtol=1e-6, atol=1e-6)  # fmt: skip
    assert "reduce" not in jax.jit(functools.partial(math.sum_small, axis=axis)).lower(x).as_text()
    assert "pad" not in jax.jit(jax.grad(loss)).lower(x).as_text()


def test_row_products_are_the_dot_products_of_every_pair_of_rows():
    rng = np.random.default_rng(1)
    a, b = jnp.asarray(rng.normal(size=(2, 4, 3))), jnp.asarray(rng.normal(size=(2, 5, 3)))
    np.testing.assert_allclose(math.row_products(a, b), jnp.einsum("nki,nli->nkl", a, b), rtol=1e-6, atol=1e-6)


def _equations(jaxpr) -> int:
    """Equations of a jaxpr, those of its sub-jaxprs (custom derivatives, loops) included."""
    return sum(1 for _ in jaxprs.equations(jaxpr))


@pytest.mark.parametrize("function, plain, shapes", PRODUCTS, ids=lambda x: getattr(x, "__name__", ""))
def test_products_trace_as_one_equation_each(function, plain, shapes):
    """The traced program holds a product as one equation (its components are written out only when it
    is lowered to XLA), which every transformation of the step then walks once instead of ~25 times."""
    shape_a, shape_b = shapes[0]
    assert _equations(jax.make_jaxpr(function)(jnp.ones(shape_a), jnp.ones(shape_b)).jaxpr) == 1


def test_quat_normalize_traces_as_one_equation():
    assert _equations(jax.make_jaxpr(math.quat_normalize)(jnp.ones((5, 4))).jaxpr) == 1


@pytest.mark.parametrize("function, plain, shapes", PRODUCTS, ids=lambda x: getattr(x, "__name__", ""))
def test_products_under_vmap_equal_their_values_one_by_one(function, plain, shapes, float64):
    """vmap over either argument or both, with the batch axis first or last, and the gradient under vmap."""
    rng = np.random.default_rng(7)
    for shape_a, shape_b in shapes:
        a, b = jnp.asarray(rng.normal(size=(2,) + shape_a)), jnp.asarray(rng.normal(size=(2,) + shape_b))

        def looped(first, second):  # the two arguments' items, two of each
            return jnp.stack([plain(x, y) for x, y in zip(first, second, strict=True)])

        close = functools.partial(np.testing.assert_allclose, rtol=1e-13, atol=1e-13)
        close(jax.vmap(function)(a, b), looped(a, b))
        close(jax.vmap(function, (0, None))(a, b[0]), looped(a, [b[0], b[0]]))
        close(jax.vmap(function, (None, 0))(a[0], b), looped([a[0], a[0]], b))
        close(jax.vmap(function, (a.ndim - 1, 0))(jnp.moveaxis(a, 0, -1), b), looped(a, b))  # batch axis last
        gradient = jax.jit(jax.vmap(jax.grad(lambda a, b: jnp.sum(jnp.sin(function(a, b))), (0, 1))))(a, b)
        expected = jax.jit(jax.vmap(jax.grad(lambda a, b: jnp.sum(jnp.sin(plain(a, b))), (0, 1))))(a, b)
        for g, e in zip(gradient, expected, strict=True):
            np.testing.assert_allclose(g, e, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("function, plain, shapes", PRODUCTS, ids=lambda x: getattr(x, "__name__", ""))
def test_products_have_the_second_derivatives_of_their_written_out_formulas(function, plain, shapes, float64):
    rng = np.random.default_rng(8)
    shape_a, shape_b = shapes[0]
    a, b = jnp.asarray(rng.normal(size=shape_a)), jnp.asarray(rng.normal(size=shape_b))
    got = jax.jit(jax.hessian(lambda a, b: jnp.sum(jnp.sin(function(a, b))), (0, 1)))(a, b)
    expected = jax.jit(jax.hessian(lambda a, b: jnp.sum(jnp.sin(plain(a, b))), (0, 1)))(a, b)
    for g, e in zip(jax.tree.leaves(got), jax.tree.leaves(expected), strict=True):
        np.testing.assert_allclose(g, e, rtol=1e-11, atol=1e-11)


def test_products_refuse_arguments_that_do_not_fit_naming_the_product():
    with pytest.raises(ValueError, match="dbdjax_cross.*\\(4,\\)"):
        math.cross(jnp.ones(4), jnp.ones(3))
    with pytest.raises(ValueError, match="dbdjax_dot: leading axes"):
        math.dot(jnp.ones((2, 3)), jnp.ones((5, 3)))
    with pytest.raises(ValueError, match="dbdjax_quat_rotate: takes"):
        math.quat_rotate(jnp.ones(3), jnp.ones(3))
    with pytest.raises(ValueError, match="dbdjax_matvec: takes"):
        math.matvec(jnp.ones((3, 4)), jnp.ones(4))


def test_products_promote_their_arguments_to_one_dtype(float64):
    single, double = jnp.ones(3, jnp.float32), jnp.ones(3, jnp.float64)
    assert math.cross(single, double).dtype == jnp.float64
    assert jax.jit(math.dot)(single, single).dtype == jnp.float32


def test_products_under_shard_map_and_explicit_sharding_equal_their_written_out_values():
    """Types that name a mesh (shard_map's manual axes, explicitly sharded axes) take the written-out
    components: same values and gradients as without a mesh."""
    mesh = jax.make_mesh((1,), ("b",))
    a = jax.device_put(jnp.arange(12.0).reshape(4, 3) / 7.0, jax.sharding.NamedSharding(mesh, P("b")))
    b = jnp.asarray([0.3, -0.2, 0.9])
    loss = lambda a, b: jnp.sum(jnp.sin(math.cross(a, b)))  # noqa: E731
    expected = jax.grad(lambda a: jnp.sum(jnp.sin(jnp.cross(a, b))))(np.asarray(a))
    mapped = jax.shard_map(jax.grad(loss), mesh=mesh, in_specs=(P("b"), P()), out_specs=P("b"))
    np.testing.assert_allclose(jax.jit(mapped)(a, b), expected, rtol=1e-6)
    np.testing.assert_allclose(jax.jit(jax.grad(loss))(a, b), expected, rtol=1e-6)  # explicitly sharded


# A block of Brax's ant's upper leg as `tree.factor` eliminated it (float32, its lower leg pinned by
# its foot's contact added): eigenvalues 1.2e-4 (its spin about its own axis) to 68 (along it). The
# inverse by 3x3 Schur complements it replaced came out 2,900 times its largest entry off (the
# Schur complement of the translation lost its smallest eigenvalue 31 times over) and the tree's
# direct solve spun the resting ant's leg 0.47 rad in one sweep.
ANT_LEG_BLOCK = np.array([
    [2.2049004e01, -2.1913996e01, 2.2875135e01, 2.2881074e00, 2.2958930e00, -2.1290553e-03],
    [-2.1913998e01, 2.1907736e01, -2.2801523e01, -2.2807496e00, -2.2884996e00, -2.8899836e-03],
    [2.2875139e01, -2.2801527e01, 2.3868809e01, 2.3835783e00, 2.3916833e00, 3.9225337e-04],
    [2.2881079e00, -2.2807498e00, 2.3835783e00, 2.3876160e-01, 2.3945464e-01, 3.9682727e-05],
    [2.2958934e00, -2.2885001e00, 2.3916833e00, 2.3945464e-01, 2.4038732e-01, 3.8923205e-05],
    [-2.1288642e-03, -2.8901738e-03, 3.9225206e-04, 3.9682636e-05, 3.8923117e-05, 1.0699978e-03],
], np.float32)  # fmt: skip


def test_gauss_jordan_inverse_of_the_ant_leg_block_holds_in_float32():
    exact = np.linalg.inv(ANT_LEG_BLOCK.astype(np.float64))
    ours = np.asarray(jax.jit(math.gauss_jordan_inverse)(jnp.asarray(ANT_LEG_BLOCK)), np.float64)
    error = np.abs(ours - exact).max() / np.abs(exact).max()
    print(f"\nrelative error of the float32 inverse: {error:.1e}")  # measured 4.6e-06
    assert error < 1e-3


@pytest.mark.parametrize("size", [3, 6, 9])
def test_gauss_jordan_inverse_error_stays_within_condition_times_roundoff(size):
    """Random positive definite matrices as ill-conditioned as a pinned limb's block (condition
    1e6): the float32 inverse's error relative to its largest entry stays below condition x unit
    roundoff (0.06), a backward stable method's bound: the inverse by 3x3 Schur complements it
    replaced was off by 2.8 (6 x 6) and 1.6 (9 x 9) on these matrices. Pivoted LU
    (`jnp.linalg.inv`) printed beside."""
    rng = np.random.default_rng(size)
    rotation, _ = np.linalg.qr(rng.normal(size=(8, size, size)))
    spectrum = np.geomspace(1e-4, 1e2, size)
    matrices = ((rotation * spectrum[None, None, :]) @ np.swapaxes(rotation, -1, -2)).astype(np.float32)
    exact = np.linalg.inv(matrices.astype(np.float64))

    def error(inverse):
        return np.abs(inverse.astype(np.float64) - exact).max(axis=(-1, -2)) / np.abs(exact).max(axis=(-1, -2))

    ours = error(np.asarray(jax.jit(math.gauss_jordan_inverse)(jnp.asarray(matrices))))
    pivoted = error(np.asarray(jax.jit(jnp.linalg.inv)(jnp.asarray(matrices))))
    print(f"\nlargest relative error: ours {ours.max():.1e}, float32 LU {pivoted.max():.1e}")
    assert ours.max() < 1e6 * np.finfo(np.float32).eps / 2


@pytest.mark.parametrize("transpose_a", [False, True])
@pytest.mark.parametrize("transpose_b", [False, True])
def test_matmul_takes_either_operand_transposed(float64, transpose_a, transpose_b):
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(5, 4, 3)), rng.normal(size=(5, 3, 6))  # (n, k) @ (k, m): 4 x 3 @ 3 x 6
    a_in = np.swapaxes(a, -1, -2) if transpose_a else a
    b_in = np.swapaxes(b, -1, -2) if transpose_b else b
    ours = math.matmul(jnp.asarray(a_in), jnp.asarray(b_in), transpose_a=transpose_a, transpose_b=transpose_b)
    np.testing.assert_allclose(np.asarray(ours), a @ b, rtol=1e-13, atol=1e-13)


def test_gauss_jordan_inverse_is_exact_in_float64(float64):
    rng = np.random.default_rng(0)
    rotation, _ = np.linalg.qr(rng.normal(size=(4, 9, 9)))
    matrices = (rotation * np.geomspace(1e-4, 1e2, 9)[None, None, :]) @ np.swapaxes(rotation, -1, -2)
    exact = np.linalg.inv(matrices)
    ours = np.asarray(math.gauss_jordan_inverse(jnp.asarray(matrices, jnp.float64)))
    np.testing.assert_allclose(ours, exact, rtol=0, atol=1e-9 * np.abs(exact).max())


def test_gauss_jordan_inverse_of_a_positive_definite_matrix_plus_a_skew_part():
    """A body's block with a velocity-dependent inertia, or with a sliding contact's tilted row, is
    positive definite up to a skew part: float32 within condition x unit roundoff there too."""
    rng = np.random.default_rng(3)
    rotation, _ = np.linalg.qr(rng.normal(size=(8, 6, 6)))
    definite = (rotation * np.geomspace(1e-3, 1e2, 6)[None, None, :]) @ np.swapaxes(rotation, -1, -2)
    skew = rng.normal(size=(8, 6, 6))
    matrices = (definite + 0.5 * (skew - np.swapaxes(skew, -1, -2))).astype(np.float32)
    exact = np.linalg.inv(matrices.astype(np.float64))
    condition = np.linalg.cond(matrices.astype(np.float64))
    ours = np.asarray(jax.jit(math.gauss_jordan_inverse)(jnp.asarray(matrices)), np.float64)
    error = np.abs(ours - exact).max(axis=(-1, -2)) / np.abs(exact).max(axis=(-1, -2))
    assert np.all(error < condition * np.finfo(np.float32).eps / 2)
