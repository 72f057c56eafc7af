"""Constraint families. Each is data (struct of arrays, one row per constraint) plus a pure
projection that moves the displacements of the bodies it touches (DBD Algorithm 1, inner loop).
`rows.py` holds the two scalar row updates every family is built from."""
