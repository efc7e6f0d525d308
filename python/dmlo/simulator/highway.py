"""A feature-poor highway beside the road: guard rails on posts, a gantry or sign pole every few hundred
metres, and open grassland with a few distant trees.

The scene real highways present to a LiDAR odometry: wide asphalt whose rings look the same from scan to
scan, rails that run along the road (they tell where the car is across the road, not along it), and only
the rails' posts, the sign poles and the trees to tell how far the car moved.
"""

from __future__ import annotations


import numpy as np

from dmlo.simulator.primitives import FENCE, POLE, TRAFFIC_SIGN, TRUNK, VEGETATION, PrimitiveSet, yaw_pitch_rotation
from dmlo.simulator.street import StreetLayout, StreetPath

RAIL_PIECE = 4.0  # metres: the beam in straight pieces, so it follows curves; a post at every joint
RAIL_BOTTOM, RAIL_TOP = 0.45, 0.8  # metres above the road: a W-beam's band
RAIL_OFFSET = 0.6  # metres beyond the road's edge


def add_highway_roadside(
    prims: PrimitiveSet, path: StreetPath, layout: StreetLayout, side: int, rng: np.random.Generator
) -> None:
    """Guard rail along the whole road on `side` (+1 left, −1 right), sign poles far apart, sparse trees."""
    edge = layout.road(side) + RAIL_OFFSET
    albedo = float(rng.uniform(0.45, 0.7))  # galvanised steel
    half = np.array([RAIL_PIECE / 2, 0.05, (RAIL_TOP - RAIL_BOTTOM) / 2])
    for s in np.arange(float(rng.uniform(0, RAIL_PIECE)), path.length, RAIL_PIECE):
        xy, z, heading = path.place(s + RAIL_PIECE / 2, side * edge)
        prims.add_box(
            [xy[0], xy[1], z + RAIL_BOTTOM + half[2]], half, yaw_pitch_rotation(heading), FENCE, 0, albedo
        )
        post, post_z, _ = path.place(s, side * (edge + 0.1))
        prims.add_cylinder([post[0], post[1], post_z - 0.2], RAIL_TOP + 0.3, 0.06, FENCE, 0, albedo)

    s = float(rng.uniform(20, 150))
    while s < path.length:
        xy, z, heading = path.place(s, side * (edge + float(rng.uniform(1.0, 3.0))))
        height = float(rng.uniform(5.0, 9.0))
        prims.add_cylinder([xy[0], xy[1], z - 0.3], height + 0.3, float(rng.uniform(0.1, 0.2)), POLE, 0, 0.4)
        board = np.array([0.05, float(rng.uniform(0.8, 2.0)), float(rng.uniform(0.5, 1.2))])
        prims.add_box(
            [xy[0], xy[1], z + height - board[2]], board, yaw_pitch_rotation(heading), TRAFFIC_SIGN, 0,
            float(rng.uniform(0.7, 0.95)),  # retro-reflective sheeting
        )
        s += float(rng.uniform(150.0, 400.0))

    s = float(rng.uniform(0, 60))
    while s < path.length:
        xy, z, _ = path.place(s, side * (edge + float(rng.uniform(15.0, 45.0))))
        trunk = float(rng.uniform(2.0, 4.0))
        prims.add_cylinder([xy[0], xy[1], z - 0.2], trunk + 0.5, float(rng.uniform(0.12, 0.3)), TRUNK, 0, 0.3)
        crown = float(rng.uniform(1.5, 3.0))
        prims.add_ellipsoid([xy[0], xy[1], z + trunk + crown * 0.7], crown * np.array([1.0, 1.0, 0.8]), VEGETATION,
                            0, float(rng.uniform(0.2, 0.4)))
        s += float(rng.uniform(40.0, 160.0))
