"""Traffic that does not follow the ego's path: cross streets, cars crossing them and cars turning.

With `traffic="mixed"` a street gets cross streets at roughly every 60–160 m of straight-enough axis. Each
is a straight road through the main street at 70–110° to it, up to 110 m to either side: the static
objects standing on it (buildings, trees, poles, parked cars, …) and the main street's kerbs and
sidewalks across its mouth are removed, and a road surface ramps from the main road's edge to the
terrain and then drapes it. Its cars drive their own paths:

- crossing cars go straight across, in the right-hand lane of their direction;
- turning cars come out of the cross street and turn into a lane of the main street, or leave the main
  street into the cross street.

Every car drives at a constant speed along a `CarPath` (a polyline on the ground, heights taken by casting
rays down onto the road and terrain, so cars sit on kerbs and hills), is labelled moving-car (252) with its
own instance id, and is timed to pass the intersection within ±9 s of the ego, never closer than half a
car plus 4 m to the ego's pose origin and never overlapping another moving car (lane or path) while the
ego records. Everything here draws from its own random stream, so the `"lanes"` traffic of a seed is
unchanged.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from dmlo_rs import RayScene

from dmlo.simulator.primitives import ROAD, SIDEWALK, PrimitiveSet
from dmlo.simulator.street import MovingCar, StreetLayout, StreetPath

TRAFFIC = ("lanes", "mixed")
_SAMPLE = 1.0  # metres between the samples of a car path
_EGO_CLEARANCE = 4.0  # metres between a car's body and the ego's pose origin, at every frame
_RAMP = 6.0  # metres beyond the main street's sidewalk where a cross street reaches the terrain
_CORNER = 3.0  # metres a cross street widens by on each side where it crosses the main sidewalks


@dataclass(frozen=True)
class CrossStreet:
    """A straight road through the main street: centre where it crosses the axis, unit direction, the
    road's half width and how far it reaches to either side (`reach[0]` backwards, `reach[1]` forwards)."""

    center: tuple[float, float]
    direction: tuple[float, float]
    half_width: float
    reach: tuple[float, float]

    def point(self, along: npt.ArrayLike, lateral: npt.ArrayLike = 0.0) -> npt.NDArray[np.float64]:
        """Points (…, 2) at distance `along` the street from its centre and `lateral` to its left."""
        d = np.asarray(self.direction)
        along_ = np.asarray(along, dtype=np.float64)[..., None]
        lateral_ = np.asarray(lateral, dtype=np.float64)[..., None]
        return np.asarray(self.center) + along_ * d + lateral_ * np.array([-d[1], d[0]])


class CarPath:
    """A polyline on the ground a car drives along: positions, heights and headings by arc length."""

    def __init__(self, xy: npt.NDArray[np.float64], ground: RayScene, fallback_z: float) -> None:
        steps = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        arc = np.concatenate([[0.0], np.cumsum(steps)])
        self.length = float(arc[-1])
        self.s = np.arange(0.0, self.length + 1e-9, _SAMPLE)
        self.xy = np.column_stack([np.interp(self.s, arc, xy[:, 0]), np.interp(self.s, arc, xy[:, 1])])
        top = fallback_z + 200.0
        origins = np.column_stack([self.xy, np.full(len(self.s), top)])
        directions = np.tile([0.0, 0.0, -1.0], (len(self.s), 1))
        ranges, _, _ = ground.cast(origins, directions, 400.0)
        z = np.where(np.isfinite(ranges), top - ranges, np.nan)
        if np.isnan(z).all():
            z[:] = fallback_z
        else:  # off the terrain (rare): hold the nearest known height
            known = np.nonzero(~np.isnan(z))[0]
            z = np.interp(np.arange(len(z)), known, z[known])
        self.ground_z = z
        tangent = np.gradient(self.xy, axis=0) if len(self.s) > 1 else np.array([[1.0, 0.0]])
        self.heading = np.unwrap(np.arctan2(tangent[:, 1], tangent[:, 0]))

    def at(self, s: float) -> tuple[npt.NDArray[np.float64], float, float, float]:
        """(xy, ground z, heading, pitch) at arc length `s`; pitch is nose-up negative as in the ego's."""
        xy = np.array([np.interp(s, self.s, self.xy[:, 0]), np.interp(s, self.s, self.xy[:, 1])])
        z0, z1 = np.interp([s - 1.5, s + 1.5], self.s, self.ground_z)
        return (
            xy,
            float(np.interp(s, self.s, self.ground_z)),
            float(np.interp(s, self.s, self.heading)),
            float(-np.arctan((z1 - z0) / 3.0)),
        )


@dataclass(frozen=True)
class PathCar:
    """A car driving along `CarPath` number `path` at constant speed: `s(t) = s0 + speed·t`."""

    instance: int
    path: int
    s0: float
    speed: float
    length: float
    width: float
    height: float
    albedo: float


@dataclass
class Traffic:
    cross_streets: list[CrossStreet]
    paths: list[CarPath]
    cars: list[PathCar]


def add_cross_traffic(
    prims: PrimitiveSet,
    path: StreetPath,
    layout: StreetLayout,
    ego_poses: npt.NDArray[np.float64],
    frame_rate_hz: float,
    seed: int,
    instances: Iterator[int],
    car_size: Callable[[np.random.Generator], tuple[float, float, float]],
    lane_cars: Sequence[MovingCar] = (),
) -> Traffic:
    """Adds cross streets to the static `prims` (clearing what stands on them) and returns their traffic.

    `ego_poses` (N,4,4) are the ego's frames (for timing and clearance), `car_size(rng)` draws a car's
    (length, width, height)."""
    rng = np.random.default_rng([seed, 0x7AFF1C])
    ground = RayScene(triangles=prims.parameters("triangles"))
    streets = _place_cross_streets(path, layout, rng)
    for street in streets:  # heights first: the ground scene still has the sidewalks
        _add_road(prims, street, layout, ground, path, rng)
    for street in streets:
        _clear_strip(prims, street)
    # Cars drive on the new roads where there are some: cast their heights onto everything on the ground.
    ground = RayScene(triangles=prims.parameters("triangles"))
    ego_xy = ego_poses[:, :2, 3]
    ego_times = np.arange(len(ego_poses)) / frame_rate_hz
    others = lane_car_tracks(path, lane_cars, ego_times)
    paths: list[CarPath] = []
    cars: list[PathCar] = []
    for street in streets:
        # When the ego comes closest to the crossing: cars are timed around that moment.
        closest = int(np.argmin(np.linalg.norm(ego_xy - np.asarray(street.center), axis=1)))
        meet = float(ego_times[closest])
        lane = min(street.half_width / 2.0, 2.0)
        routes = []
        for sign in (1.0, -1.0):  # straight across, either way, keeping right
            start = -street.reach[0] if sign > 0 else street.reach[1]
            end = street.reach[1] if sign > 0 else -street.reach[0]
            routes.append(street.point(np.arange(start, end, sign * 2.0), -sign * lane))
        for _ in range(int(rng.integers(1, 3))):
            routes.append(_turning_route(path, layout, street, lane, rng))
        for route in routes:
            if len(route) < 2:
                continue
            car_path = CarPath(route, ground, float(np.mean(path.ground_z)))
            if car_path.length < 20.0:
                continue
            for _ in range(int(rng.integers(1, 4))):
                length, width, height = car_size(rng)
                car = _timed_car(car_path, length, width, meet, ego_xy, ego_times, others, rng)
                if car is None:
                    continue
                s0, speed = car
                cars.append(
                    PathCar(
                        instance=next(instances),
                        path=len(paths),
                        s0=s0,
                        speed=speed,
                        length=length,
                        width=width,
                        height=height,
                        albedo=float(
                            np.clip(rng.choice([0.08, 0.2, 0.35, 0.6]) + rng.normal(0, 0.03), 0.03, 1.0)
                        ),
                    )
                )
            paths.append(car_path)
    return Traffic(cross_streets=streets, paths=paths, cars=cars)


def _place_cross_streets(
    path: StreetPath, layout: StreetLayout, rng: np.random.Generator
) -> list[CrossStreet]:
    streets = []
    s = float(rng.uniform(20.0, 100.0))
    main_half = max(layout.outer(1), layout.outer(-1))
    while s < path.length - 30.0:
        _, _, heading = path.at(np.array([s - 25.0, s, s + 25.0]))
        if np.ptp(heading) < np.radians(15.0):
            angle = float(heading[1] + np.pi / 2 + rng.uniform(-0.35, 0.35))
            direction = (float(np.cos(angle)), float(np.sin(angle)))
            center = path.at(s)[0]
            half_width = float(rng.uniform(3.5, 6.0))
            street = CrossStreet((float(center[0]), float(center[1])), direction, half_width, (0.0, 0.0))
            reach = tuple(_free_reach(path, street, sign, main_half) for sign in (-1.0, 1.0))
            if min(reach) > main_half + 20.0:
                sides = (reach[0], reach[1])
                streets.append(CrossStreet(street.center, direction, half_width, sides))
        s += float(rng.uniform(60.0, 160.0))
    return streets


def _free_reach(path: StreetPath, street: CrossStreet, sign: float, main_half: float) -> float:
    """How far the cross street can run to one side before it meets another part of the main street."""
    along = np.arange(main_half + 2.0, 110.0, 2.0)
    distance = np.minimum(
        path.distance(street.point(sign * along, -street.half_width))[0],
        path.distance(street.point(sign * along, street.half_width))[0],
    )
    # Beside its own crossing the distance to the axis grows with `along`; elsewhere the street is in the way.
    blocked = distance < np.minimum(along * 0.8, main_half + 8.0)
    first = int(np.argmax(blocked)) if blocked.any() else len(along)
    return float(along[first - 1]) if first > 0 else 0.0


def _clear_strip(prims: PrimitiveSet, street: CrossStreet) -> None:
    """Removes every box, cylinder and ellipsoid whose footprint reaches onto the street (plus 1.5 m), and
    the main street's sidewalk and kerb triangles across the street's mouth."""
    d = np.asarray(street.direction)
    n = np.array([-d[1], d[0]])
    c = np.asarray(street.center)
    margin = street.half_width + 1.5

    def overlapping(corners: npt.NDArray[np.float64]) -> npt.NDArray[np.bool_]:
        """`corners` (P, K, 2): does each primitive's corner set span into the strip?"""
        across = (corners - c) @ n
        along = (corners - c) @ d
        return (
            (across.min(1) < margin)
            & (across.max(1) > -margin)
            & (along.max(1) > -street.reach[0])
            & (along.min(1) < street.reach[1])
        )

    triangles = prims.parameters("triangles")
    if len(triangles):
        centroid = triangles.mean(axis=1)[:, :2]
        in_mouth = np.abs((centroid - c) @ n) < street.half_width + _CORNER
        prims.drop("triangles", in_mouth & (prims.semantics("triangles") == SIDEWALK))
    boxes = prims.parameters("boxes")
    if len(boxes):
        rotation = boxes[:, 3:12].reshape(-1, 3, 3)
        half = boxes[:, 12:15]
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
        corners = boxes[:, None, :3] + np.einsum("pij,pkj->pki", rotation, signs[None] * half[:, None, :])
        prims.drop("boxes", overlapping(corners[..., :2]))
    for kind, radius in (("cylinders", lambda p: p[:, 4]), ("ellipsoids", lambda p: p[:, 3:5].max(1))):
        params = prims.parameters(kind)
        if len(params):
            r = radius(params)[:, None]
            square = np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]], dtype=float)
            corners = params[:, None, :2] + square[None] * r[..., None]
            prims.drop(kind, overlapping(corners))


def _add_road(
    prims: PrimitiveSet,
    street: CrossStreet,
    layout: StreetLayout,
    ground: RayScene,
    path: StreetPath,
    rng: np.random.Generator,
) -> None:
    """The cross street's asphalt from the main road's edge outwards, 3 cm above the ground it drapes.
    Under the main street's sidewalks the terrain dips below its mesh, so up to `_RAMP` metres beyond
    them the road runs straight from the main road's height to the terrain's (or on the terrain where
    that is higher). Across the sidewalks it is
    `_CORNER` metres wider on each side (the corners turning cars cut), narrowing over the ramp."""
    albedo = float(rng.uniform(0.28, 0.4))
    unit = np.linspace(-1.0, 1.0, 5)
    top = float(path.ground_z.max()) + 200.0
    # The street meets the main road askew: start far enough in that its whole first row is on the road.
    _, nearest = path.distance(np.asarray(street.center))
    heading = path.heading[int(nearest)]
    cos_skew = abs(float(np.dot(street.direction, (-np.sin(heading), np.cos(heading)))))
    widest = street.half_width + _CORNER
    inset = 0.5 + widest * np.sqrt(max(0.0, 1.0 - cos_skew**2)) / max(cos_skew, 0.1)
    for sign, reach, side in ((-1.0, street.reach[0], -1), (1.0, street.reach[1], 1)):
        distance = np.arange(max(layout.road(side) - inset, 1.0), reach + 1e-9, 2.0)
        if len(distance) < 2:
            continue
        flare = _CORNER * np.clip((layout.outer(side) + _RAMP - distance) / (_RAMP - 1.0), 0.0, 1.0)
        half_width = street.half_width + flare
        grid = street.point(sign * distance[:, None], half_width[:, None] * unit[None, :])  # (A, L, 2)
        flat = grid.reshape(-1, 2)
        ranges, _, _ = ground.cast(
            np.column_stack([flat, np.full(len(flat), top)]), np.tile([0.0, 0.0, -1.0], (len(flat), 1)), 400.0
        )
        z = np.where(np.isfinite(ranges), top - ranges, np.nan).reshape(grid.shape[:2])
        ramp = distance < layout.outer(side) + _RAMP
        if ramp.any() and not ramp.all():
            end = int(np.argmin(ramp))  # first sample beyond the ramp
            fraction = (distance[ramp] - distance[0]) / (distance[end] - distance[0])
            straight = z[0] + fraction[:, None] * (z[end] - z[0])
            # Over the sidewalk the straight line; beyond it never below the terrain next to the road.
            beyond_sidewalk = (distance[ramp] > layout.outer(side))[:, None]
            z[ramp] = np.where(beyond_sidewalk, np.fmax(straight, z[ramp]), straight)
        vertices = np.concatenate([grid, z[..., None] + 0.03], axis=-1)
        a, b, c, d = vertices[:-1, :-1], vertices[:-1, 1:], vertices[1:, :-1], vertices[1:, 1:]
        tris = np.concatenate([np.stack([a, b, d], -2), np.stack([a, d, c], -2)]).reshape(-1, 3, 3)
        tris = tris[np.isfinite(tris).all(axis=(1, 2))]
        prims.add_triangles(tris, ROAD, 0, np.clip(albedo + rng.normal(0, 0.02, len(tris)), 0.02, 1.0))


def _turning_route(
    path: StreetPath, layout: StreetLayout, street: CrossStreet, lane: float, rng: np.random.Generator
) -> npt.NDArray[np.float64]:
    """A route out of one arm of the cross street into a main-street lane, or the reverse, with a smooth
    turn between; both parts in the right-hand lane of their driving direction (empty if it does not fit)."""
    side = 1.0 if rng.random() < 0.5 else -1.0  # which arm of the cross street
    forward = 1.0 if rng.random() < 0.5 else -1.0  # main-street direction driven
    inbound = bool(rng.random() < 0.5)  # out of the arm into the main street, else the reverse
    reach = street.reach[1] if side > 0 else street.reach[0]
    s_center = float(path.s[int(np.argmin(np.linalg.norm(path.xy - np.asarray(street.center), axis=1)))])
    main_lane = -forward * 3.3  # the lanes of the "lanes" traffic: +s at u = −3.3, −s at u = +3.3
    corner = street.half_width + 2.0
    arm_along = side * np.arange(reach, layout.outer(int(side)) + 2.0, -2.0)  # far → near
    main_offsets = np.arange(corner, corner + 140.0, 2.0)  # near → far from the crossing
    if inbound:
        arm = street.point(arm_along, side * lane)
        main_s = s_center + forward * main_offsets
    else:
        arm = street.point(arm_along[::-1], -side * lane)
        main_s = s_center - forward * main_offsets[::-1]
    main_s = main_s[(main_s > 0.0) & (main_s < path.length)]
    if len(arm) < 2 or len(main_s) < 2:
        return np.zeros((0, 2))
    main = np.stack([path.place(float(s), main_lane)[0] for s in main_s])
    first, second = (arm, main) if inbound else (main, arm)
    corner_point = _lines_meet(first[-2], first[-1], second[0], second[1])
    turn = _bezier(first[-1], corner_point, second[0], 12)
    return np.vstack([first, turn[1:-1], second])


def _lines_meet(
    a0: npt.NDArray[np.float64],
    a1: npt.NDArray[np.float64],
    b0: npt.NDArray[np.float64],
    b1: npt.NDArray[np.float64],
) -> npt.NDArray[np.float64]:
    """Where line a0→a1 meets line b0→b1 (their midpoint when nearly parallel)."""
    da, db = a1 - a0, b1 - b0
    denominator = da[0] * db[1] - da[1] * db[0]
    if abs(denominator) < 1e-9:
        return (a1 + b0) / 2
    t = ((b0[0] - a0[0]) * db[1] - (b0[1] - a0[1]) * db[0]) / denominator
    return a0 + t * da


def _bezier(
    p0: npt.NDArray[np.float64], p1: npt.NDArray[np.float64], p2: npt.NDArray[np.float64], count: int
) -> npt.NDArray[np.float64]:
    t = np.linspace(0.0, 1.0, count)[:, None]
    return (1 - t) ** 2 * p0 + 2 * (1 - t) * t * p1 + t**2 * p2


@dataclass(frozen=True)
class _Track:
    """Where a car is at each of the ego's frame times: centre (T,2), heading (T,), whether it is on its path
    (T,), and its footprint."""

    xy: npt.NDArray[np.float64]
    heading: npt.NDArray[np.float64]
    present: npt.NDArray[np.bool_]
    length: float
    width: float


def lane_car_tracks(
    path: StreetPath, cars: Sequence[MovingCar], times: npt.NDArray[np.float64]
) -> list[_Track]:
    """Tracks of the `"lanes"` traffic (cars along the street axis) at `times`."""
    tracks = []
    for car in cars:
        s = car.s0 + car.direction * car.speed * times
        xy, _, heading = path.at(np.clip(s, 0.0, path.length))
        normal = np.stack([-np.sin(heading), np.cos(heading)], axis=-1)
        tracks.append(
            _Track(
                xy + car.lateral * normal,
                heading if car.direction > 0 else heading + np.pi,
                (s >= 0.0) & (s <= path.length),
                car.length,
                car.width,
            )
        )
    return tracks


def _path_track(car_path: CarPath, s: npt.NDArray[np.float64], length: float, width: float) -> _Track:
    xy = np.column_stack(
        [np.interp(s, car_path.s, car_path.xy[:, 0]), np.interp(s, car_path.s, car_path.xy[:, 1])]
    )
    heading = np.interp(s, car_path.s, car_path.heading)
    return _Track(xy, heading, (s >= 0.0) & (s <= car_path.length), length, width)


def _collide(a: _Track, b: _Track, margin: float = 0.5) -> bool:
    """Whether the two cars' footprints (grown by `margin`) overlap at any time both are present
    (separating axis test on the four box axes)."""
    both = a.present & b.present
    if not both.any():
        return False
    offset = b.xy[both] - a.xy[both]
    overlapping = np.ones(int(both.sum()), dtype=bool)
    headings = (a.heading[both], b.heading[both])
    for axis_heading in (*headings, headings[0] + np.pi / 2, headings[1] + np.pi / 2):
        axis = np.stack([np.cos(axis_heading), np.sin(axis_heading)], axis=-1)
        radius = np.zeros(len(offset))
        for track, heading in ((a, headings[0]), (b, headings[1])):
            along = np.abs(np.cos(heading - axis_heading))
            across = np.abs(np.sin(heading - axis_heading))
            radius = radius + (track.length / 2 + margin) * along + (track.width / 2 + margin) * across
        overlapping &= np.abs(np.sum(offset * axis, axis=1)) < radius
    return bool(overlapping.any())


def _timed_car(
    car_path: CarPath,
    length: float,
    width: float,
    meet: float,
    ego_xy: npt.NDArray[np.float64],
    ego_times: npt.NDArray[np.float64],
    others: list[_Track],
    rng: np.random.Generator,
) -> tuple[float, float] | None:
    """(s0, speed) putting the car at its path's point nearest the ego's meeting point within ±9 s of the
    meeting time, never within `_EGO_CLEARANCE` + half its length of the ego's pose origin and never
    overlapping the cars of `others` while the ego looks (its track is then added to them); None when
    eight draws all fail."""
    meet_xy = ego_xy[int(np.argmin(np.abs(ego_times - meet)))]
    s_meet = float(car_path.s[int(np.argmin(np.linalg.norm(car_path.xy - meet_xy, axis=1)))])
    for _ in range(8):
        speed = float(rng.uniform(4.0, 13.0))
        s0 = s_meet - speed * (meet + float(rng.uniform(-9.0, 9.0)))
        track = _path_track(car_path, s0 + speed * ego_times, length, width)
        if not track.present.any():
            continue
        gap = np.linalg.norm(track.xy - ego_xy, axis=1)[track.present]
        if gap.min() <= length / 2 + _EGO_CLEARANCE:
            continue
        if any(_collide(track, other) for other in others):
            continue
        others.append(track)
        return s0, speed
    return None
