"""The colouring of the constraint graph (colouring.py, builder.colour_classes): every colour a
valid Gauss-Seidel group (no body moved twice) holding one kind of joint, and the colours evened
out without changing any body's order of projections."""

from pathlib import Path

import jax
import numpy as np
import pytest
import scenes

import dbdjax as dbd
from dbdjax import colouring, ragdoll
from dbdjax.constraints import joints as joint_rows

ASSETS = Path(__file__).parent / "assets"


def _ragdoll():
    builder, _ = ragdoll.build()
    return builder.finalize()


MODELS = {
    "mixed tree": scenes.mixed_tree,
    "humanoid": lambda: dbd.load_mjcf(ASSETS / "humanoid.xml"),
    "ragdoll": _ragdoll,
}


@pytest.mark.parametrize("name", sorted(MODELS))
def test_every_colour_moves_each_body_once_and_holds_one_kind_of_joint(name):
    model = MODELS[name]()
    structure = model.structure
    tables = structure.family_bodies()
    kind_of = np.full(structure.num_joints, -1)
    for k, (members, _) in enumerate(joint_rows.variants(structure)):
        kind_of[members] = k
    coloured = [np.zeros(len(table), int) for table in tables]
    kinds_per_colour = []
    for colour in structure.colours:
        moved = np.concatenate([tables[f][nodes.array].reshape(-1) for f, nodes in enumerate(colour.nodes)])
        moved = moved[moved < structure.num_bodies]
        assert len(moved) == len(set(moved.tolist())), "a body moved twice in one colour"
        families = [f for f, nodes in enumerate(colour.nodes) if len(nodes.array)]
        joints_here = colour.nodes[0].array
        if len(joints_here):
            assert families == [0], "joints share a colour with another family"
            kinds_per_colour.append(set(kind_of[joints_here].tolist()))
        for f, nodes in enumerate(colour.nodes):
            coloured[f][nodes.array] += 1
    assert all(len(kinds) == 1 for kinds in kinds_per_colour), kinds_per_colour
    assert all(np.all(count == 1) for count in coloured), "every node is in exactly one colour"
    kinds = {next(iter(k)) for k in kinds_per_colour}
    assert len(kinds) == len(joint_rows.variants(structure)) > 1


def test_humanoid_runs_each_kind_of_joint_once_per_colour_it_needs():
    """Brax's humanoid: 5 hinges (no two on one body) fit one colour; its 3 universal joints all on
    the torso need 3, which its 2 gimbal hips (on the pelvis) share: 4 joint colours, where the
    kinds mixed needed 3 colours that each ran both kinds."""
    structure = dbd.load_mjcf(ASSETS / "humanoid.xml").structure
    sizes = [len(colour.nodes[0].array) for colour in structure.colours if len(colour.nodes[0].array)]
    assert sorted(sizes) == [1, 2, 2, 5]


def test_nodes_of_different_classes_never_share_a_colour_and_lower_classes_come_first():
    # A chain of 6 bodies, 5 links; links 0, 2, 4 in class 1 and 1, 3 in class 0; a second family
    # of one node (class 2) on bodies 0 and 5.
    links = np.array([[k, k + 1] for k in range(5)])
    other = np.array([[0, 5]])
    colours = colouring.colour_groups([links, other], 6, classes=[np.array([1, 0, 1, 0, 1]), 2])
    members = [([int(m) for m in c.nodes[0].array], [int(m) for m in c.nodes[1].array]) for c in colours]
    # Class 0 (links 1 and 3 share no body): one colour; class 1 (0, 2, 4): one; class 2: one.
    assert members == [([1, 3], []), ([0, 2, 4], []), ([], [0])]
    with pytest.raises(ValueError, match="2 classes for 1 families"):
        colouring.colour_groups([links], 6, classes=[0, 1])
    with pytest.raises(ValueError, match="family 0 has 5 nodes"):
        colouring.colour_groups([links], 6, classes=[np.array([0, 1])])


def _order_on_each_body(bodies, colours, num_bodies):
    """Per body, the constraints that move it in the order a sweep projects them."""
    return [sorted((colours[k], k) for k, moved in enumerate(bodies) if b in moved) for b in range(num_bodies)]


def _check_even_colouring(bodies, num_bodies):
    greedy = colouring.greedy_colouring(bodies, num_bodies)
    even = colouring.even_colouring(bodies, num_bodies, greedy)
    assert max(even) == max(greedy), "the number of colours changed"
    assert np.bincount(even).max() <= np.bincount(greedy).max()
    order = [[k for _, k in on_body] for on_body in _order_on_each_body(bodies, even, num_bodies)]
    assert order == [[k for _, k in on_body] for on_body in _order_on_each_body(bodies, greedy, num_bodies)]
    for on_body in _order_on_each_body(bodies, even, num_bodies):
        colours_here = [c for c, _ in on_body]
        assert len(colours_here) == len(set(colours_here)), "a body moved twice in one colour"
    return greedy, even


def test_even_colouring_evens_the_ants_colours_and_keeps_each_bodys_order():
    # Brax's ant: hip k on the torso (0) and thigh 2k + 1, ankle k on thigh and shin 2k + 2.
    bodies = dbd.load_mjcf(ASSETS / "ant.xml").structure.family_bodies()[0].tolist()
    assert bodies == [[0, 1], [1, 2], [0, 3], [3, 4], [0, 5], [5, 6], [0, 7], [7, 8]]
    greedy, even = _check_even_colouring(bodies, 9)
    assert np.bincount(greedy).tolist() == [4, 2, 1, 1]
    assert np.bincount(even).tolist() == [2, 2, 2, 2]


def test_even_colouring_keeps_each_bodys_order_on_random_graphs():
    rng = np.random.default_rng(0)
    evened = 0
    for _ in range(200):
        num_bodies = int(rng.integers(2, 12))
        count = int(rng.integers(1, 20))
        bodies = [rng.choice(num_bodies + 1, size=int(rng.integers(1, 4)), replace=False).tolist()
                  for _ in range(count)]  # fmt: skip
        greedy, even = _check_even_colouring(bodies, num_bodies)
        evened += even != greedy
    assert evened > 20  # the random graphs do exercise the evening


@pytest.mark.slow
def test_the_ant_steps_alike_with_even_and_greedy_colours(monkeypatch):
    """Evening the colours keeps every body's projection order, so the sweep computes the same."""
    control = 0.4 * np.sin(np.arange(20)[:, None] + np.arange(8)[None, :])

    def trajectory():
        model = dbd.load_mjcf(ASSETS / "ant.xml")

        def body(state, u):
            state = dbd.step(model, state, u)
            return state, state.pos

        return model, np.asarray(jax.jit(lambda s: jax.lax.scan(body, s, control)[1])(dbd.init(model)))

    even_model, even = trajectory()
    monkeypatch.setattr(colouring, "even_colouring", lambda bodies, num_bodies, colours: list(colours))
    greedy_model, greedy = trajectory()
    sizes = [[len(c.nodes[0].array) for c in m.structure.colours[:4]] for m in (even_model, greedy_model)]
    assert sizes == [[2, 2, 2, 2], [4, 2, 1, 1]]
    np.testing.assert_allclose(even, greedy, rtol=0, atol=1e-6)
    assert np.ptp(even[:, 0, 2]) > 0.01  # the torso did move


def test_colour_groups_even_a_class_of_one_family_and_leave_a_class_of_several_as_greedy():
    """Evening across families would change which families each colour holds (the solver's runs)."""
    legs = np.array([[0, 1], [1, 2], [0, 3], [3, 4], [0, 5], [5, 6], [0, 7], [7, 8]])  # the ant's joints
    one_family = colouring.colour_groups([legs], 9)
    assert [len(c.nodes[0].array) for c in one_family] == [2, 2, 2, 2]
    hips, ankles = legs[0::2], legs[1::2]
    two_families = colouring.colour_groups([hips, ankles], 9)
    # Greedy, hips first: each hip a colour of its own on the torso; ankle 1 after hip 1, the
    # others in the first colour.
    assert [[len(nodes.array) for nodes in c.nodes] for c in two_families] == [[1, 3], [1, 1], [1, 0], [1, 0]]
