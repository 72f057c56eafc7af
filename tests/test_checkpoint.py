"""dbdjax.training.checkpoint: pytrees round-trip through .npz files, and pickles are refused."""

import dataclasses
import pathlib
import pickle

import jax.numpy as jnp
import numpy as np
import optax
import pytest

import dbdjax as dbd
from dbdjax.training import checkpoint


def example_tree():
    state = dbd.State(
        pos=jnp.arange(6.0).reshape(2, 3),
        quat=jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (2, 1)),
        vel=jnp.full((2, 3), -0.5),
        ang_vel=jnp.zeros((2, 3)),
    )
    return {
        "state": state,
        "controls": np.linspace(-1.0, 1.0, 12).reshape(4, 3),
        "history": [np.float64(3.5), (np.arange(3, dtype=np.int32), None)],
        "flag": np.array(True),
        "half": jnp.array([1.5, -2.0], dtype=jnp.bfloat16),
    }


def assert_same_leaves(a, b):
    import jax

    leaves_a, leaves_b = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(leaves_a) == len(leaves_b)
    for x, y in zip(leaves_a, leaves_b, strict=True):
        assert np.asarray(x).dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_round_trip_with_a_template_restores_the_pytree_and_metadata(tmp_path):
    tree = example_tree()
    metadata = {"task": "ik_chain", "steps": 200, "losses": [1.0, 0.5]}
    checkpoint.save(tmp_path / "ckpt.npz", tree, metadata)
    loaded, loaded_metadata = checkpoint.load(tmp_path / "ckpt.npz", like=tree)
    assert isinstance(loaded["state"], dbd.State)
    assert isinstance(loaded["history"][1], tuple) and loaded["history"][1][1] is None
    assert_same_leaves(loaded, tree)
    assert loaded_metadata == metadata


def test_round_trip_without_a_template_rebuilds_containers_and_turns_nodes_into_dicts(tmp_path):
    tree = example_tree()
    checkpoint.save(tmp_path / "ckpt.npz", tree)
    loaded, metadata = checkpoint.load(tmp_path / "ckpt.npz")
    assert metadata == {}
    assert isinstance(loaded["history"], list) and isinstance(loaded["history"][1], tuple)
    assert loaded["history"][1][1] is None
    assert set(loaded["state"]) == {field.name for field in dataclasses.fields(dbd.State)}  # a node -> a dict
    np.testing.assert_array_equal(loaded["state"]["vel"], np.asarray(tree["state"].vel))
    np.testing.assert_array_equal(loaded["controls"], tree["controls"])
    assert loaded["half"].dtype == jnp.bfloat16


def test_an_optax_state_round_trips_with_a_template(tmp_path):
    transform = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(0.1))
    params = {"w": jnp.ones((3, 2)), "b": jnp.zeros(2)}
    state = transform.init(params)
    _, state = transform.update(params, state, params)  # non-trivial moments and count
    checkpoint.save(tmp_path / "opt.npz", state)
    loaded, _ = checkpoint.load(tmp_path / "opt.npz", like=transform.init(params))
    assert_same_leaves(loaded, state)


def test_a_single_array_round_trips(tmp_path):
    checkpoint.save(tmp_path / "one.npz", jnp.arange(4.0))
    loaded, _ = checkpoint.load(tmp_path / "one.npz")
    np.testing.assert_array_equal(loaded, np.arange(4.0, dtype=np.float32))


class _Trap:
    """Unpickling this touches a marker file: proof that code from the file ran."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (pathlib.Path.touch, (pathlib.Path(self.marker),))


def test_a_file_with_a_pickled_object_array_is_refused_and_runs_no_code(tmp_path):
    marker = tmp_path / "code_ran"
    # A genuine checkpoint with a pickled object array smuggled in beside its members.
    checkpoint.save(tmp_path / "good.npz", {"controls": np.zeros(3)})
    with np.load(tmp_path / "good.npz") as archive:
        members = {name: archive[name] for name in archive.files}
    members["evil"] = np.array([_Trap(marker)], dtype=object)
    np.savez(tmp_path / "evil.npz", **members)  # numpy pickles object arrays when saving
    # numpy with pickles allowed would run the payload: the file really carries code.
    with np.load(tmp_path / "evil.npz", allow_pickle=True) as archive:
        archive["evil"]
    assert marker.exists()
    marker.unlink()

    with pytest.raises(ValueError, match="pickled"):
        checkpoint.load(tmp_path / "evil.npz")
    assert not marker.exists()


def test_a_pickle_file_is_not_a_checkpoint(tmp_path):
    marker = tmp_path / "code_ran"
    path = tmp_path / "result.npz"
    path.write_bytes(pickle.dumps({"controls": _Trap(marker)}))
    with pytest.raises(ValueError):
        checkpoint.load(path)
    assert not marker.exists()


def test_an_npz_without_the_header_is_refused(tmp_path):
    np.savez(tmp_path / "plain.npz", controls=np.zeros(3))
    with pytest.raises(ValueError, match="not a dbdjax checkpoint"):
        checkpoint.load(tmp_path / "plain.npz")


def test_a_template_that_does_not_match_is_refused(tmp_path):
    checkpoint.save(tmp_path / "ckpt.npz", {"controls": np.zeros((4, 3))})
    with pytest.raises(ValueError, match="missing"):
        checkpoint.load(tmp_path / "ckpt.npz", like={"params": np.zeros((4, 3))})
    with pytest.raises(ValueError, match="shape"):
        checkpoint.load(tmp_path / "ckpt.npz", like={"controls": np.zeros((5, 3))})


def test_object_leaves_and_non_json_metadata_are_refused_on_save(tmp_path):
    with pytest.raises(TypeError, match="dtype object"):
        checkpoint.save(tmp_path / "a.npz", {"x": np.array([object()], dtype=object)})
    with pytest.raises(TypeError, match="JSON"):
        checkpoint.save(tmp_path / "b.npz", {"x": np.zeros(2)}, metadata={"when": object()})
    assert not list(tmp_path.iterdir())  # nothing half-written left behind
