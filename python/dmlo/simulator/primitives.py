"""Collects simulator primitives with their semantic class, instance id and albedo, and turns them into a
`dmlo_rs.RayScene` whose hit indices map back to those attributes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from dmlo_rs import RayScene

# SemanticKITTI class ids used by the simulator.
CAR = 10
PERSON = 30
ROAD = 40
SIDEWALK = 48
BUILDING = 50
FENCE = 51
OTHER_STRUCTURE = 52
LANE_MARKING = 60
VEGETATION = 70
TRUNK = 71
TERRAIN = 72
POLE = 80
TRAFFIC_SIGN = 81
OTHER_OBJECT = 99
MOVING_CAR = 252


def yaw_pitch_rotation(yaw: float, pitch: float = 0.0) -> npt.NDArray[np.float64]:
    """Rotation about z by `yaw`, then about the new y by `pitch` (radians)."""
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    return np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]]) @ np.array(
        [[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]]
    )


@dataclass
class SceneAttributes:
    """Per-primitive attributes in `RayScene` numbering (triangles, boxes, cylinders, ellipsoids)."""

    semantic: npt.NDArray[np.uint32]
    instance: npt.NDArray[np.uint32]
    albedo: npt.NDArray[np.float32]
    # (P,3) window grid of facades: horizontal spacing, floor height, depth of the room behind (0 = none).
    windows: npt.NDArray[np.float64]
    # (P,15) box parameters as `RayScene` takes them (NaN for other primitives), to find facade coordinates.
    boxes: npt.NDArray[np.float64]

    @staticmethod
    def concatenate(parts: list[SceneAttributes]) -> SceneAttributes:
        """Attributes of scenes whose primitive numbers follow each other."""
        return SceneAttributes(
            semantic=np.concatenate([p.semantic for p in parts]),
            instance=np.concatenate([p.instance for p in parts]),
            albedo=np.concatenate([p.albedo for p in parts]),
            windows=np.concatenate([p.windows for p in parts]),
            boxes=np.concatenate([p.boxes for p in parts]),
        )


class PrimitiveSet:
    """Accumulates primitives of the four kinds, each with (class, instance, albedo)."""

    def __init__(self) -> None:
        self._params: dict[str, list[npt.NDArray[np.float64]]] = {k: [] for k in _KINDS}
        self._attrs: dict[str, list[tuple[int, int, float]]] = {k: [] for k in _KINDS}
        self._windows: dict[str, list[tuple[float, float, float]]] = {k: [] for k in _KINDS}

    def __len__(self) -> int:
        return sum(len(v) for v in self._attrs.values())

    def add_triangles(
        self,
        triangles: npt.NDArray[np.float64],
        semantic: int,
        instance: int,
        albedo: float | npt.NDArray[np.float64],
    ) -> None:
        """`triangles` (N, 3, 3); `albedo` one value or one per triangle."""
        triangles = np.asarray(triangles, dtype=np.float64).reshape(-1, 3, 3)
        albedos = np.broadcast_to(np.asarray(albedo, dtype=np.float64), (len(triangles),))
        self._params["triangles"].extend(triangles)
        self._attrs["triangles"].extend((semantic, instance, float(a)) for a in albedos)
        self._windows["triangles"].extend([(0.0, 0.0, 0.0)] * len(albedos))

    def add_box(
        self,
        center: npt.ArrayLike,
        half_extents: npt.ArrayLike,
        rotation: npt.NDArray[np.float64],
        semantic: int,
        instance: int,
        albedo: float,
        windows: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None:
        """`windows`: (horizontal spacing, floor height, room depth) of a window grid on the side faces."""
        row = np.concatenate(
            [np.asarray(center, float), np.asarray(rotation, float).ravel(), np.asarray(half_extents, float)]
        )
        self._params["boxes"].append(row)
        self._attrs["boxes"].append((semantic, instance, albedo))
        self._windows["boxes"].append(windows)

    def add_cylinder(
        self, base: npt.ArrayLike, height: float, radius: float, semantic: int, instance: int, albedo: float
    ) -> None:
        self._params["cylinders"].append(np.array([*np.asarray(base, float), height, radius]))
        self._attrs["cylinders"].append((semantic, instance, albedo))
        self._windows["cylinders"].append((0.0, 0.0, 0.0))

    def add_ellipsoid(
        self, center: npt.ArrayLike, radii: npt.ArrayLike, semantic: int, instance: int, albedo: float
    ) -> None:
        self._params["ellipsoids"].append(
            np.concatenate([np.asarray(center, float), np.asarray(radii, float)])
        )
        self._attrs["ellipsoids"].append((semantic, instance, albedo))
        self._windows["ellipsoids"].append((0.0, 0.0, 0.0))

    def parameters(self, kind: str) -> npt.NDArray[np.float64]:
        """Parameters of one kind (`triangles`, `boxes`, `cylinders`, `ellipsoids`) as `arrays` gives them,
        empty with the right trailing shape when there are none."""
        if not self._params[kind]:
            return np.zeros((0, *_SHAPES[kind][1:]))
        return np.asarray(self._params[kind], dtype=np.float64).reshape(_SHAPES[kind])

    def semantics(self, kind: str) -> npt.NDArray[np.uint32]:
        """The class of every primitive of `kind`."""
        return np.asarray([a[0] for a in self._attrs[kind]], dtype=np.uint32)

    def drop(self, kind: str, remove: npt.NDArray[np.bool_]) -> None:
        """Removes the primitives of `kind` where `remove` (one flag per primitive of that kind) is set."""
        if len(remove) != len(self._params[kind]):
            raise ValueError(f"remove: {len(remove)} flags for {len(self._params[kind])} {kind}")
        keep = [i for i, flag in enumerate(remove) if not flag]
        self._params[kind] = [self._params[kind][i] for i in keep]
        self._attrs[kind] = [self._attrs[kind][i] for i in keep]
        self._windows[kind] = [self._windows[kind][i] for i in keep]

    def arrays(self) -> dict[str, npt.NDArray[np.float64] | None]:
        """Primitive parameter arrays as `RayScene` takes them (None for an empty kind)."""
        return {
            kind: (
                np.asarray(self._params[kind], dtype=np.float64).reshape(_SHAPES[kind])
                if self._params[kind]
                else None
            )
            for kind in _KINDS
        }

    def build(self) -> tuple[RayScene, SceneAttributes]:
        """The ray-casting scene and the attributes of its primitives, in its numbering."""
        attrs = [a for kind in _KINDS for a in self._attrs[kind]]
        table = np.asarray(attrs, dtype=np.float64).reshape(-1, 3)
        counts = {kind: len(self._attrs[kind]) for kind in _KINDS}
        boxes = np.full((len(table), 15), np.nan)
        if counts["boxes"]:
            boxes[counts["triangles"] : counts["triangles"] + counts["boxes"]] = np.asarray(
                self._params["boxes"]
            )
        attributes = SceneAttributes(
            semantic=table[:, 0].astype(np.uint32),
            instance=table[:, 1].astype(np.uint32),
            albedo=table[:, 2].astype(np.float32),
            windows=np.asarray([w for kind in _KINDS for w in self._windows[kind]], dtype=np.float64).reshape(
                -1, 3
            ),
            boxes=boxes,
        )
        return RayScene(**self.arrays()), attributes


_KINDS = ("triangles", "boxes", "cylinders", "ellipsoids")
_SHAPES = {"triangles": (-1, 3, 3), "boxes": (-1, 15), "cylinders": (-1, 5), "ellipsoids": (-1, 6)}
