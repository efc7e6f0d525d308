"""A real HDL-64E's reflectance, calibrated on the statistics of real KITTI scans, and those statistics.

The simulator's own measurement model (`dmlo.simulator.sensor`) gives every return
`albedo · (0.55 + 0.45 cos θ)` plus noise: even lasers, no fade with range, no zeros. A real KITTI scan's
reflectance (issue 52) differs in three ways this module models, on top of that value `s`:

- **per-laser gain and offset** and **a fade with range**: `g_l · s · 1 / (1 + (range / range_scale)^range_power)
  − o_l`; with the floor below it turns far returns to 0 (real scans: about a quarter of the returns at
  30–40 m read 0, half at 40–60 m, nearly all beyond 60 m), and a positive offset makes the dark returns of
  a laser read 0, as some of the real lasers do at every range;
- **grazing incidence**: that `· clip((cos θ − grazing_cos) / grazing_width, 0, 1)` (the road far ahead);
- **a detection floor**: what falls below `zero_below` reads 0 (real scans hold few values just above 0);
- rounded to KITTI's 0.01 steps, clipped to [0, 1].

`ReflectanceModel.apply` maps the simulator's values to these; `simulate_sequence(..., reflectance="kitti")`
applies `KITTI_HDL64E` (the table in `hdl64e_kitti_reflectance.json`, written by
`benchmarks/reflectance_stats.py --calibrate` from the shared real scans' per-row histograms; never from
their poses). Point positions do not change: the model only rewrites the reflectance of the returns the
simulator keeps, with a random stream of its own.

The statistics (`row_statistics`) are per row of the KITTI cylinder image (0.4° of elevation, row 0 at
+2°): the rows the network reads, and a laser ring each (two in the upper block, where the lasers are 1/3°
apart), defined the same way for real and simulated scans.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

TABLE = Path(__file__).with_name("hdl64e_kitti_reflectance.json")

FOV_UP_DEG = 2.0  # the KITTI cylinder image's top edge (`dmlo_rs.CylinderConfig.kitti()`)
ROW_DEG = 0.4
ROWS = 68  # the full image's rows (26.9° / 0.4°); the network's input is the 64 below the top 2 (crop)
BINS = np.linspace(0.0, 1.0, 102) - 0.005  # one bin per KITTI step 0.00 … 1.00
QUANTILES = (0.1, 0.25, 0.5, 0.75, 0.9)


@dataclass(frozen=True)
class ReflectanceModel:
    """Per-laser gains and offsets, a fade with range, a fade at grazing incidence, KITTI's 0.01 steps."""

    gains: tuple[float, ...]
    offsets: tuple[float, ...]
    range_scale: float = 1e9
    range_power: float = 2.0
    grazing_cos: float = 0.0
    grazing_width: float = 1e-9
    zero_below: float = 0.0
    step: float = 0.01

    def __post_init__(self) -> None:
        if len(self.gains) != len(self.offsets):
            raise ValueError(f"gains and offsets: one per laser, got {len(self.gains)} and {len(self.offsets)}")
        if self.range_scale <= 0 or self.grazing_width <= 0 or self.step < 0:
            raise ValueError("range_scale and grazing_width must be > 0, step >= 0")

    @property
    def lasers(self) -> int:
        return len(self.gains)

    def range_fade(self, ranges: npt.ArrayLike) -> npt.NDArray[np.float64]:
        return 1.0 / (1.0 + (np.asarray(ranges, dtype=np.float64) / self.range_scale) ** self.range_power)

    def grazing_fade(self, cos_incidence: npt.ArrayLike) -> npt.NDArray[np.float64]:
        cos = np.asarray(cos_incidence, dtype=np.float64)
        return np.clip((cos - self.grazing_cos) / self.grazing_width, 0.0, 1.0)

    def apply(
        self,
        reflectance: npt.ArrayLike,
        ranges: npt.ArrayLike,
        cos_incidence: npt.ArrayLike,
        lasers: npt.ArrayLike,
    ) -> npt.NDArray[np.float64]:
        """The real sensor's reflectance for returns the simulator measured as `reflectance` (its own model),
        at `ranges` (m), `cos_incidence` and from `lasers` (0 = the top one)."""
        lasers = np.asarray(lasers, dtype=np.int64)
        if len(lasers) and (lasers.min() < 0 or lasers.max() >= self.lasers):
            raise ValueError(f"lasers: 0 … {self.lasers - 1}, got {lasers.min()} … {lasers.max()}")
        gains = np.asarray(self.gains)[lasers]
        offsets = np.asarray(self.offsets)[lasers]
        value = gains * np.asarray(reflectance, dtype=np.float64) * self.range_fade(ranges) - offsets
        value = value * self.grazing_fade(cos_incidence)  # after the offset: grazing returns read 0 on every laser
        value = np.where(value < self.zero_below, 0.0, np.clip(value, 0.0, 1.0))
        if self.step > 0:
            value = np.round(value / self.step) * self.step
        return np.clip(value, 0.0, 1.0)

    def to_dict(self) -> dict[str, object]:
        return {key: (list(value) if isinstance(value, tuple) else value) for key, value in asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> ReflectanceModel:
        fields = dict(values)
        fields["gains"] = tuple(float(v) for v in fields["gains"])
        fields["offsets"] = tuple(float(v) for v in fields["offsets"])
        known = set(cls.__dataclass_fields__)
        return cls(**{k: v for k, v in fields.items() if k in known})

    def save(self, path: str | Path, extra: dict[str, object] | None = None) -> None:
        Path(path).write_text(json.dumps({**self.to_dict(), **(extra or {})}, indent=1) + "\n")

    @classmethod
    def load(cls, path: str | Path = TABLE) -> ReflectanceModel:
        return cls.from_dict(json.loads(Path(path).read_text()))


def kitti_hdl64e() -> ReflectanceModel:
    """The calibrated table for the simulator's HDL-64E (`hdl64e_kitti_reflectance.json`)."""
    return ReflectanceModel.load(TABLE)


REFLECTANCE_MODELS = ("simple", "kitti")
"""`simulate_sequence(reflectance=…)`: the simulator's own model (byte for byte as before) or the calibrated one."""


# -- statistics ---------------------------------------------------------------------------------------


def image_rows(points: npt.NDArray[np.floating]) -> npt.NDArray[np.int64]:
    """Each point's row in the KITTI cylinder image (0.4° of elevation, row 0 just below +2°); rows outside
    0 … 67 are outside the image."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    elevation = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    return np.floor((FOV_UP_DEG - elevation) / ROW_DEG).astype(np.int64)


@dataclass
class RowStatistics:
    """Per image row (ROWS): point count, reflectance histogram (KITTI's 101 steps, normalised), quantiles
    (`QUANTILES`), mean, share of zeros; and the same by range band (`RANGE_BANDS`)."""

    counts: npt.NDArray[np.int64]
    histograms: npt.NDArray[np.float64]  # (ROWS, 101)
    quantiles: npt.NDArray[np.float64]  # (ROWS, len(QUANTILES)); NaN for empty rows
    means: npt.NDArray[np.float64]
    zeros: npt.NDArray[np.float64]
    band_histograms: npt.NDArray[np.float64]  # (len(RANGE_BANDS), 101)
    band_counts: npt.NDArray[np.int64]

    @property
    def medians(self) -> npt.NDArray[np.float64]:
        return self.quantiles[:, QUANTILES.index(0.5)]


RANGE_BANDS = ((0, 5), (5, 10), (10, 15), (15, 20), (20, 30), (30, 40), (40, 60), (60, 80), (80, 200))


def _histogram(values: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    counts, _ = np.histogram(np.clip(values, 0.0, 1.0), bins=BINS)
    return counts / max(1, counts.sum())


def row_statistics(scans: list[npt.NDArray[np.floating]]) -> RowStatistics:
    """`RowStatistics` of the reflectance of `scans` (N×4, x y z reflectance in [0, 1]), pooled."""
    points = np.concatenate([np.asarray(scan, dtype=np.float64)[:, :4] for scan in scans])
    rows = image_rows(points)
    inside = (rows >= 0) & (rows < ROWS)
    points, rows = points[inside], rows[inside]
    reflectance = points[:, 3]
    ranges = np.linalg.norm(points[:, :3], axis=1)
    counts = np.bincount(rows, minlength=ROWS)
    histograms = np.zeros((ROWS, len(BINS) - 1))
    quantiles = np.full((ROWS, len(QUANTILES)), np.nan)
    means = np.full(ROWS, np.nan)
    zeros = np.full(ROWS, np.nan)
    order = np.argsort(rows, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)])
    for row in range(ROWS):
        values = reflectance[order[starts[row] : starts[row + 1]]]
        if len(values) == 0:
            continue
        histograms[row] = _histogram(values)
        quantiles[row] = np.quantile(values, QUANTILES)
        means[row] = values.mean()
        zeros[row] = float(np.mean(values == 0))
    bands = np.zeros((len(RANGE_BANDS), len(BINS) - 1))
    band_counts = np.zeros(len(RANGE_BANDS), dtype=np.int64)
    for index, (near, far) in enumerate(RANGE_BANDS):
        inside_band = (ranges >= near) & (ranges < far)
        band_counts[index] = int(inside_band.sum())
        if band_counts[index]:
            bands[index] = _histogram(reflectance[inside_band])
    return RowStatistics(counts, histograms, quantiles, means, zeros, bands, band_counts)


def wasserstein(first: npt.NDArray[np.float64], second: npt.NDArray[np.float64]) -> float:
    """Earth mover's distance between two normalised reflectance histograms (in reflectance units)."""
    return float(np.abs(np.cumsum(first) - np.cumsum(second)).sum() * 0.01)


@dataclass
class Agreement:
    """How close simulated reflectance statistics are to real ones, row by row (rows both have points)."""

    rows: npt.NDArray[np.int64]
    row_distance: npt.NDArray[np.float64]  # Wasserstein-1 per row
    median_difference: npt.NDArray[np.float64]  # simulated − real, per row
    zero_difference: npt.NDArray[np.float64]  # share of zeros, simulated − real, per row
    band_distance: npt.NDArray[np.float64]  # Wasserstein-1 per range band (NaN where one side is empty)

    @property
    def mean_row_distance(self) -> float:
        return float(self.row_distance.mean())

    @property
    def mean_abs_median_difference(self) -> float:
        return float(np.abs(self.median_difference).mean())

    @property
    def mean_abs_zero_difference(self) -> float:
        return float(np.abs(self.zero_difference).mean())

    @property
    def mean_band_distance(self) -> float:
        return float(np.nanmean(self.band_distance))


def agreement(real: RowStatistics, simulated: RowStatistics, min_points: int = 500) -> Agreement:
    """Row-by-row agreement of `simulated` with `real` over the rows where both have `min_points`."""
    rows = np.nonzero((real.counts >= min_points) & (simulated.counts >= min_points))[0]
    distance = np.array([wasserstein(real.histograms[r], simulated.histograms[r]) for r in rows])
    bands = np.array([
        wasserstein(real.band_histograms[b], simulated.band_histograms[b])
        if real.band_counts[b] >= min_points and simulated.band_counts[b] >= min_points else np.nan
        for b in range(len(RANGE_BANDS))
    ])
    return Agreement(
        rows=rows,
        row_distance=distance,
        median_difference=simulated.medians[rows] - real.medians[rows],
        zero_difference=simulated.zeros[rows] - real.zeros[rows],
        band_distance=bands,
    )
