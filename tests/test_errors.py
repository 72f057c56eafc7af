"""Bad input is refused at build time with a ValueError naming the item and the reason."""

import math

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
        (lambda b: b.finalize(dt=0.0), r"finalize: dt must be positive"),
        (lambda b: b.finalize(iterations=0), r"finalize: iterations must be a positive integer"),
        (lambda b: b.finalize(substeps=1.5), r"finalize: substeps must be a positive integer"),
        (lambda b: b.finalize(solver="magic"), r"finalize: unknown solver 'magic'"),
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
