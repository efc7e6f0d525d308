"""Procedural street scenes along the ego trajectory.

The trajectory is turned into an arc-length parametrised street axis (`StreetPath`), extended 150 m past
both ends so the sensor never looks off the edge of the world. Everything is placed in street coordinates
(arc length `s`, lateral offset `u`, positive to the left) and rejected when it would stand too close to
any part of the trajectory (loops and crossings included):

- ground: a corridor mesh following the path (cambered road with dashed lane markings, gutters, kerbs,
  sidewalks) over a terrain heightfield of gentle hills;
- both sides, block by block: buildings made of several boxes with recessed and protruding facade parts,
  balconies, gaps between buildings; or walls, fences and hedges; or open ground with trees;
- street furniture: lamp poles with arms, sign poles, street trees (trunk + a cluster of ellipsoids as a
  noisy canopy), bushes, standing pedestrians, clutter (bins, benches, bollards, boxes);
- parked cars along the kerbs and moving cars in the lanes beside the ego lane with their own speeds;
- with `traffic="mixed"`, cross streets with cars crossing and turning (`dmlo.simulator.traffic`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from dmlo.simulator.primitives import (
    BUILDING,
    CAR,
    FENCE,
    LANE_MARKING,
    MOVING_CAR,
    OTHER_OBJECT,
    OTHER_STRUCTURE,
    PERSON,
    POLE,
    ROAD,
    SIDEWALK,
    TERRAIN,
    TRAFFIC_SIGN,
    TRUNK,
    VEGETATION,
    PrimitiveSet,
    yaw_pitch_rotation,
)
from dmlo.simulator.highway import add_highway_roadside
from dmlo.simulator.street import MovingCar, StreetLayout, StreetPath
from dmlo.simulator.traffic import TRAFFIC, PathCar, Traffic, add_cross_traffic
from dmlo.simulator.trajectory import FRAME_RATE_HZ

__all__ = ["TRAFFIC", "MovingCar", "PathCar", "StreetLayout", "StreetPath", "StreetScene", "generate_street"]

SCENES = ("street", "highway", "narrow", "stop-and-go")
TERRAIN_CELL = 5.0
TERRAIN_REACH = 140.0


@dataclass(frozen=True)
class EscortCar:
    """A car keeping pace with the ego, `offset` metres ahead along the axis (negative: behind) and
    `lateral` to its left: the lead car of a traffic jam, and the cars beside and behind the ego."""

    instance: int
    offset: float
    lateral: float
    length: float
    width: float
    height: float
    albedo: float


@dataclass
class StreetScene:
    """A generated street: static primitives, moving cars in the lanes along the axis, and (mixed traffic)
    cross streets with cars on their own paths."""

    path: StreetPath
    layout: StreetLayout
    static: PrimitiveSet
    moving_cars: list[MovingCar] = field(default_factory=list)
    traffic: Traffic | None = None
    escort_cars: list[EscortCar] = field(default_factory=list)

    @property
    def path_cars(self) -> list[PathCar]:
        return [] if self.traffic is None else self.traffic.cars

    def dynamic(self, time: float, ego_xy: npt.NDArray[np.float64], reach: float = 150.0) -> PrimitiveSet:
        """Primitives of the moving cars at `time` seconds within `reach` metres of the ego (cars that
        would overlap the ego car are left out)."""
        dynamic = PrimitiveSet()
        for car in self.moving_cars:
            s = car.s0 + car.direction * car.speed * time
            if not (0.0 <= s <= self.path.length):
                continue
            xy, z, heading = self.path.place(s, car.lateral)
            if float(np.linalg.norm(xy - ego_xy)) > reach:
                continue
            # Where the trajectory crosses itself a car of another pass could overlap the ego car: skip it.
            along = abs(np.cos(heading) * (ego_xy[0] - xy[0]) + np.sin(heading) * (ego_xy[1] - xy[1]))
            across = abs(-np.sin(heading) * (ego_xy[0] - xy[0]) + np.cos(heading) * (ego_xy[1] - xy[1]))
            if along < car.length / 2 + 2.5 and across < car.width / 2 + 1.5:
                continue
            pitch = -np.arctan(self.path.grade(s)) * car.direction
            yaw = heading if car.direction > 0 else heading + np.pi
            _add_car(
                dynamic,
                xy,
                z,
                yaw,
                pitch,
                car.length,
                car.width,
                car.height,
                MOVING_CAR,
                car.instance,
                car.albedo,
            )
        ego_s = self.path.ego_s(time) if self.escort_cars else 0.0
        for escort in self.escort_cars:
            xy, z, heading = self.path.place(ego_s + escort.offset, escort.lateral)
            pitch = -np.arctan(self.path.grade(ego_s + escort.offset))
            _add_car(dynamic, xy, z, heading, pitch, escort.length, escort.width, escort.height, MOVING_CAR,
                     escort.instance, escort.albedo)
        for path_car in self.path_cars:
            assert self.traffic is not None
            car_path = self.traffic.paths[path_car.path]
            s = path_car.s0 + path_car.speed * time
            if not (0.0 <= s <= car_path.length):
                continue
            xy, z, heading, pitch = car_path.at(s)
            if float(np.linalg.norm(xy - ego_xy)) > reach or _overlaps_ego(
                xy, heading, path_car.length, path_car.width, ego_xy
            ):
                continue
            _add_car(
                dynamic,
                xy,
                z,
                heading,
                pitch,
                path_car.length,
                path_car.width,
                path_car.height,
                MOVING_CAR,
                path_car.instance,
                path_car.albedo,
            )
        return dynamic


def _overlaps_ego(
    xy: npt.NDArray[np.float64], heading: float, length: float, width: float, ego_xy: npt.NDArray[np.float64]
) -> bool:
    """Whether a car at `xy` heading `heading` could overlap the ego car around `ego_xy`."""
    along = abs(np.cos(heading) * (ego_xy[0] - xy[0]) + np.sin(heading) * (ego_xy[1] - xy[1]))
    across = abs(-np.sin(heading) * (ego_xy[0] - xy[0]) + np.cos(heading) * (ego_xy[1] - xy[1]))
    return bool(along < length / 2 + 2.5 and across < width / 2 + 1.5)


def _add_car(
    prims: PrimitiveSet,
    xy: npt.NDArray[np.float64],
    ground_z: float,
    yaw: float,
    pitch: float,
    length: float,
    width: float,
    height: float,
    semantic: int,
    instance: int,
    albedo: float,
) -> None:
    """Body, cabin and four wheels as oriented boxes."""
    rot = yaw_pitch_rotation(yaw, pitch)
    origin = np.array([xy[0], xy[1], ground_z])

    def box(offset: tuple[float, float, float], half: tuple[float, float, float], a: float) -> None:
        prims.add_box(origin + rot @ np.asarray(offset), half, rot, semantic, instance, a)

    body_bottom, body_top = 0.3, 0.55 * height + 0.2
    box(
        (0.0, 0.0, (body_bottom + body_top) / 2),
        (length / 2, width / 2, (body_top - body_bottom) / 2),
        albedo,
    )
    cabin_len = 0.5 * length
    box(
        (-0.08 * length, 0.0, (body_top + height) / 2),
        (cabin_len / 2, width / 2 - 0.08, (height - body_top) / 2),
        0.08,
    )
    for fx in (0.32, -0.32):
        for fy in (0.5, -0.5):
            box((fx * length, fy * (width - 0.2), 0.33), (0.33, 0.1, 0.33), 0.05)


def generate_street(
    lidar_poses: npt.NDArray[np.float64],
    seed: int,
    mount_height: float = 1.73,
    traffic: str = "lanes",
    scene: str = "street",
    escorts: bool = False,
) -> StreetScene:
    """A street scene covering the whole trajectory `lidar_poses` ((N,4,4) `T_world_lidar`, one a frame at
    10 Hz), `mount_height` above the ground. `traffic`: `"lanes"` or `"mixed"` (see `simulate_sequence`).
    `scene`: `"street"` (buildings, furniture, parked cars) or `"highway"` (`dmlo.simulator.highway`: wide
    asphalt, guard rails, sparse sign poles and trees, fast traffic in the lanes beside the ego's).
    `"narrow"`: a residential street, the kerbs 3.5–5.5 m from the ego's path and cars parked along them,
    without the lanes of traffic beside the ego's (crossing traffic with `"mixed"`; escorts only ahead and
    behind). `"stop-and-go"`: a street in a traffic jam — the escorts (always on) fill the ego's lane and
    the lane on its right and stop and go with the ego, while the oncoming lane flows at 6–15 m/s (drive
    it with `generate_stop_and_go`). `escorts`: cars that keep pace with the ego (`EscortCar`), as in a
    traffic jam."""
    if traffic not in TRAFFIC:
        raise ValueError(f"traffic: unknown {traffic!r}; known: {', '.join(TRAFFIC)}")
    if scene not in SCENES:
        raise ValueError(f"scene: unknown {scene!r}; known: {', '.join(SCENES)}")
    if scene == "highway" and traffic != "lanes":
        raise ValueError("traffic: a highway has no cross streets; only 'lanes' traffic")
    rng = np.random.default_rng([seed, 0x5CE7E])
    path = StreetPath(lidar_poses, mount_height)
    jam = scene == "stop-and-go"
    escort_cars = _escort_cars(np.random.default_rng([seed, 0xE5C0]), 70000) if escorts or jam else []
    narrow = scene == "narrow"
    if narrow:  # no lane beside the ego's
        escort_cars = [car for car in escort_cars if abs(car.lateral) < 1.0]
    if jam:  # the queue fills the ego's lane and the one on its right; the oncoming lane flows
        escort_cars = [car for car in escort_cars if car.lateral < 1.0]
    if scene == "highway":
        highway = _highway(path, rng)
        highway.escort_cars = escort_cars
        return highway
    layout = StreetLayout(
        road_left=float(rng.uniform(3.5, 5.5) if narrow else rng.uniform(7.0, 9.0)),
        road_right=float(rng.uniform(3.5, 5.5) if narrow else rng.uniform(7.0, 8.5)),
        sidewalk_left=float(rng.uniform(2.0, 4.5)),
        sidewalk_right=float(rng.uniform(2.0, 4.5)),
        kerb=float(rng.uniform(0.1, 0.16)),
    )
    prims = PrimitiveSet()
    _add_corridor(prims, path, layout, rng)
    _add_terrain(prims, path, layout, rng)
    instances = iter(range(1, 65535))
    for side in (1, -1):
        _add_roadside(prims, path, layout, side, rng)
        _add_furniture(prims, path, layout, side, rng, instances)
        _add_parked_cars(prims, path, layout, side, rng, instances)
    lanes = () if narrow else _STREET_LANES[:1] if jam else _STREET_LANES
    moving = _moving_cars(path, layout, rng, instances, lanes=lanes)
    cross = None
    if traffic == "mixed":
        cross = add_cross_traffic(
            prims, path, layout, lidar_poses, FRAME_RATE_HZ, seed, instances, _car_size, moving
        )
    return StreetScene(
        path=path, layout=layout, static=prims, moving_cars=moving, traffic=cross, escort_cars=escort_cars
    )


# Where the escorts ride, relative to the ego: (offset along the axis, lateral offset), metres.
_ESCORT_PLACES = ((8.0, 0.0), (-9.0, 0.0), (1.5, 3.4), (-7.0, 3.4), (4.0, -3.4), (-4.5, -3.4))


def _escort_cars(rng: np.random.Generator, first_instance: int) -> list[EscortCar]:
    """A lead car and a follower in the ego's lane and two cars in each lane beside it, each placed a
    little off its slot so that no two drives look alike."""
    cars = []
    for k, (offset, lateral) in enumerate(_ESCORT_PLACES):
        length, width, height = _car_size(rng)
        cars.append(EscortCar(
            instance=first_instance + k,
            offset=offset + float(rng.uniform(-1.0, 1.0)) + float(np.sign(offset)) * length / 2,
            lateral=lateral + float(rng.uniform(-0.3, 0.3)),
            length=length, width=width, height=height,
            albedo=float(np.clip(rng.choice([0.08, 0.2, 0.35, 0.6]) + rng.normal(0, 0.03), 0.03, 1.0)),
        ))
    return cars


# Street lanes beside the ego's: (lateral offset, direction, speed range m/s), as `_moving_cars` takes them.
_STREET_LANES = ((3.3, -1, 6.0, 15.0), (-3.3, 1, 3.0, 17.0))
# Highway lanes beside the ego's: (lateral offset, direction, speed range m/s), as `_moving_cars` takes them.
_HIGHWAY_LANES = ((3.6, -1, 20.0, 32.0), (-3.6, 1, 18.0, 30.0), (7.2, -1, 20.0, 32.0))


def _highway(path: StreetPath, rng: np.random.Generator) -> StreetScene:
    layout = StreetLayout(
        road_left=float(rng.uniform(10.5, 12.5)),  # three lanes and a shoulder
        road_right=float(rng.uniform(10.5, 12.5)),
        sidewalk_left=1.0,  # a gravel verge
        sidewalk_right=1.0,
        kerb=0.02,
    )
    prims = PrimitiveSet()
    _add_corridor(prims, path, layout, rng)
    _add_terrain(prims, path, layout, rng)
    for side in (1, -1):
        add_highway_roadside(prims, path, layout, side, rng)
    moving = _moving_cars(path, layout, rng, iter(range(1, 65535)), lanes=_HIGHWAY_LANES)
    return StreetScene(path=path, layout=layout, static=prims, moving_cars=moving, traffic=None)


def _add_corridor(
    prims: PrimitiveSet, path: StreetPath, layout: StreetLayout, rng: np.random.Generator
) -> None:
    """Road, gutters, kerbs and sidewalks as triangle strips between cross-sections along the axis."""
    camber = 0.015
    lr, rr, k = layout.road_left, layout.road_right, layout.kerb
    # (lateral offset, height above the axis ground, class of the strip towards the next point)
    profile = [
        (-layout.outer(-1), k + 0.03 - 0.6, SIDEWALK),  # skirt down to the terrain
        (-layout.outer(-1), k + 0.03, SIDEWALK),
        (-rr, k, SIDEWALK),  # kerb top
        (-rr, -camber * rr, ROAD),  # gutter
        (-rr / 2, -camber * rr / 2, ROAD),
        (0.0, 0.0, ROAD),
        (lr / 2, -camber * lr / 2, ROAD),
        (lr, -camber * lr, SIDEWALK),
        (lr, k, SIDEWALK),
        (layout.outer(1), k + 0.03, SIDEWALK),
        (layout.outer(1), k + 0.03 - 0.6, SIDEWALK),
    ]
    offsets = np.array([p[0] for p in profile])
    heights = np.array([p[1] for p in profile])
    normal = np.column_stack([-np.sin(path.heading), np.cos(path.heading)])
    xy = path.xy[:, None, :] + offsets[None, :, None] * normal[:, None, :]
    z = path.ground_z[:, None] + heights[None, :]
    vertices = np.concatenate([xy, z[..., None]], axis=-1)  # (S, P, 3)
    road_albedo = float(rng.uniform(0.28, 0.4))
    walk_albedo = float(rng.uniform(0.3, 0.45))
    for j in range(len(profile) - 1):
        a, b = vertices[:-1, j], vertices[:-1, j + 1]
        c, d = vertices[1:, j], vertices[1:, j + 1]
        tris = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
        tris = tris[_non_degenerate(tris)]
        semantic = profile[j][2]
        albedo = road_albedo if semantic == ROAD else walk_albedo
        # Asphalt is patchy: vary albedo per triangle.
        prims.add_triangles(tris, semantic, 0, np.clip(albedo + rng.normal(0, 0.02, len(tris)), 0.02, 1.0))
    # Dashed lane markings 1 mm above the road, between the ego lane and the neighbouring lanes.
    for u in (1.75, -1.75):
        for s0 in np.arange(rng.uniform(0, 9), path.length - 3.0, 9.0):
            s = np.array([s0, s0 + 3.0])
            pts = []
            for du in (-0.07, 0.07):
                for si in s:
                    p, gz, _ = path.place(si, u + du)
                    pts.append([p[0], p[1], gz - camber * abs(u + du) + 0.002])
            quad = np.asarray(pts)
            tris = np.stack([quad[[0, 1, 3]], quad[[0, 3, 2]]])
            tris = tris[_non_degenerate(tris)]
            if len(tris):
                prims.add_triangles(tris, LANE_MARKING, 0, 0.9)


def _non_degenerate(tris: npt.NDArray[np.float64]) -> npt.NDArray[np.bool_]:
    area = np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    return area > 1e-6


def _add_terrain(
    prims: PrimitiveSet, path: StreetPath, layout: StreetLayout, rng: np.random.Generator
) -> None:
    """A heightfield of gentle hills around the street, kept below the corridor near the axis."""
    lo = path.xy.min(0) - TERRAIN_REACH
    hi = path.xy.max(0) + TERRAIN_REACH
    gx = np.arange(lo[0], hi[0] + TERRAIN_CELL, TERRAIN_CELL)
    gy = np.arange(lo[1], hi[1] + TERRAIN_CELL, TERRAIN_CELL)
    grid = np.stack(np.meshgrid(gx, gy, indexing="ij"), axis=-1)  # (X, Y, 2)
    distance, nearest = path.distance(grid)
    rel = grid - path.xy[nearest]
    heading = path.heading[nearest]
    side = np.where(-np.sin(heading) * rel[..., 0] + np.cos(heading) * rel[..., 1] >= 0, 1, -1)
    outer = np.where(side > 0, layout.outer(1), layout.outer(-1))
    waves = [
        (rng.uniform(0.2, 0.6), rng.uniform(40, 120), rng.uniform(0, 2 * np.pi, 2), rng.uniform(0, 2 * np.pi))
        for _ in range(4)
    ]
    hills = sum(
        a * np.sin((grid[..., 0] * np.cos(th[0]) + grid[..., 1] * np.sin(th[0])) * 2 * np.pi / w + ph)
        for a, w, th, ph in waves
    )
    rise = np.clip((distance - outer - 3.0) / 40.0, 0.0, 1.0)  # flat next to the sidewalk, hills further out
    z = path.ground_z[nearest] + layout.kerb + np.where(distance < outer + 0.5, -0.5, 0.0) + rise * hills
    z = z + rng.normal(0, 0.03, z.shape)
    keep = distance < TERRAIN_REACH
    vertices = np.concatenate([grid, z[..., None]], axis=-1)
    a, b, c, d = vertices[:-1, :-1], vertices[1:, :-1], vertices[:-1, 1:], vertices[1:, 1:]
    cell_keep = keep[:-1, :-1] & keep[1:, :-1] & keep[:-1, 1:] & keep[1:, 1:]
    # Cells entirely under the corridor mesh are never seen: leave them out.
    hidden = distance < outer - 1.0
    cell_keep &= ~(hidden[:-1, :-1] & hidden[1:, :-1] & hidden[:-1, 1:] & hidden[1:, 1:])
    tris = np.concatenate([np.stack([a, b, d], -2)[cell_keep], np.stack([a, d, c], -2)[cell_keep]])
    prims.add_triangles(
        tris, TERRAIN, 0, np.clip(rng.uniform(0.3, 0.45) + rng.normal(0, 0.04, len(tris)), 0.05, 1)
    )


def _clear(path: StreetPath, xy: npt.ArrayLike, clearance: float) -> bool:
    """Whether every point is at least `clearance` from the trajectory axis (all passes)."""
    distance, _ = path.distance(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
    return bool(distance.min() >= clearance)


def _footprint(
    center: npt.NDArray[np.float64], yaw: float, half_long: float, half_lat: float
) -> npt.NDArray[np.float64]:
    c, s = np.cos(yaw), np.sin(yaw)
    pts = []
    for fx in np.linspace(-1, 1, 5):
        for fy in (-1.0, 1.0):
            pts.append(center + fx * half_long * np.array([c, s]) + fy * half_lat * np.array([-s, c]))
    return np.asarray(pts)


def _add_roadside(
    prims: PrimitiveSet, path: StreetPath, layout: StreetLayout, side: int, rng: np.random.Generator
) -> None:
    """Block by block beside the sidewalk: buildings, walls/fences/hedges, or open ground with trees."""
    clearance = min(layout.road_left, layout.road_right) + 1.5
    s = float(rng.uniform(0, 10))
    building_albedo = float(rng.uniform(0.1, 0.35))
    while s < path.length:
        kind = rng.choice(["building", "fence", "open"], p=[0.72, 0.14, 0.14])
        length = float(rng.uniform(10.0, 35.0) if kind == "building" else rng.uniform(10.0, 40.0))
        front = layout.outer(side) + float(rng.uniform(0.5, 6.0))
        if kind == "building":
            depth = _add_building(prims, path, side, s, length, front, clearance, building_albedo, rng)
            if rng.random() < 0.5:  # a second row behind: structure at long range
                back = front + depth + float(rng.uniform(4.0, 30.0))
                _add_building(
                    prims,
                    path,
                    side,
                    s + float(rng.uniform(-5, 5)),
                    length,
                    back,
                    clearance,
                    building_albedo,
                    rng,
                )
            gap = float(rng.uniform(0.0, 1.5) if rng.random() < 0.6 else rng.uniform(3.0, 14.0))
        elif kind == "fence":
            _add_fence(prims, path, side, s, length, front, clearance, rng)
            gap = float(rng.uniform(0.0, 5.0))
        else:
            for _ in range(int(rng.integers(0, 5))):
                ts = s + float(rng.uniform(0, length))
                xy, z, _ = path.place(ts, side * (front + float(rng.uniform(1.0, 25.0))))
                if _clear(path, xy, clearance + 2.0):
                    _add_tree(prims, xy, z + layout.kerb, rng)
            gap = 0.0
        s += length + gap


def _add_building(
    prims: PrimitiveSet,
    path: StreetPath,
    side: int,
    s: float,
    length: float,
    front: float,
    clearance: float,
    albedo: float,
    rng: np.random.Generator,
) -> float:
    """Adds one building of 1–4 facade parts starting at arc length `s`; returns its depth."""
    base_height = float(rng.uniform(6.0, 24.0))
    depth = float(rng.uniform(8.0, 18.0))
    parts = int(rng.integers(1, 5))
    cuts = np.sort(rng.uniform(0, length, parts - 1))
    edges = np.concatenate([[0.0], cuts, [length]])
    facade_albedo = float(np.clip(albedo + rng.normal(0, 0.08), 0.03, 0.9))
    windows = (
        (float(rng.uniform(2.2, 4.5)), float(rng.uniform(2.8, 3.6)), float(rng.uniform(0.3, 4.0)))
        if rng.random() < 0.8
        else (0.0, 0.0, 0.0)
    )
    for a, b in zip(edges[:-1], edges[1:]):
        if b - a < 2.0:
            continue
        mid = s + (a + b) / 2
        recess = 0.0 if rng.random() < 0.5 else float(rng.uniform(-0.8, 2.5))  # negative: protruding bay
        height = max(3.5, base_height + float(rng.uniform(-2.0, 3.0)))
        u_center = side * (front + recess + depth / 2)
        xy, z, heading = path.place(mid, u_center)
        half = np.array([(b - a) / 2, depth / 2, (height + 1.0) / 2])
        if not _clear(path, _footprint(xy, heading, half[0], half[1]), clearance):
            continue
        rot = yaw_pitch_rotation(heading)
        # Boxes reach 1 m below the ground (no gap on slopes); the window grid counts from the box bottom.
        prims.add_box([xy[0], xy[1], z - 1.0 + half[2]], half, rot, BUILDING, 0, facade_albedo, windows)
        # Balconies / ledges sticking out of the facade on some parts.
        if rng.random() < 0.35 and b - a > 5.0:
            floors = int((height - 3.0) // 3.0)
            for floor in range(1, floors + 1):
                bxy, _, _ = path.place(mid, side * (front + recess - 0.6))
                prims.add_box(
                    [bxy[0], bxy[1], z + 3.0 * floor],
                    [min(2.5, (b - a) / 3), 0.6, 0.08],
                    rot,
                    BUILDING,
                    0,
                    facade_albedo,
                )
    return depth


def _add_fence(
    prims: PrimitiveSet,
    path: StreetPath,
    side: int,
    s: float,
    length: float,
    front: float,
    clearance: float,
    rng: np.random.Generator,
) -> None:
    """A wall, fence or hedge in pieces of ≤ 6 m so it follows curves."""
    kind = rng.choice(["wall", "fence", "hedge"])
    height = float(rng.uniform(0.8, 2.5))
    thickness = {"wall": 0.3, "fence": 0.06, "hedge": 0.9}[kind]
    semantic = {"wall": OTHER_STRUCTURE, "fence": FENCE, "hedge": VEGETATION}[kind]
    albedo = float(rng.uniform(0.3, 0.6))
    pieces = max(1, int(np.ceil(length / 6.0)))
    step = length / pieces
    for k in range(pieces):
        mid = s + (k + 0.5) * step
        xy, z, heading = path.place(mid, side * (front + thickness / 2))
        half = np.array([step / 2, thickness / 2, (height + 0.5) / 2])
        if not _clear(path, _footprint(xy, heading, half[0], half[1]), clearance):
            continue
        prims.add_box(
            [xy[0], xy[1], z - 0.5 + half[2]], half, yaw_pitch_rotation(heading), semantic, 0, albedo
        )
    if kind == "fence":  # posts
        for k in range(pieces + 1):
            xy, z, _ = path.place(s + k * step, side * front)
            if _clear(path, xy, clearance):
                prims.add_cylinder([xy[0], xy[1], z - 0.3], height + 0.4, 0.05, FENCE, 0, albedo)


def _add_tree(
    prims: PrimitiveSet, xy: npt.NDArray[np.float64], ground: float, rng: np.random.Generator
) -> None:
    trunk_height = float(rng.uniform(1.8, 3.5))
    radius = float(rng.uniform(0.1, 0.25))
    prims.add_cylinder(
        [xy[0], xy[1], ground - 0.2], trunk_height + 0.6, radius, TRUNK, 0, float(rng.uniform(0.25, 0.4))
    )
    crown = float(rng.uniform(1.5, 3.5))
    center_z = ground + trunk_height + crown * 0.7
    for _ in range(int(rng.integers(3, 7))):
        offset = rng.normal(0, 0.35 * crown, 3) * np.array([1, 1, 0.6])
        radii = crown * rng.uniform(0.5, 0.9) * np.array([1.0, 1.0, rng.uniform(0.7, 1.0)])
        prims.add_ellipsoid(
            [xy[0] + offset[0], xy[1] + offset[1], center_z + offset[2]],
            radii,
            VEGETATION,
            0,
            float(rng.uniform(0.2, 0.45)),
        )


def _add_furniture(
    prims: PrimitiveSet,
    path: StreetPath,
    layout: StreetLayout,
    side: int,
    rng: np.random.Generator,
    instances: Iterator[int],
) -> None:
    """Lamp poles, sign poles, street trees, bushes, standing pedestrians and clutter on the sidewalk."""
    road = layout.road(side)
    walk = layout.outer(side) - road
    clearance = min(layout.road_left, layout.road_right) - 0.5
    ground_offset = layout.kerb
    # Lamp poles with an arm over the road.
    s = float(rng.uniform(0, 30))
    while s < path.length:
        xy, z, heading = path.place(s, side * (road + 0.6))
        if _clear(path, xy, clearance + 0.5):
            height = float(rng.uniform(5.0, 9.0))
            albedo = float(rng.uniform(0.35, 0.55))
            prims.add_cylinder(
                [xy[0], xy[1], z], height + ground_offset, float(rng.uniform(0.07, 0.14)), POLE, 0, albedo
            )
            arm_xy, _, _ = path.place(s, side * (road + 0.6 - 0.9))
            prims.add_box(
                [arm_xy[0], arm_xy[1], z + height],
                [0.9, 0.06, 0.06],
                yaw_pitch_rotation(heading + np.pi / 2),
                POLE,
                0,
                albedo,
            )
        s += float(rng.uniform(18.0, 40.0))
    # Sign poles with a retro-reflective plate.
    s = float(rng.uniform(0, 60))
    while s < path.length:
        xy, z, heading = path.place(s, side * (road + 0.4))
        if _clear(path, xy, clearance + 0.3):
            prims.add_cylinder([xy[0], xy[1], z], 2.0 + ground_offset, 0.04, POLE, 0, 0.5)
            prims.add_box(
                [xy[0], xy[1], z + 2.4],
                [0.03, 0.35, 0.35],
                yaw_pitch_rotation(heading),
                TRAFFIC_SIGN,
                0,
                0.95,
            )
        s += float(rng.uniform(40.0, 120.0))
    # Street trees in tree-lined stretches.
    s = 0.0
    while s < path.length:
        stretch = float(rng.uniform(30.0, 80.0))
        if rng.random() < 0.5:
            t = s + float(rng.uniform(0, 8))
            while t < s + stretch:
                xy, z, _ = path.place(t, side * (road + walk * float(rng.uniform(0.45, 0.75))))
                if _clear(path, xy, clearance + 1.0):
                    _add_tree(prims, xy, z + ground_offset, rng)
                t += float(rng.uniform(7.0, 15.0))
        s += stretch
    # Bushes between the sidewalk and the buildings.
    s = float(rng.uniform(0, 15))
    while s < path.length:
        xy, z, _ = path.place(s, side * (road + walk + float(rng.uniform(0.5, 2.5))))
        if _clear(path, xy, clearance + 1.0):
            radius = float(rng.uniform(0.4, 1.2))
            for _ in range(int(rng.integers(1, 4))):
                offset = rng.normal(0, 0.4 * radius, 2)
                prims.add_ellipsoid(
                    [xy[0] + offset[0], xy[1] + offset[1], z + ground_offset + 0.6 * radius],
                    [radius, radius, 0.8 * radius],
                    VEGETATION,
                    0,
                    float(rng.uniform(0.35, 0.6)),
                )
        s += float(rng.uniform(5.0, 40.0))
    # Pedestrians standing on the sidewalk: legs and torso as a cylinder, head as a sphere.
    s = float(rng.uniform(0, 30))
    while s < path.length:
        xy, z, _ = path.place(s, side * (road + float(rng.uniform(0.5, max(0.6, walk - 0.3)))))
        if _clear(path, xy, clearance):
            height = float(rng.uniform(1.55, 1.9))
            person = next(instances)
            body_radius = float(rng.uniform(0.17, 0.24))
            prims.add_cylinder(
                [xy[0], xy[1], z + ground_offset], height - 0.22, body_radius, PERSON, person, 0.3
            )
            prims.add_ellipsoid(
                [xy[0], xy[1], z + ground_offset + height - 0.11], [0.1, 0.1, 0.12], PERSON, person, 0.25
            )
        s += float(rng.uniform(15.0, 80.0))
    # Clutter: bins, bollards, benches, boxes.
    s = float(rng.uniform(0, 10))
    while s < path.length:
        xy, z, heading = path.place(s, side * (road + float(rng.uniform(0.3, max(0.4, walk - 0.4)))))
        z += ground_offset
        if _clear(path, xy, clearance):
            item = rng.choice(["bin", "bollard", "bench", "box"])
            albedo = float(rng.uniform(0.15, 0.6))
            if item == "bin":
                prims.add_cylinder(
                    [xy[0], xy[1], z], float(rng.uniform(0.8, 1.2)), 0.3, OTHER_OBJECT, 0, albedo
                )
            elif item == "bollard":
                prims.add_cylinder([xy[0], xy[1], z], 0.9, 0.08, OTHER_OBJECT, 0, albedo)
            else:
                half = [0.9, 0.3, 0.25] if item == "bench" else list(rng.uniform(0.2, 0.7, 3))
                yaw = heading if item == "bench" else float(rng.uniform(0, np.pi))
                prims.add_box(
                    [xy[0], xy[1], z + half[2]], half, yaw_pitch_rotation(yaw), OTHER_OBJECT, 0, albedo
                )
        s += float(rng.uniform(6.0, 30.0))


def _car_size(rng: np.random.Generator) -> tuple[float, float, float]:
    if rng.random() < 0.12:  # van
        return float(rng.uniform(4.8, 5.6)), float(rng.uniform(1.9, 2.1)), float(rng.uniform(1.9, 2.4))
    return float(rng.uniform(3.7, 4.9)), float(rng.uniform(1.65, 1.9)), float(rng.uniform(1.35, 1.6))


def _add_parked_cars(
    prims: PrimitiveSet,
    path: StreetPath,
    layout: StreetLayout,
    side: int,
    rng: np.random.Generator,
    instances: Iterator[int],
) -> None:
    occupancy = float(rng.uniform(0.15, 0.6))
    s = float(rng.uniform(0, 10))
    while s < path.length:
        stretch = float(rng.uniform(20.0, 60.0))
        if rng.random() < occupancy:
            t = s
            while t < s + stretch:
                length, width, height = _car_size(rng)
                u = side * (layout.road(side) - width / 2 - float(rng.uniform(0.15, 0.4)))
                xy, z, heading = path.place(t + length / 2, u)
                yaw = heading + float(rng.normal(0, 0.03)) + (np.pi if rng.random() < 0.5 else 0.0)
                if _clear(path, _footprint(xy, heading, length / 2, width / 2), 2.2):
                    albedo = float(rng.choice([0.08, 0.2, 0.35, 0.6]) + rng.normal(0, 0.03))
                    _add_car(prims, xy, z, yaw, 0.0, length, width, height, CAR, next(instances), albedo)
                t += length + float(rng.uniform(0.6, 3.0))
        s += stretch + float(rng.uniform(5.0, 20.0))


def _moving_cars(
    path: StreetPath,
    layout: StreetLayout,
    rng: np.random.Generator,
    instances: Iterator[int],
    lanes: tuple[tuple[float, int, float, float], ...],
) -> list[MovingCar]:
    """Cars in `lanes` (lateral offset, direction, speed range m/s) along the ego's path."""
    cars = []
    for lateral, direction, v_min, v_max in lanes:
        count = int(rng.poisson(2.0 * path.length / 100.0))
        for _ in range(count):
            length, width, height = _car_size(rng)
            cars.append(
                MovingCar(
                    instance=next(instances),
                    s0=float(rng.uniform(0, path.length)),
                    speed=float(rng.uniform(v_min, v_max)),
                    direction=direction,
                    lateral=lateral,
                    length=length,
                    width=width,
                    height=height,
                    albedo=float(
                        np.clip(rng.choice([0.08, 0.2, 0.35, 0.6]) + rng.normal(0, 0.03), 0.03, 1.0)
                    ),
                )
            )
    return cars
