"""Bad input is refused at build time with a ValueError naming the item and the reason."""

import math

import jax.numpy as jnp
import pytest

import dbdjax as dbd


def builder_with_two_bodies():
    b = dbd.ModelBuilder()
    b.add_body(pos=(0, 0, 1), name="upper")
    b.add_body(pos=(0, 0, 0), name="lower")
    return b


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda b: b.add_body(mass=0.0, name="ghost"), r"body 2 \('ghost'\): mass must be positive"),
        (lambda b: b.add_body(mass=-1.0), r"body 2: mass must be positive"),
        (lambda b: b.add_body(inertia=(0.1, -0.1, 0.1)), r"body 2: inertia must be positive definite"),
        (lambda b: b.add_body(inertia=(0.1, 0.1, 0.5)), r"body 2: inertia .* triangle inequality"),
        (lambda b: b.add_body(pos=(0, math.nan, 0)), r"body 2: pos contains NaN"),
        (lambda b: b.add_body(quat=(0, 0, 0, 0)), r"body 2: quat is the zero quaternion"),
        (lambda b: b.add_ball_joint(0, 7, anchor=(0, 0, 0)), r"ball joint 0: body_b = 7 is not a body index"),
        (lambda b: b.add_hinge_joint(1, 1, anchor=(0, 0, 0), axis=(0, 0, 1)), r"hinge joint 0: .*body 1 to itself"),
        (lambda b: b.add_ball_joint(dbd.WORLD, dbd.WORLD, anchor=(0, 0, 0)), r"ball joint 0: .*the world to itself"),
        (
            lambda b: b.add_hinge_joint(0, 1, anchor=(0, 0, 0), axis=(0, 1, 0), limits=(1.0, -1.0)),
            r"hinge joint 0: lower limit 1.0 is above upper limit -1.0",
        ),
        (
            lambda b: b.add_slider_joint(0, 1, anchor=(0, 0, 0), axis=(0, 1, 0), limits=(0.5, 0.1), name="rail"),
            r"slider joint 0 \('rail'\): lower limit 0.5 is above upper limit 0.1",
        ),
        (
            lambda b: b.add_hinge_joint(0, 1, anchor=(0, 0, 0), axis=(0, 0, 0)),
            r"hinge joint 0: axis is the zero vector",
        ),
        (
            lambda b: b.add_slider_joint(0, 1, anchor=(0, 0, 0), axis=(0, 0, 0)),
            r"slider joint 0: axis is the zero vector",
        ),
        (lambda b: b.add_fixed_joint(0, 1, anchor=(0, math.inf, 0)), r"fixed joint 0: anchor contains NaN or infinity"),
        (lambda b: b.add_ball_joint(0, 1, anchor=(0, 0, 0), cone_limit=math.nan), r"ball joint 0: cone_limit is NaN"),
        (lambda b: b.add_ball_joint(0, 1, anchor=(0, 0, 0), cone_limit=-0.1), r"ball joint 0: cone_limit must be in"),
        (lambda b: b.add_ball_joint(0, 1, anchor=(0, 0, 0), relaxation=2.5), r"ball joint 0: relaxation must be in"),
        (lambda b: b.add_drive(0, stiffness=1.0), r"add_drive: joint = 0 is not a joint index"),
        (
            lambda b: b.add_drive(b.add_fixed_joint(0, 1, (0, 0, 0)), 1.0),
            r"add_drive: fixed joint 0 .*hinge, ball, universal and gimbal",
        ),
        (lambda b: b.add_drive(b.add_ball_joint(0, 1, (0, 0, 0)), -5.0), r"add_drive on ball joint 0 .*stiffness must"),
        (
            lambda b: b.add_drive(b.add_ball_joint(0, 1, (0, 0, 0), name="hip"), 5.0, max_torque=0.0),
            r"add_drive on ball joint 0 \('hip'\): max_torque must be positive",
        ),
        (lambda b: b.add_motor(b.add_ball_joint(0, 1, (0, 0, 0)), 1.0), r"add_motor: ball joint 0 .*hinge and slider"),
        (
            lambda b: b.add_motor(b.add_hinge_joint(0, 1, (0, 0, 0), (0, 1, 0)), max_force=math.nan),
            r"add_motor on hinge joint 0 .*max_force is NaN",
        ),
        (lambda b: b.add_spring(0, 5, (0, 0, 0), (0, 0, 1), 1.0), r"spring 0: body_b = 5 is not a body index"),
        (lambda b: b.add_spring(0, 1, (0, 0, 0), (0, 0, 1), stiffness=-1.0), r"spring 0: stiffness must be >= 0"),
        (lambda b: b.add_distance(0, 0, (0, 0, 0), (0, 0, 1)), r"distance 0: .*body 0 to itself"),
        (lambda b: b.add_rope([0, dbd.WORLD]), r"rope 0: -1 is not a body index .*world cannot be a node"),
        (lambda b: b.add_rope([0, 1, 0]), r"rope 0: a body appears twice"),
        (lambda b: b.add_volume([0, 1]), r"volume 0: needs at least 4 bodies"),
        (lambda b: b.add_force([0], "not a function"), r"force 0: function must be callable"),
        (lambda b: b.add_force([0], lambda *a: a, params=math.nan, name="wind"), r"force 0 \('wind'\): params"),
        (lambda b: b.finalize(dt=0.0), r"finalize: dt must be positive"),
        (lambda b: b.finalize(iterations=0), r"finalize: iterations must be a positive integer"),
        (lambda b: b.finalize(substeps=1.5), r"finalize: substeps must be a positive integer"),
        (lambda b: b.finalize(solver="magic"), r"finalize: unknown solver 'magic'"),
        (lambda b: b.finalize(point_sweeps=-1), r"finalize: point_sweeps must be a non-negative integer, got -1"),
        (lambda b: b.finalize(point_sweeps=True), r"finalize: point_sweeps must be a non-negative integer"),
        (
            lambda b: b.finalize(solver="impulse", point_sweeps=2),
            r"finalize: point_sweeps are the DBD solver's; solver='impulse' sweeps its joints' points",
        ),
        (
            lambda b: (b.add_ik_target(1, (0, 0, 0)), b.finalize(solver="impulse")),
            r"finalize: IK target 0 \(on body 1\): the impulse solver has no IK target constraint",
        ),
    ],
)
def test_bad_input_raises_value_error_naming_the_item(call, message):
    with pytest.raises(ValueError, match=message):
        call(builder_with_two_bodies())


def test_empty_model_is_refused():
    with pytest.raises(ValueError, match="no bodies"):
        dbd.ModelBuilder().finalize()


def test_gravity_with_nan_is_refused():
    with pytest.raises(ValueError, match="gravity contains NaN"):
        dbd.ModelBuilder(gravity=(0, 0, math.nan))


def test_drive_added_twice_is_refused():
    b = builder_with_two_bodies()
    hinge = b.add_hinge_joint(0, 1, anchor=(0, 0, 0.5), axis=(0, 1, 0), name="knee")
    b.add_drive(hinge, stiffness=1.0)
    with pytest.raises(ValueError, match=r"hinge joint 0 \('knee'\) already has a drive"):
        b.add_drive(hinge, stiffness=2.0)


def test_coplanar_tetrahedron_needs_a_rest_volume():
    b = dbd.ModelBuilder()
    nodes = [b.add_body(pos=p) for p in ((0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0))]
    with pytest.raises(ValueError, match="volume 0: the four centres of mass are coplanar"):
        b.add_volume(nodes)


def test_control_of_the_wrong_shape_is_refused():
    b = builder_with_two_bodies()
    b.add_drive(b.add_ball_joint(0, 1, anchor=(0, 0, 0.5)), stiffness=1.0)
    model = b.finalize()
    with pytest.raises(ValueError, match=r"control must have shape \(3,\)"):
        dbd.step(model, dbd.init(model), jnp.zeros(2))
    with pytest.raises(ValueError, match=r"controls must have shape \(T, 3\)"):
        dbd.rollout(model, dbd.init(model), jnp.zeros((4, 1)))
