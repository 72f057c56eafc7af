"""dbdjax: differentiable rigid-body dynamics in JAX by Displacement Based Dynamics.

import dbdjax as dbd
b = dbd.ModelBuilder(gravity=(0, 0, -9.81))
link = b.add_body(pos=(0, 0, 1), mass=1.0, inertia=(0.1, 0.1, 0.1))
b.add_ball_joint(dbd.WORLD, link, anchor=(0, 0, 2))
model = b.finalize(dt=1 / 60)
state = dbd.step(model, dbd.init(model))
"""

from dbdjax import _layout, diagnostics, math, render, sharding
from dbdjax.builder import ModelBuilder
from dbdjax.compiling import compiler_options, jit
from dbdjax.mjcf import load_mjcf, mujoco_model
from dbdjax.model import WORLD, Model, State
from dbdjax.mujoco_state import state_from_mujoco, state_to_mujoco
from dbdjax.pipeline import init, is_finite, rollout, step
from dbdjax.trailing_batch import vmap

__all__ = [
    "WORLD",
    "Model",
    "compiler_options",
    "diagnostics",
    "ModelBuilder",
    "State",
    "init",
    "is_finite",
    "jit",
    "load_mjcf",
    "math",
    "mujoco_model",
    "render",
    "rollout",
    "sharding",
    "state_from_mujoco",
    "state_to_mujoco",
    "step",
    "vmap",
]
__version__ = "0.1.0"

_layout.map_source_folders()
