"""Quaternion and vector math shared by the whole engine.

Quaternions are arrays (..., 4) ordered (w, x, y, z); vectors are (..., 3). Every function
broadcasts over leading axes. Functions that divide by a norm or take an `arcsin`/`arctan2`
that can meet a singular point go through the *double-where* trick, decided per element, so
that the gradient is finite wherever the value is (JAX FAQ, "gradients contain NaN where using
where"). The value at the singular point is the limit, not a scrubbed NaN.

The products (dot, cross, matvec, quaternion product and rotation, normalisation) are written out
component by component, which XLA fuses into the kernels around them: each takes its arguments'
components, computes on those and stacks its result once (`_components`). An operation on a whole
(..., 3) or (..., 4) array inside one (`q / |q|`, `w * t` with w broadcast along the components)
kept XLA:CPU from fusing a chain of them into arithmetic on whole components: Brax's humanoid
stepped 1.2x slower at batch 256 (docs/brax_comparison.md, "Session 42"). Each is a JAX primitive of its own
(`_written_out_primitive`), for two reasons:
- Its derivative is a matrix (the derivative at the primals) times the tangent, summed over the
  last axis (`_times`), which reverse mode transposes into products again. Left to JAX, every
  component slice `v[..., k]` would become, in reverse mode, a kernel of its own that pads the
  slice's cotangent back to the whole vector (on CPU a sixth of the kernels of Brax's ant's
  gradient): Brax's humanoid's gradient ran 1.9x faster (docs/brax_comparison.md, "Session 39").
- A traced program holds one equation for a product instead of its ~25 component operations, and
  every transformation (vmap, linearize, remat, transpose) walks the program: the humanoid's step
  is traced as 7,854 equations instead of 20,193, and the grad of its 100-step rollout in 10 s
  instead of 19 (docs/brax_comparison.md, "Session 40: the products as primitives"). Only the lowering to XLA writes
  the components out. Arguments whose types name a mesh (`shard_map`, explicit sharding) take the
  written-out components directly (`_unsharded`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import ShapedArray
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

# The written-out function of each product primitive, by the primitive's name (`trailing_batch`
# evaluates them in place).
WRITTEN_OUT: dict[str, Callable] = {}

# Below this squared length a vector is treated as zero (its direction is undefined).
_TINY_SQUARED = 1e-24


def _times(matrix: jnp.ndarray, vector: jnp.ndarray) -> jnp.ndarray:
    """matrix (..., n, m) times vector (..., m) as a product summed over the last axis: the form a
    tangent takes here, which reverse mode transposes without slicing (module docstring)."""
    return jnp.sum(matrix * vector[..., None, :], axis=-1)


def matmul(a: jnp.ndarray, b: jnp.ndarray, transpose_a: bool = False, transpose_b: bool = False) -> jnp.ndarray:
    """a (..., n, k) @ b (..., k, m) as k broadcast products summed: no dot op, which costs XLA:CPU far
    more to compile and to run on 3 x 3 matrices than these multiplications, which fuse.
    transpose_a: a is (..., k, n) and a^T is taken; transpose_b: b is (..., m, k) and b^T is taken
    (read by slicing the other axis: a transposed operand would be one more kernel on CPU)."""
    column = (lambda k: a[..., k, :, None]) if transpose_a else (lambda k: a[..., :, k, None])
    row = (lambda k: b[..., None, :, k]) if transpose_b else (lambda k: b[..., None, k, :])
    total = column(0) * row(0)
    for k in range(1, a.shape[-2] if transpose_a else a.shape[-1]):
        total = total + column(k) * row(k)
    return total


def _components(x: jnp.ndarray) -> tuple[jnp.ndarray, ...]:
    """The components x[..., k] of a vector or quaternion, each (...,): what the products' written-out
    forms compute on (module docstring)."""
    return tuple(x[..., k] for k in range(x.shape[-1]))


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def sum_small(x: jnp.ndarray, axis: int = -1) -> jnp.ndarray:
    """x summed over a short `axis` (a few entries) as additions of its slices: no reduce op, which
    XLA:CPU runs as a kernel of its own (for a batch, a library call that cost 50 ns an element on
    the humanoid's impulse solve), while additions fuse with the arithmetic around them. Its
    derivative is the sum itself, which reverse mode transposes into one broadcast (the slices'
    transposes would be a padding kernel each, as the module docstring says of the products)."""
    parts = [jax.lax.index_in_dim(x, k, axis, keepdims=False) for k in range(x.shape[axis])]
    return functools.reduce(jnp.add, parts[1:], parts[0])


@sum_small.defjvp
def _sum_small_jvp(axis, primals, tangents):
    return sum_small(primals[0], axis), jnp.sum(tangents[0], axis=axis)


def row_products(rows_1: jnp.ndarray, rows_2: jnp.ndarray) -> jnp.ndarray:
    """(..., K, L) dot products of every row of rows_1 (..., K, 3) with every row of rows_2
    (..., L, 3): `dot` broadcast, not a batched matrix product, which compiles to far more code on
    CPU and runs as a library call of its own there."""
    return dot(rows_1[..., :, None, :], rows_2[..., None, :, :])


def _unsharded(x: jnp.ndarray) -> bool:
    """True where the type of x names no mesh: no explicitly sharded axes, no `shard_map` manual axes.
    The primitives' shape rule gives types without those, so for such arguments the written-out
    components run instead (JAX's own operations, which carry them: the same values)."""
    aval = jax.typeof(x)
    return aval.sharding.mesh.empty and aval.mat.empty


def _written_out_primitive(
    name: str, item_ranks: tuple[int, ...], item_shape: Callable[..., tuple], tangent_maps: Callable
) -> Callable[[Callable], Callable]:
    """Decorator: `written_out(*arrays)`, a function broadcasting over leading axes, as a JAX
    primitive (module docstring) that lowers to it.

    item_ranks: how many trailing axes each argument's item has (a vector 1, a matrix 2).
    item_shape(*argument_items) -> the output item's shape; raises ValueError where they do not fit.
    tangent_maps(*primals) -> one linear function per argument, taking that argument's tangent to
    the output's (its derivative at the primals), written so that reverse mode transposes it
    without slices (`_times`). Arguments with no tangent are skipped. The decorated function
    promotes its arguments to one dtype.
    """

    def decorate(written_out: Callable) -> Callable:
        primitive = Primitive(name)
        WRITTEN_OUT[name] = written_out
        mlir.register_lowering(primitive, mlir.lower_fun(written_out, multiple_results=False))

        def abstract(*avals):
            leads = [a.shape[: a.ndim - r] for a, r in zip(avals, item_ranks, strict=True)]
            items = [a.shape[a.ndim - r :] for a, r in zip(avals, item_ranks, strict=True)]
            try:
                leading = np.broadcast_shapes(*leads)
            except ValueError as error:
                raise ValueError(f"{name}: leading axes {leads} do not broadcast") from error
            if len({a.dtype for a in avals}) != 1:
                raise TypeError(f"{name}: arguments of dtypes {[str(a.dtype) for a in avals]}")
            try:
                out_item = item_shape(*items)
            except ValueError as error:
                raise ValueError(f"{name}: {error}") from None
            return ShapedArray(tuple(leading) + out_item, avals[0].dtype, weak_type=all(a.weak_type for a in avals))

        primitive.def_abstract_eval(abstract)

        def eager(*arrays):  # outside jit: the same checks of the arguments, then the components
            abstract(*(ShapedArray(np.shape(x), x.dtype) for x in arrays))
            return written_out(*arrays)

        primitive.def_impl(eager)

        def derivative(primals, tangents):
            out = primitive.bind(*primals)
            maps = tangent_maps(*primals)
            parts = [apply(t) for apply, t in zip(maps, tangents, strict=True) if type(t) is not ad.Zero]
            if not parts:
                return out, ad.Zero.from_primal_value(out)
            return out, jnp.broadcast_to(sum(parts[1:], parts[0]), out.shape)

        ad.primitive_jvps[primitive] = derivative

        def batched(args, dims):
            # The batch axis moves to the front of every mapped argument (dims: None where not
            # mapped), followed by unit axes up to the most leading axes of any argument, so that
            # the unmapped arguments broadcast against it.
            size = next(x.shape[d] for x, d in zip(args, dims, strict=True) if d is not None)
            leading = max(x.ndim - (d is not None) - r for x, d, r in zip(args, dims, item_ranks, strict=True))
            moved = []
            for x, d, r in zip(args, dims, item_ranks, strict=True):
                if d is not None:
                    x = jnp.moveaxis(x, d, 0)
                    shape = (size,) + (1,) * (leading - (x.ndim - 1 - r)) + x.shape[1:]
                    x = x if x.shape == shape else jnp.reshape(x, shape)
                moved.append(x)
            return primitive.bind(*moved), 0

        batching.primitive_batchers[primitive] = batched

        def bind(*arrays: jnp.ndarray) -> jnp.ndarray:
            dtype = jnp.result_type(*arrays)
            arrays = [jnp.asarray(a, dtype) for a in arrays]
            if not all(_unsharded(a) for a in arrays):
                return written_out(*arrays)
            return primitive.bind(*arrays)

        return functools.update_wrapper(bind, written_out)

    return decorate


def _items(size: int, out: tuple[int, ...] | None = None) -> Callable[..., tuple]:
    """item_shape for products of vectors of `size` components: the output item `out` (default:
    a vector of `size`)."""

    def shape(*items):
        if any(item != (size,) for item in items):
            raise ValueError(f"takes items of shape ({size},), got {tuple(items)}")
        return (size,) if out is None else out

    return shape


def _dot_tangents(a, b):
    return (lambda t: jnp.sum(t * b, axis=-1)), (lambda t: jnp.sum(a * t, axis=-1))


@_written_out_primitive("dbdjax_dot", (1, 1), _items(3, ()), _dot_tangents)
def dot(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Dot product over the last axis, (..., 3) x (..., 3) -> (...), written out so it fuses."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _cross_tangents(a, b):
    """a x b = -[b]x a = [a]x b."""
    return (lambda t: -_times(skew(b), t)), (lambda t: _times(skew(a), t))


@_written_out_primitive("dbdjax_cross", (1, 1), _items(3), _cross_tangents)
def cross(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Cross product over the last axis, written out so it fuses well on every backend."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


def skew(v: jnp.ndarray) -> jnp.ndarray:
    """Cross-product matrix [v]x (DBD eq. 9): skew(v) @ u == cross(v, u). (..., 3) -> (..., 3, 3)."""
    zero = jnp.zeros_like(v[..., 0])
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return jnp.stack(
        [
            jnp.stack([zero, -z, y], axis=-1),
            jnp.stack([z, zero, -x], axis=-1),
            jnp.stack([-y, x, zero], axis=-1),
        ],
        axis=-2,
    )


def safe_sqrt(x: jnp.ndarray) -> jnp.ndarray:
    """sqrt(x) for x >= 0 whose gradient at exactly zero is 0 instead of infinity."""
    is_zero = x <= _TINY_SQUARED
    return jnp.where(is_zero, 0.0, jnp.sqrt(jnp.where(is_zero, 1.0, x)))


def safe_norm(v: jnp.ndarray, axis: int = -1, keepdims: bool = False) -> jnp.ndarray:
    """Euclidean norm whose gradient at exactly zero is 0 instead of NaN."""
    squared = jnp.sum(v * v, axis=axis, keepdims=keepdims)
    is_zero = squared <= _TINY_SQUARED
    safe_squared = jnp.where(is_zero, 1.0, squared)
    return jnp.where(is_zero, 0.0, jnp.sqrt(safe_squared))


def safe_normalize(v: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(unit vector, norm) of v (..., 3). A zero vector gives the zero vector and norm 0.

    The zero direction is what every caller wants: a correction along an undefined direction is
    no correction, and its gradient is 0 rather than NaN.
    """
    squared = dot(v, v)
    is_zero = squared <= _TINY_SQUARED
    safe_squared = jnp.where(is_zero, 1.0, squared)
    norm = jnp.sqrt(safe_squared)
    unit = jnp.where(is_zero[..., None], 0.0, v / norm[..., None])
    return unit, jnp.where(is_zero, 0.0, norm)


def clamp_norm(v: jnp.ndarray, bound) -> jnp.ndarray:
    """v (3,) scaled back onto |v| <= bound () (bound = inf: v unchanged), with a finite gradient:
    a drive's torque bound (DBD (114)), a velocity block's impulse bound, a friction disc."""
    direction, size = safe_normalize(v)
    limited = jnp.isfinite(bound)  # an unlimited bound is stored as inf: keep it out of the products
    finite_bound = jnp.where(limited, bound, 0.0)
    return jnp.where(limited & (size > finite_bound), finite_bound * direction, v)


def any_perpendicular(u: jnp.ndarray) -> jnp.ndarray:
    """A unit vector perpendicular to unit u (..., 3): u x e_k for the basis vector least aligned
    with u (chosen by comparisons, first on ties, so the choice is deterministic)."""
    size = jnp.abs(u)
    x_least = (size[..., 0] <= size[..., 1]) & (size[..., 0] <= size[..., 2])
    y_least = ~x_least & (size[..., 1] <= size[..., 2])
    basis = jnp.stack([x_least, y_least, ~x_least & ~y_least], axis=-1).astype(u.dtype)
    return safe_normalize(cross(u, basis))[0]


def safe_asin(x: jnp.ndarray) -> jnp.ndarray:
    """arcsin clipped to [-1, 1] whose gradient at |x| = 1 is finite (it is the limit slope 0)."""
    at_edge = jnp.abs(x) >= 1.0
    safe_x = jnp.where(at_edge, 0.0, x)
    return jnp.where(at_edge, jnp.sign(x) * (jnp.pi / 2), jnp.arcsin(safe_x))


def safe_atan2(y: jnp.ndarray, x: jnp.ndarray) -> jnp.ndarray:
    """arctan2 whose gradient at (0, 0) is 0 instead of NaN; the value there is 0."""
    both_zero = (y * y + x * x) <= _TINY_SQUARED
    safe_x = jnp.where(both_zero, 1.0, x)
    return jnp.where(both_zero, 0.0, jnp.arctan2(y, safe_x))


def wrap_angle(angle: jnp.ndarray) -> jnp.ndarray:
    """angle (rad) wrapped to [-pi, pi], with gradient 1 (whole turns subtracted: no sine, cosine or
    arctangent, which the solver's sweeps would evaluate in every limit and drive row)."""
    return angle - (2.0 * jnp.pi) * jnp.round(angle / (2.0 * jnp.pi))


def diagonal(matrix: jnp.ndarray) -> jnp.ndarray:
    """The diagonals (..., n) of square matrices (..., n, n), as a strided slice of each matrix's
    entries: `jnp.diagonal` gathers, and reverse mode turns a gather into a scatter (a loop of
    kernels on CPU: `dbdjax.indexing`)."""
    n = matrix.shape[-1]
    return matrix.reshape(matrix.shape[:-2] + (n * n,))[..., :: n + 1]


def quat_identity(shape: tuple[int, ...] = ()) -> jnp.ndarray:
    """Identity quaternions of the given leading shape, (*shape, 4)."""
    return jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0, 0.0]), shape + (4,))


def _product_tangents(p, q):
    """p * q = R(q) p = L(p) q: the 4 x 4 matrices of the Hamilton product by q on the right and by
    p on the left, as the derivatives along p and along q."""
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = lambda *r: jnp.stack([jnp.stack(row, axis=-1) for row in r], axis=-2)  # noqa: E731
    right = rows([qw, -qx, -qy, -qz], [qx, qw, qz, -qy], [qy, -qz, qw, qx], [qz, qy, -qx, qw])
    left = rows([pw, -px, -py, -pz], [px, pw, -pz, py], [py, pz, pw, -px], [pz, -py, px, pw])
    return (lambda t: _times(right, t)), (lambda t: _times(left, t))


@_written_out_primitive("dbdjax_quat_multiply", (1, 1), _items(4), _product_tangents)
def quat_multiply(p: jnp.ndarray, q: jnp.ndarray) -> jnp.ndarray:
    """Hamilton product p * q (rotate by q, then by p)."""
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_conjugate(q: jnp.ndarray) -> jnp.ndarray:
    """Conjugate, the inverse of a unit quaternion."""
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def _normalisation_tangent(q):
    """d(q / |q|) = (dq - n (n . dq)) / |q| with n = q / |q| (0 at the zero quaternion)."""
    unit = quat_normalize(q)
    squared = jnp.sum(q * q, axis=-1, keepdims=True)
    is_zero = squared <= _TINY_SQUARED
    norm = jnp.sqrt(jnp.where(is_zero, 1.0, squared))
    return (lambda dq: jnp.where(is_zero, 0.0, (dq - unit * jnp.sum(unit * dq, axis=-1, keepdims=True)) / norm),)


@_written_out_primitive("dbdjax_quat_normalize", (1,), _items(4), _normalisation_tangent)
def quat_normalize(q: jnp.ndarray) -> jnp.ndarray:
    """Unit quaternion; a zero quaternion becomes the identity."""
    # Summed component by component, not by a reduction: a reduce ends an XLA fusion on CPU, and
    # the solver renormalises two quaternions in every row it projects.
    w, x, y, z = _components(q)
    squared = w * w + x * x + y * y + z * z
    is_zero = squared <= _TINY_SQUARED
    norm = jnp.sqrt(jnp.where(is_zero, 1.0, squared))
    return jnp.stack(
        [jnp.where(is_zero, 1.0, w / norm)] + [jnp.where(is_zero, 0.0, c / norm) for c in (x, y, z)], axis=-1
    )


def _rotation_tangents(q, v):
    """Derivatives of q v q* = v + w t + u x t (t = 2 u x v, q = (w, u)): along q the (..., 3, 4)
    matrix [t | -2 w [v]x - [t]x - 2 [u]x [v]x], along v the rotation I + 2 w [u]x + 2 [u]x^2."""
    w, u = q[..., :1, None], q[..., 1:]
    skew_u = skew(u)

    def along_q(tangent):
        t, skew_v = 2.0 * cross(u, v), skew(v)
        along_u = -2.0 * w * skew_v - skew(t) - 2.0 * matmul(skew_u, skew_v)
        return _times(jnp.concatenate([t[..., None], jnp.broadcast_to(along_u, t.shape + (3,))], axis=-1), tangent)

    def along_v(tangent):
        return _times(jnp.eye(3, dtype=q.dtype) + 2.0 * w * skew_u + 2.0 * matmul(skew_u, skew_u), tangent)

    return along_q, along_v


def _rotation_items(q_item, v_item):
    if q_item != (4,) or v_item != (3,):
        raise ValueError(f"takes (..., 4) and (..., 3), got items {q_item} and {v_item}")
    return (3,)


@_written_out_primitive("dbdjax_quat_rotate", (1, 1), _rotation_items, _rotation_tangents)
def quat_rotate(q: jnp.ndarray, v: jnp.ndarray) -> jnp.ndarray:
    """Rotate vector v (..., 3) by unit quaternion q (..., 4): v' = q v q*."""
    w, ux, uy, uz = _components(q)
    vx, vy, vz = _components(v)
    tx, ty, tz = 2.0 * (uy * vz - uz * vy), 2.0 * (uz * vx - ux * vz), 2.0 * (ux * vy - uy * vx)  # t = 2 u x v
    return jnp.stack(
        [vx + w * tx + (uy * tz - uz * ty), vy + w * ty + (uz * tx - ux * tz), vz + w * tz + (ux * ty - uy * tx)],
        axis=-1,
    )


def quat_rotate_inverse(q: jnp.ndarray, v: jnp.ndarray) -> jnp.ndarray:
    """Rotate v by the inverse of unit quaternion q: v' = q* v q."""
    return quat_rotate(quat_conjugate(q), v)


def quat_to_matrix(q: jnp.ndarray) -> jnp.ndarray:
    """Rotation matrix (..., 3, 3) of unit quaternion q; columns are the rotated basis vectors."""
    eye = jnp.eye(3, dtype=q.dtype)
    columns = quat_rotate(q[..., None, :], eye)  # (..., 3 basis vectors, 3)
    return jnp.swapaxes(columns, -1, -2)


def quat_exp(rotation_vector: jnp.ndarray) -> jnp.ndarray:
    """Quaternion of a rotation vector theta * n (DBD: q(theta) = exp(i theta / 2)).

    Uses sin(|v|/2)/|v| with its Taylor series near zero, so value and gradient are exact at 0.
    """
    angle_squared = dot(rotation_vector, rotation_vector)
    small = angle_squared < 1e-8
    safe_squared = jnp.where(small, 1.0, angle_squared)
    angle = jnp.sqrt(safe_squared)
    half_sinc = jnp.where(small, 0.5 - angle_squared / 48.0, jnp.sin(0.5 * angle) / angle)
    half_cos = jnp.where(small, 1.0 - angle_squared / 8.0, jnp.cos(0.5 * angle))
    return jnp.concatenate([half_cos[..., None], half_sinc[..., None] * rotation_vector], axis=-1)


def shortest_rotation(rotation_vector: jnp.ndarray) -> jnp.ndarray:
    """The rotation vector of length <= pi that turns as exp(i rotation_vector / 2) does.

    theta n and (theta - 2 pi k) n are the same rotation; this picks the k that makes the angle
    smallest. Below pi the vector is returned as it is (bit for bit, with its gradient).
    """
    angle_squared = dot(rotation_vector, rotation_vector)
    wraps = angle_squared > jnp.pi**2
    angle = jnp.sqrt(jnp.where(wraps, angle_squared, 1.0))
    turns = jnp.round(angle / (2.0 * jnp.pi))
    scale = jnp.where(wraps, 1.0 - 2.0 * jnp.pi * turns / angle, 1.0)
    return scale[..., None] * rotation_vector


def quat_log(q: jnp.ndarray) -> jnp.ndarray:
    """Rotation vector theta * n of unit quaternion q, with theta in [0, pi] (shortest arc)."""
    q = jnp.where(q[..., :1] < 0.0, -q, q)  # q and -q are the same rotation
    vector = q[..., 1:]
    sin_half_squared = dot(vector, vector)
    small = sin_half_squared < 1e-8
    sin_half = jnp.sqrt(jnp.where(small, 1.0, sin_half_squared))
    half_angle = jnp.arctan2(sin_half, q[..., 0])
    # angle / sin(angle/2) -> 2 (1 + s^2/6) as s = sin(angle/2) -> 0 with cos(angle/2) ~ 1
    scale = jnp.where(small, 2.0 + sin_half_squared / 3.0, 2.0 * half_angle / sin_half)
    return scale[..., None] * vector


def quat_twist_angle(q: jnp.ndarray, axis: jnp.ndarray) -> jnp.ndarray:
    """Angle in [-pi, pi] of the twist of rotation q about unit `axis` (swing-twist split).

    The twist is the part of q that rotates about `axis`; this is the hinge angle of SI
    (104)-(106), extended to rotations whose axis is not exactly `axis`.
    """
    q = jnp.where(q[..., :1] < 0.0, -q, q)
    along = dot(q[..., 1:], axis)
    return 2.0 * safe_atan2(along, q[..., 0])


def angle_between(a: jnp.ndarray, b: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(angle in [0, pi], unit axis that turns a toward b) for unit vectors a, b (..., 3).

    DBD (73) writes the angle as asin|a x b|; atan2(|a x b|, a . b) is the same below pi/2 and
    stays right beyond it. At a == b the axis is the zero vector and the gradient finite.
    """
    axis, sine = safe_normalize(cross(a, b))
    return safe_atan2(sine, dot(a, b)), axis


def _matvec_items(matrix_item, vector_item):
    if matrix_item != (3, 3) or vector_item != (3,):
        raise ValueError(f"takes (..., 3, 3) and (..., 3), got items {matrix_item} and {vector_item}")
    return (3,)


def _matvec_tangents(matrix, vector):
    return (lambda t: jnp.sum(t * vector[..., None, :], axis=-1)), (lambda t: _times(matrix, t))


@_written_out_primitive("dbdjax_matvec", (2, 1), _matvec_items, _matvec_tangents)
def matvec(matrix: jnp.ndarray, vector: jnp.ndarray) -> jnp.ndarray:
    """matrix (..., 3, 3) times vector (..., 3), written out (no reduction op) so it fuses."""
    x, y, z = _components(vector)
    return jnp.stack([matrix[..., i, 0] * x + matrix[..., i, 1] * y + matrix[..., i, 2] * z for i in range(3)], axis=-1)


def gauss_jordan_inverse(matrix: jnp.ndarray) -> jnp.ndarray:
    """Inverse of (..., n, n) matrices whose symmetric part is positive definite (a body's block
    with a velocity-dependent inertia, a sliding contact's tilted row: positive definite up to a
    skew part), by Gauss-Jordan elimination on [A | 1] without pivoting, kept in one n x n array:
    n row steps, each one elementwise op over the batch between two updates in place.

    Without pivoting, stable for such matrices: its float32 error stays within the matrix's
    condition number times the unit roundoff, as pivoted LU's does. The inverse by 3x3 Schur
    complements that `solvers/tree.py` used before was not: the block of a resting ant's upper
    leg, its lower leg pinned by its foot (eigenvalues from 1.2e-4, its spin about its own axis,
    to 68, along it), lost its smallest eigenvalue 31 times over in the Schur complement of its
    translation, the inverse came out off by 2,900 times its largest entry, and the tree's direct
    solve spun the leg 0.47 rad (this one: off by 5e-6, `tests/test_math.py`). An L U inverse
    written out entry by entry was as accurate and made the tree's step 1.6x slower on CPU; this
    one, 1.02-1.19x (`benchmarks/results/profile_step_paired_session61_tree_inverse.json`). In place
    rather than on the n x 2n [A | 1] it made the tree's step 1.07-1.25x faster (session 65,
    `..._session65_in_place_inverse.json`); written with selects instead of the updates in place,
    about 2x slower (nothing then keeps XLA from fusing the steps together; the HLO not looked at).
    """
    n = matrix.shape[-1]
    # In place: step k turns column k of [A | 1] into e_k and column k of its right half from e_k
    # into the inverse's column k, so one n x n array holds both halves' live columns (the same
    # operations on each entry as on [A | 1], so the same result to the bit). The row and column
    # writes are updates in place, which also keep XLA from fusing one step into the next.
    inverse = matrix
    for k in range(n):
        pivot = inverse[..., k, k]
        pivot_row = (inverse[..., k, :] / pivot[..., None]).at[..., k].set(1.0 / pivot)
        column = inverse[..., :, k, None]
        inverse = inverse.at[..., :, k].set(0.0) - column * pivot_row[..., None, :]
        inverse = inverse.at[..., k, :].set(pivot_row)
    return inverse


def adjugate3(matrix: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(adjugate (..., 3, 3), determinant (...)) of (..., 3, 3) matrices: the inverse is their
    quotient (`inverse3`). Columns are cross products of rows, the determinant the first row's
    product with the first column, so a caller that tests the determinant before dividing
    (`rows.definite_inverse`) computes them once."""
    c0 = cross(matrix[..., 1, :], matrix[..., 2, :])
    c1 = cross(matrix[..., 2, :], matrix[..., 0, :])
    c2 = cross(matrix[..., 0, :], matrix[..., 1, :])
    return jnp.stack([c0, c1, c2], axis=-1), dot(matrix[..., 0, :], c0)


def inverse3(matrix: jnp.ndarray) -> jnp.ndarray:
    """Inverse of (..., 3, 3) matrices by the adjugate: elementwise, so it fuses and batches
    (a batched LAPACK call per body costs far more on CPU than the 3x3 arithmetic)."""
    adjugate, determinant = adjugate3(matrix)
    return adjugate / determinant[..., None, None]


def euler_angles(
    axes_a: jnp.ndarray, axes_b: jnp.ndarray, universal: jnp.ndarray | bool
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Angles of two or three successive hinges through one point, as MuJoCo composes the hinges
    of one body, and the directions in which each angle grows.

    The relative rotation is X = R(m1, t1) R(m2, t2) R(m3, t3) (b's orientation = a's X rest),
    each hinge axis in the frame the previous rotations left: m1 is fixed in a, m3 in b, m2 in
    between. axes_a: (..., 3, 3) rows m1, m2, m3 as carried by body a (world), axes_b the same
    three as carried by body b; all three mutually perpendicular, handedness s = m1 . (m2 x m3).
    With M_ij = axes_a[i] . axes_b[j] = m_i . X m_j, M = Rx(s t1) Ry(s t2) Rz(s t3) in the
    (m1, m2, m3) basis (conjugating by a reflection reverses the sense of rotation), so
      t1 = s atan2(-M12, M22), t2 = s atan2(M02, |(M12, M22)|), t3 = s atan2(-M01, M00),
    t1, t3 in (-pi, pi], t2 in [-pi/2, pi/2]: a gimbal, singular at |t2| = pi/2 where m1 and m3
    align. universal: (...) bool (a Python bool traces one kind only); two hinges (m3 = m1 x m2,
    t3 = 0 held by the joint's lock row): t1 = atan2(M21, M11) (m2 carried by b, seen about m1),
    t2 = atan2(M02, M00) (m1 carried by a, seen about m2 in b), both in (-pi, pi], no singularity.

    Returns (angles (..., 3) rad, directions (..., 3, 3)): row k is g_k = d t_k / d delta, delta a
    small world rotation of b relative to a. They are the dual basis of the current hinge axes
    (m1 on a, e2, m3 on b): with c = m3_b x m1_a (|c| = cos t2), g1 = (c x m3_b) / |c|^2,
    g2 = e2 = s c / |c|, g3 = (m1_a x c) / |c|^2. A torque tau g_k on b (and -tau g_k on a) is the
    generalised force tau on hinge k alone. For the universal joint g1 = m1_a, g2 = m2_b, g3 = 0
    (exact while the lock row holds m1_a . m2_b = 0). |c|^2 is floored at 1e-6 (cos t2 >= 1e-3)
    so the directions stay finite at the gimbal singularity.
    """
    products = dot(axes_a[..., :, None, :], axes_b[..., None, :, :])  # (..., 3, 3): M_ij
    m = [[products[..., i, j] for j in range(3)] for i in range(3)]
    first = axes_a[..., 0, :]
    if universal is not True:
        s = dot(first, cross(axes_a[..., 1, :], axes_a[..., 2, :]))
        middle_cos = safe_sqrt(m[1][2] ** 2 + m[2][2] ** 2)
        gimbal = jnp.stack(
            [s * safe_atan2(-m[1][2], m[2][2]), s * safe_atan2(m[0][2], middle_cos), s * safe_atan2(-m[0][1], m[0][0])],
            axis=-1,
        )
        last = axes_b[..., 2, :]
        common = cross(last, first)
        middle, size = safe_normalize(common)
        squared = jnp.maximum(size * size, 1e-6)[..., None]
        gimbal_directions = jnp.stack(
            [cross(common, last) / squared, s[..., None] * middle, cross(first, common) / squared], axis=-2
        )
        if universal is False:
            return gimbal, gimbal_directions
    two = jnp.stack([safe_atan2(m[2][1], m[1][1]), safe_atan2(m[0][2], m[0][0]), jnp.zeros_like(m[0][0])], axis=-1)
    two_directions = jnp.stack([first, axes_b[..., 1, :], jnp.zeros_like(first)], axis=-2)
    if universal is True:
        return two, two_directions
    universal = jnp.asarray(universal)
    angles = jnp.where(universal[..., None], two, gimbal)
    directions = jnp.where(universal[..., None, None], two_directions, gimbal_directions)
    return angles, directions
