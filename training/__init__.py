"""Training on top of dbdjax: trajectory optimisation through differentiable rollouts
(`dbdjax.training.trajopt`) and pickle-free checkpoints (`dbdjax.training.checkpoint`).

This folder sits at the repository root and is mapped into the package as `dbdjax.training`
(pyproject.toml `[tool.setuptools.package-dir]`). Its modules need the `train` extra (optax,
rich, matplotlib); importing this package itself imports nothing heavy.
"""
