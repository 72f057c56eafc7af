"""The colouring of the constraint graph (colouring.py, builder.colour_classes): every colour a
valid Gauss-Seidel group (no body moved twice) holding one kind of joint."""

from pathlib import Path

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
