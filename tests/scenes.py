"""Scenes shared by the tests (and mirrored by the benchmarks): plain builders, no magic."""

from __future__ import annotations

import numpy as np

import dbdjax as dbd

LINK_LENGTH = 0.1
LINK_MASS = 0.1
# A slender rod: m l^2 / 12 across, m r^2 / 2 along (r = 1 cm).
LINK_INERTIA = (LINK_MASS * 0.01**2 / 2, LINK_MASS * LINK_LENGTH**2 / 12, LINK_MASS * LINK_LENGTH**2 / 12)


def chain(
    links: int = 20,
    origin=(0.0, 0.0, 2.0),
    pinned: bool = True,
    gravity=(0.0, 0.0, -9.81),
    velocities=None,
    **finalize,
):
    """A horizontal chain of rods along +x joined by ball joints, pinned to the world at `origin`."""
    b = dbd.ModelBuilder(gravity=gravity)
    origin = np.asarray(origin, dtype=np.float64)
    previous = dbd.WORLD
    for i in range(links):
        centre = origin + np.array([(i + 0.5) * LINK_LENGTH, 0.0, 0.0])
        vel = (0.0, 0.0, 0.0) if velocities is None else velocities[i]
        body = b.add_body(pos=centre, mass=LINK_MASS, inertia=LINK_INERTIA, vel=vel)
        if previous != dbd.WORLD or pinned:
            b.add_ball_joint(previous, body, anchor=origin + np.array([i * LINK_LENGTH, 0.0, 0.0]))
        previous = body
    return b.finalize(**finalize)


def pendulum(joint: str = "hinge", length: float = 1.0, angle: float = 0.05, radius: float = 0.1, **finalize):
    """A solid sphere (radius `radius`, 1 kg) hanging `length` below a pivot at the origin."""
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    moment = 0.4 * radius**2
    bob = b.add_body(pos=(length * np.sin(angle), 0.0, -length * np.cos(angle)), mass=1.0, inertia=(moment,) * 3)
    if joint == "hinge":
        b.add_hinge_joint(dbd.WORLD, bob, anchor=(0, 0, 0), axis=(0, 1, 0))
    else:
        b.add_ball_joint(dbd.WORLD, bob, anchor=(0, 0, 0))
    return b.finalize(**finalize)
