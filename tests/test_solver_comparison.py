"""The scenes and measures of benchmarks/solver_comparison.py (issue 5's DBD-vs-impulse-vs-Brax sweep).

Building every scene is cheap and runs in the fast suite; stepping costs one XLA compilation per
(scene, solver), so only the cheapest scene steps in the fast suite and the rest are slow.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import dbdjax as dbd

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "solver_comparison.py"
_SPEC = importlib.util.spec_from_file_location("solver_comparison", _PATH)
comparison = importlib.util.module_from_spec(_SPEC)
sys.modules[_SPEC.name] = comparison  # dataclasses look their module up
_SPEC.loader.exec_module(comparison)

DT = 1 / 30
FAST_STEPPED = ("stretched_chain",)  # the cheapest compilation


@pytest.fixture(scope="module")
def built():
    """Every scene on both solvers at dt 1/30, one iteration, one substep."""
    return {(name, solver): make(dt=DT, substeps=1, iterations=1, solver=solver)
            for name, make in comparison.SCENES.items() for solver in ("dbd", "impulse")}  # fmt: skip


def test_every_comparison_scene_builds_on_both_solvers(built):
    for (name, solver), scene in built.items():
        assert scene.model.options.solver == solver, name
        assert scene.model.num_bodies == scene.start.pos.shape[0], name
        assert bool(dbd.is_finite(scene.start)), name
        assert name in comparison.PRIMARY, name
        if scene.twin is not None:  # a far scene and its twin at the origin share one compiled step
            start = dbd.init(scene.twin) if scene.twin_start is None else scene.twin_start
            assert jax.tree.structure((comparison._canonical(scene.model), scene.start)) == jax.tree.structure(
                (comparison._canonical(scene.twin), start)
            ), name


def test_ragdoll_pile_dolls_touch_each_other_and_the_floor_but_not_themselves(built):
    """3 dolls x 15 capsules: every capsule against the floor (45 pairs) and against each capsule
    of the other two dolls (3 x 15 x 15 = 675 pairs), none within a doll."""
    model = built["ragdoll_pile", "dbd"].model
    pairs = sorted(group.bodies.array.shape[0] for group in model.structure.contact_groups)
    assert model.num_bodies == 45 and model.num_joints == 42
    assert pairs == [45, 675]
    for group in model.structure.contact_groups:
        bodies = np.asarray(group.bodies.array)
        doll = np.where(bodies < model.num_bodies, bodies // 15, -1)  # -1: the floor
        assert np.all((doll[:, 0] != doll[:, 1]) | (doll[:, 0] < 0) | (doll[:, 1] < 0))


def test_far_ragdoll_pile_is_the_pile_moved_10_km(built):
    near, far = built["ragdoll_pile", "dbd"], built["far_ragdoll_pile", "dbd"]
    shift = np.asarray(far.start.pos, np.float64) - np.asarray(near.start.pos, np.float64)
    expected = np.array([1e4, -1e4, 1e4]) / np.sqrt(3.0)
    # float32 positions 5.8 km out: spacing 4.9e-4 m, so the shift is exact to that
    np.testing.assert_allclose(shift, np.broadcast_to(expected, shift.shape), atol=5e-4)
    np.testing.assert_array_equal(np.asarray(far.start.quat), np.asarray(near.start.quat))


def test_measure_reads_the_start_error_of_the_stretched_chain(built):
    """At t = 0 the stretched chain's first joint is open by half a link, the other 19 by a whole
    link (0.1 m); nothing moves, so the energy relative to the start is 0."""
    scene = built["stretched_chain", "dbd"]
    frame = jax.tree.map(lambda x: np.asarray(x)[None], scene.start)
    result = comparison.measure("stretched_chain", scene, frame, DT, 1, {"penetration": {}})
    gaps = np.asarray(dbd.diagnostics.joint_gaps(scene.model, frame))[0]
    np.testing.assert_allclose(gaps[0], 0.5 * comparison.LINK, rtol=1e-5)
    np.testing.assert_allclose(gaps[1:], comparison.LINK, rtol=1e-5)
    assert result["gap_max_mm"] == pytest.approx(100.0, rel=1e-5)
    assert result["energy_drift"] == 0.0 and not result["blew_up"]


@pytest.mark.parametrize(
    "name", [n if n in FAST_STEPPED else pytest.param(n, marks=pytest.mark.slow) for n in comparison.SCENES]
)
def test_comparison_scene_steps_on_both_solvers(name):
    """A chunk of steps through the sweep's compiled rollout (dt traced), both solvers, and the
    measures of `run` on it: finite, one row per step."""
    caches = {"rollout": {}, "penetration": {}, "offsets": {}}
    for solver in ("dbd", "impulse"):
        scene = comparison.SCENES[name](dt=DT, substeps=1, iterations=2, solver=solver)
        rollout, _ = comparison.compiled_rollout(scene.model, scene.start, caches["rollout"])
        final, trajectory, _ = rollout(scene.model, scene.start, DT, comparison.CHUNK)
        assert trajectory.pos.shape == (comparison.CHUNK,) + scene.start.pos.shape
        assert bool(dbd.is_finite(final)), (name, solver)
        result = comparison.measure(name, scene, trajectory, DT, comparison.CHUNK, caches)
        assert all(np.isfinite(v) for v in result.values() if isinstance(v, float)), (name, solver, result)


def test_traced_time_step_gives_the_static_time_step_numbers():
    """The sweep compiles once per (scene, solver, iterations) with dt an argument; a pendulum
    (not chaotic, so rounding stays rounding) steps as dbd.rollout compiled with that dt static,
    on both solvers, to float32 rounding. (A chaotic scene does not: the stretched chain at 2
    iterations turns a 1e-7 m rounding difference into 0.19 m within 7 steps at dt 1/30.)"""
    import scenes

    for solver in ("dbd", "impulse"):
        model = scenes.pendulum("ball", 1.0, 0.3, dt=DT, iterations=4, solver=solver)
        start = dbd.init(model)
        rollout, _ = comparison.compiled_rollout(model, start, {})
        final, _, _ = rollout(model, start, DT, comparison.CHUNK)
        reference, _ = jax.jit(lambda m, s: dbd.rollout(m, s, steps=comparison.CHUNK))(model, start)
        np.testing.assert_allclose(np.asarray(final.pos), np.asarray(reference.pos), atol=1e-5)
        np.testing.assert_allclose(np.asarray(final.vel), np.asarray(reference.vel), atol=1e-4)


@pytest.mark.slow  # 30 s; a check of the benchmark's Brax scenes, not of the engine
def test_brax_mjcf_of_each_scene_has_its_bodies_masses_and_start(built):
    """The MJCF written for Brax: one link per dbdjax body, in order, with its mass and principal
    moments, at its start position (forward kinematics of the initial q)."""
    pytest.importorskip("brax")
    from brax import kinematics
    from brax.io import mjcf

    for name in comparison.SCENES:
        if name in comparison.BRAX_SKIPPED and name not in comparison.BRAX_TOO_SLOW:
            continue
        scene = built[name, "dbd"]
        xml = comparison.brax_mjcf(name, scene)
        pairs = [(xml[0], scene.model, scene.start), (xml[1], scene.twin, dbd.init(scene.twin))] if isinstance(
            xml, tuple) else [(xml, scene.model, scene.start)]  # fmt: skip
        for text, model, start in pairs:
            system = mjcf.loads(text)
            assert system.num_links() == model.num_bodies, name
            np.testing.assert_allclose(np.asarray(system.link.inertia.mass), np.asarray(model.bodies.mass), rtol=1e-6)
            inertia = np.asarray(system.link.inertia.i)
            np.testing.assert_allclose(np.diagonal(inertia, axis1=1, axis2=2), np.asarray(model.bodies.inertia),
                                       rtol=1e-5)  # fmt: skip
            x, _ = kinematics.forward(system, system.init_q, np.zeros(system.qd_size(), np.float32))
            scale = 1.0 + float(np.max(np.abs(np.asarray(start.pos))))
            np.testing.assert_allclose(np.asarray(x.pos), np.asarray(start.pos), atol=1e-6 * scale, err_msg=name)
            np.testing.assert_allclose(np.abs(np.sum(np.asarray(x.rot) * np.asarray(start.quat), -1)), 1.0, atol=1e-6)


def test_plan_runs_whole_iteration_counts_first_and_brax_once():
    runs = comparison.plan(["a", "b"], ["dbd", comparison.BRAX], [0.1, 0.2], [8, 2])
    assert runs[:6] == [("a", "dbd", 8, 0.1), ("a", "dbd", 8, 0.2), ("a", comparison.BRAX, None, 0.1),
                        ("a", comparison.BRAX, None, 0.2), ("b", "dbd", 8, 0.1), ("b", "dbd", 8, 0.2)]  # fmt: skip
    brax = [r for r in runs if r[1] == comparison.BRAX]
    assert brax == [("a", comparison.BRAX, None, 0.1), ("a", comparison.BRAX, None, 0.2),
                    ("b", comparison.BRAX, None, 0.1), ("b", comparison.BRAX, None, 0.2)]  # fmt: skip
    assert runs[-2:] == [("b", "dbd", 2, 0.1), ("b", "dbd", 2, 0.2)]


def test_write_records_the_planned_runs_without_a_result_as_unfinished(tmp_path):
    """A result's dt may come back rounded to 6 decimals (0.016667 for 1/60): it still counts."""
    planned = comparison.plan(["a"], ["dbd"], [1 / 60, 1 / 30], [8])
    path = tmp_path / "out.json"
    result = {"scene": "a", "solver": "dbd", "iterations": 8, "dt": 0.016667}
    comparison.write(path, {"dts": [1 / 60, 1 / 30]}, [result], planned)
    assert json.loads(path.read_text())["unfinished"] == [["a", "dbd", 8, 1 / 30]]
