"""The public step: `init`, `step`, `rollout`, `is_finite`. Pure functions of (model, state).

step(model, state, control):
  scan over substeps of h = dt / substeps:
    solver="dbd":
    X*, V*  = integrator.predict(model, state, h)                  DBD (21)-(24)
    slots   = collision.detect(model, state, X*, h)                fixed shape, inactive masked
    dX, lam, r = solvers.dbd.solve(model, X*, control, slots, h, X)  Algorithm 1, (45)-(52), (84)-(93)
    state   = integrator.apply(X*, dX, h)                          (36)-(39)
    state   = solvers.dbd.rotor_momentum(model, state, r, h)       velocity pass: rotors' unpaid spin
    state   = solvers.dbd.restitution(model, state, slots, lam, h) velocity pass (SI 2.1.4)
    solver="impulse":
    X*, V*  = solvers.impulse.predict(model, state, h)             SI (12): V* = V + h M^-1 F_ext
    slots   = collision.detect(model, state, X*, h)                the same slots
    dV, lam = solvers.impulse.solve(model, state, V*, ...)         sequential impulses, warm-started,
                                                                   then the same rotor pass
    state   = solvers.impulse.integrate((X, V* + dV), lam, h)      SI (12): X' = X + h V'
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from dbdjax import collision, integrator, sharding
from dbdjax.model import Model, State
from dbdjax.solvers import dbd, impulse


def init(model: Model) -> State:
    """The state the model was built in (positions, orientations, velocities of `add_body`)."""
    bodies = model.bodies
    return _ready(
        model,
        State(pos=bodies.initial_pos, quat=bodies.initial_quat, vel=bodies.initial_vel, ang_vel=bodies.initial_ang_vel),
    )


def _ready(model: Model, state: State) -> State:
    """The impulse solver carries its impulses in the state: give a state without them zeros (a
    cold start), so that a step's output has the structure of its input (lax.scan, rollout)."""
    if model.options.solver == "impulse" and state.impulses is None:
        return dataclasses.replace(state, impulses=impulse.initial_impulses(model, state.pos.dtype))
    return state


def _check_control(model: Model, control) -> None:
    expected = model.num_controls
    if control is None:
        return
    shape = jnp.shape(control)
    if shape != (expected,):
        raise ValueError(f"control must have shape ({expected},) = (model.num_controls,), got {shape}")


def substep(model: Model, state: State, control: jnp.ndarray | None, h: float) -> State:
    """One substep of h seconds: predict, detect contacts, solve, apply, restitution (or, with
    the impulse solver, predict, detect contacts, solve velocities, integrate)."""
    if model.options.solver == "impulse":
        predicted = impulse.predict(model, state, h, control)
        slots = collision.detect(model, state, predicted, h)
        velocity, spin, impulses, _ = impulse.solve(model, state, predicted, control, slots, h)
        solved = impulse.solved_velocities(state, predicted, velocity, spin)
        return impulse.integrate(solved, impulses, h)
    predicted = integrator.predict(model, state, h, control)
    slots = collision.detect(model, state, predicted, h)
    displacement, rotation, normal_multipliers, rotor_excess = dbd.solve(model, predicted, control, slots, h,
                                                                         start=state)  # fmt: skip
    state = integrator.apply(predicted, displacement, rotation, h)
    state = dbd.rotor_momentum(model, state, rotor_excess, h)
    return dbd.restitution(model, state, slots, normal_multipliers, h)


def step(model: Model, state: State, control: jnp.ndarray | None = None) -> State:
    """Advance `state` by model.dt seconds.

    state: a `State` for one scene (vmap for batches). control: (model.num_controls,) or None.
    Pure: jit, vmap and grad go through it (w.r.t. state, control and model float leaves).
    """
    _check_control(model, control)
    state = _ready(model, state)
    options = model.options
    h = options.dt / options.substeps
    one_substep = lambda s: substep(model, s, control, h)  # noqa: E731
    if options.checkpoint:
        one_substep = jax.checkpoint(one_substep)
    if options.substeps == 1:
        return one_substep(state)
    state = sharding.varying_like(state, state, control)  # under shard_map: as varying as what comes back
    state, _ = jax.lax.scan(lambda s, _: (one_substep(s), None), state, None, length=options.substeps)
    return state


def rollout(
    model: Model, state: State, controls: jnp.ndarray | None = None, steps: int | None = None
) -> tuple[State, State]:
    """Run `step` over controls (T, num_controls), or `steps` times with no control.

    Returns (final state, trajectory): the trajectory is the State after each step, stacked on
    a leading axis of length T.
    """
    if controls is None:
        if steps is None:
            raise ValueError("rollout needs controls of shape (T, num_controls) or steps=T")
        controls = jnp.zeros((steps, model.num_controls))
    elif jnp.ndim(controls) != 2 or jnp.shape(controls)[1] != model.num_controls:
        raise ValueError(
            f"controls must have shape (T, {model.num_controls}) = (T, model.num_controls), got {jnp.shape(controls)}"
        )

    def one_step(s, control):
        s = step(model, s, control)
        return s, s

    state = _ready(model, state)
    return jax.lax.scan(one_step, sharding.varying_like(state, state, controls), controls)


def is_finite(state: State) -> jnp.ndarray:
    """True where every number of the state is finite (one bool per batch element)."""
    finite = [jnp.all(jnp.isfinite(x), axis=(-2, -1)) for x in jax.tree.leaves(state)]
    return jnp.logical_and.reduce(jnp.stack(finite), axis=0)
