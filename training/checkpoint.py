"""Checkpoints of pytrees (controls, parameters, optimiser states, metrics) without pickle.

    from dbdjax.training import checkpoint
    checkpoint.save("result.npz", {"controls": controls, "losses": losses}, metadata={"task": "ik_chain"})
    tree, metadata = checkpoint.load("result.npz")                  # dicts, lists, tuples rebuilt
    tree, metadata = checkpoint.load("result.npz", like=template)   # any pytree, e.g. a State

A checkpoint is one numpy .npz archive: one array per pytree leaf, named by the leaf's path
(`jax.tree_util.keystr`, e.g. "['controls']" or ".pos"), and one uint8 array holding a JSON header
(format, version, leaf keys and dtypes, a description of the tree's structure, the metadata).
Loading reads every member with `allow_pickle=False`, so a file from an untrusted source that
carries a pickled object array is refused before anything in it is unpickled: loading a
checkpoint cannot run code. (Python's pickle, and `np.load(..., allow_pickle=True)`, would.)
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import jax
import numpy as np

FORMAT = "dbdjax-checkpoint"
VERSION = 1
HEADER_KEY = "__dbdjax_checkpoint__"  # the member holding the JSON header
ROOT = "<root>"  # the key of a pytree that is a single leaf (its path is empty)


def _leaf_array(key: str, leaf: Any) -> np.ndarray:
    """A leaf as a plain numeric numpy array; objects and strings are refused (they would need pickle)."""
    array = np.asarray(leaf)
    if array.dtype.kind not in "biufc" and array.dtype.name != "bfloat16":
        raise TypeError(f"checkpoint.save: leaf {key} has dtype {array.dtype}; only numeric and bool arrays "
                        "are stored (objects would need pickle)")  # fmt: skip
    return array


def _one_level(tree: Any) -> list[tuple[str, Any]]:
    """The immediate children of a pytree node as (key string of their path entry, child)."""
    children, _ = jax.tree_util.tree_flatten_with_path(tree, is_leaf=lambda node: node is not tree)
    return [(jax.tree_util.keystr(path), child) for path, child in children]


def _describe(tree: Any, prefix: str = "") -> dict:
    """JSON description of the tree's structure; leaves are named by their full key string."""
    if tree is None:
        return {"none": None}
    if jax.tree_util.treedef_is_leaf(jax.tree_util.tree_structure(tree)):
        return {"leaf": prefix or ROOT}
    children = [(key, _describe(child, prefix + key)) for key, child in _one_level(tree)]
    if isinstance(tree, dict):
        if not all(isinstance(name, str) for name in tree):
            raise TypeError("checkpoint.save: dict keys must be strings")
        # jax flattens dicts in sorted key order, the same order as `children`
        return {"dict": {name: description for name, (_, description) in zip(sorted(tree), children, strict=True)}}
    if isinstance(tree, list):
        return {"list": [description for _, description in children]}
    if type(tree) is tuple:
        return {"tuple": [description for _, description in children]}
    # Any other registered node (a dataclass like `State`, a namedtuple, an optax state): its class
    # name is informational; without `like` it comes back as a dict of its children.
    return {"node": f"{type(tree).__module__}.{type(tree).__qualname__}", "children": dict(children)}


def _rebuild(description: dict, arrays: dict[str, np.ndarray]) -> Any:
    if "leaf" in description:
        return arrays[description["leaf"]]
    if "none" in description:
        return None
    if "dict" in description:
        return {name: _rebuild(child, arrays) for name, child in description["dict"].items()}
    if "list" in description:
        return [_rebuild(child, arrays) for child in description["list"]]
    if "tuple" in description:
        return tuple(_rebuild(child, arrays) for child in description["tuple"])
    if "node" in description:
        # ".pos" -> "pos", "[0]" -> "0", "['a']" -> "a"
        return {key.strip(".[]'\""): _rebuild(child, arrays) for key, child in description["children"].items()}
    raise ValueError(f"checkpoint.load: unknown structure entry {sorted(description)}")


def save(path: str | os.PathLike, pytree: Any, metadata: dict | None = None) -> Path:
    """Write `pytree` (numeric array leaves) and JSON-serialisable `metadata` to `path` (.npz).

    The file is written to a temporary name and renamed, so a crash never leaves half a
    checkpoint. Returns the path written. Raises TypeError for object/string leaves or metadata
    that is not JSON.
    """
    path = Path(path)
    leaves, _ = jax.tree_util.tree_flatten_with_path(pytree)
    arrays = {}
    for key_path, leaf in leaves:
        key = jax.tree_util.keystr(key_path) or ROOT
        arrays[key] = _leaf_array(key, leaf)
    structure = _describe(pytree)
    header = {
        "format": FORMAT,
        "version": VERSION,
        "keys": list(arrays),
        "dtypes": {key: array.dtype.name for key, array in arrays.items()},
        "structure": structure,
        "metadata": {} if metadata is None else metadata,
    }
    try:
        encoded = json.dumps(header, allow_nan=True).encode()
    except TypeError as error:
        raise TypeError(f"checkpoint.save: metadata must be JSON-serialisable ({error})") from error
    if HEADER_KEY in arrays:
        raise ValueError(f"checkpoint.save: {HEADER_KEY!r} is reserved")
    arrays[HEADER_KEY] = np.frombuffer(encoded, dtype=np.uint8)

    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as file:
            np.savez(file, **arrays)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path


def load(path: str | os.PathLike, like: Any = None) -> tuple[Any, dict]:
    """Read a checkpoint written by `save`. Returns (pytree, metadata).

    like: a pytree with the same structure (e.g. the object that was saved, or one of the same
    shapes): the result has its structure, and every leaf's key and shape are checked against
    it. None: dicts, lists, tuples and None are rebuilt from the file's structure description;
    other node types (dataclasses, namedtuples) come back as dicts of their children.
    Leaves are numpy arrays with the dtype they were saved with.

    Raises ValueError for a file with a pickled (object) array in it, whether or not that array
    belongs to the checkpoint, for a file that is not a dbdjax checkpoint, and for a `like` that
    does not match.
    """
    members = {}
    with np.load(path, allow_pickle=False) as archive:
        for name in archive.files:  # every member, so nothing pickled hides in an unread entry
            try:
                members[name] = archive[name]
            except ValueError as error:
                raise ValueError(f"checkpoint.load: {path} holds a pickled object array {name!r}; refused "
                                 "(loading it could run code)") from error  # fmt: skip
    if HEADER_KEY not in members:
        raise ValueError(f"checkpoint.load: {path} is not a dbdjax checkpoint (no {HEADER_KEY!r} header)")
    header = json.loads(members.pop(HEADER_KEY).tobytes().decode())
    if header.get("format") != FORMAT or header.get("version") != VERSION:
        raise ValueError(f"checkpoint.load: {path} has format {header.get('format')!r} version "
                         f"{header.get('version')!r}; expected {FORMAT!r} version {VERSION}")  # fmt: skip
    keys = header["keys"]
    if set(keys) != set(members):
        raise ValueError(f"checkpoint.load: {path} members {sorted(members)} do not match its header {sorted(keys)}")
    arrays = {}
    for key in keys:
        array, dtype = members[key], header["dtypes"][key]
        if array.dtype.name != dtype:  # extension dtypes (bfloat16) come back as raw void bytes
            array = array.view(jax.numpy.dtype(dtype))
        arrays[key] = array

    if like is None:
        return _rebuild(header["structure"], arrays), header["metadata"]

    template, treedef = jax.tree_util.tree_flatten_with_path(like)
    expected = [jax.tree_util.keystr(key_path) or ROOT for key_path, _ in template]
    if sorted(expected) != sorted(keys):
        missing, extra = sorted(set(expected) - set(keys)), sorted(set(keys) - set(expected))
        raise ValueError(f"checkpoint.load: {path} does not match `like`: missing {missing}, unexpected {extra}")
    leaves = []
    for key, (_, leaf) in zip(expected, template, strict=True):
        if np.shape(leaf) != arrays[key].shape:
            raise ValueError(f"checkpoint.load: leaf {key} has shape {arrays[key].shape} in {path}, "
                             f"{np.shape(leaf)} in `like`")  # fmt: skip
        leaves.append(arrays[key])
    return jax.tree_util.tree_unflatten(treedef, leaves), header["metadata"]
