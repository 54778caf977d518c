"""Hollow shapes for task objects, built from convex geoms: rings and open cups.

MuJoCo collides convex geoms only, so a ring (a roll of tape, the wall of a cup) is a regular
polygon of ``n`` box segments around the body's +z axis. Its hole is the polygon whose apothem
is ``inner_radius``: a circle of that radius fits inside it; its outer faces have apothem
``outer_radius`` and its outer corners lie at :func:`circumradius` of it.
"""

from __future__ import annotations

import mujoco
import numpy as np

from beavr_sim.tasks.objects import geom_kwargs


def circumradius(apothem: float, n_sides: int) -> float:
    """Distance from the centre to a corner of a regular ``n_sides``-gon of ``apothem``."""
    return apothem / float(np.cos(np.pi / n_sides))


def add_ring(
    body: mujoco.MjsBody,
    name: str,
    inner_radius: float,
    outer_radius: float,
    z_range: tuple[float, float],
    n_segments: int,
    rgba,
    mass: float | None = None,
) -> None:
    """A ring of ``n_segments`` boxes around the body's z axis, from z_range[0] to z_range[1].

    The segments are named ``f"{name}{i}"``; ``mass`` (kg, whole ring) is split evenly, or
    left to the default density when None (fixtures, whose mass never matters).
    """
    half_radial = (outer_radius - inner_radius) / 2
    half_tangential = outer_radius * float(np.tan(np.pi / n_segments))  # outer corners meet
    half_height = (z_range[1] - z_range[0]) / 2
    mid_radius, mid_z = (inner_radius + outer_radius) / 2, (z_range[0] + z_range[1]) / 2
    for i in range(n_segments):
        angle = 2 * np.pi * i / n_segments
        extra = {} if mass is None else {"mass": mass / n_segments}
        body.add_geom(
            name=f"{name}{i}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[half_radial, half_tangential, half_height],
            pos=[mid_radius * np.cos(angle), mid_radius * np.sin(angle), mid_z],
            quat=[np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)],
            **geom_kwargs(rgba, **extra),
        )


def add_cup(
    body: mujoco.MjsBody,
    name: str,
    inner_radius: float,
    outer_radius: float,
    height: float,
    bottom_thickness: float,
    n_segments: int,
    rgba,
    mass: float | None = None,
) -> None:
    """An open cup standing on the body origin, its axis the body's +z, rim at ``height``.

    A bottom disc (``f"{name}/bottom"``, radius ``outer_radius``) and a wall ring of
    ``n_segments`` boxes (``f"{name}/wall{i}"``) from the table to the rim. ``mass`` (kg) is
    split between bottom and wall in proportion to their volumes.
    """
    wall_volume = np.pi * (outer_radius**2 - inner_radius**2) * height
    bottom_volume = np.pi * outer_radius**2 * bottom_thickness
    bottom_share = bottom_volume / (wall_volume + bottom_volume)
    extra = {} if mass is None else {"mass": mass * bottom_share}
    body.add_geom(
        name=f"{name}/bottom",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[outer_radius, bottom_thickness / 2, 0.0],
        pos=[0.0, 0.0, bottom_thickness / 2],
        **geom_kwargs(rgba, **extra),
    )
    add_ring(
        body,
        f"{name}/wall",
        inner_radius,
        outer_radius,
        (0.0, height),
        n_segments,
        rgba,
        None if mass is None else mass * (1 - bottom_share),
    )
