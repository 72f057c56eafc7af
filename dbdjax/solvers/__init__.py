"""Constraint solvers: `dbd` (DBD Algorithm 1)."""
