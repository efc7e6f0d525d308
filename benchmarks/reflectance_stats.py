"""Real and simulated reflectance, row by row of the KITTI cylinder image: how far apart, and the calibration.

    python benchmarks/reflectance_stats.py [--data ../shared/data] [--calibrate] [--figure docs/figures/reflectance_rows.png]

Reads every scan of the shared real KITTI sets (`DATA/kitti_real/*`) and simulates a few scans of street
drives (their own seeds, never the real sets' poses), then prints, per image row (0.4° of elevation, a
laser ring or two; `dmlo.simulator.reflectance`), the real and simulated median and share of zeros, and the
agreement measures: the mean Wasserstein-1 distance between the per-row histograms, the mean absolute
median and zero-share differences, and the mean distance per range band; for the simulator's own model
("simple") and the calibrated one ("kitti").

`--calibrate` fits the calibrated model again on the statistics alone (the real scans' per-row and
per-range-band histograms: never their poses) from returns simulated along the recipe's training drives'
trajectories, and writes `python/dmlo/simulator/hdl64e_kitti_reflectance.json`; the agreement printed after
it is measured on other drives (seed 1 along KITTI 07, seed 3 along KITTI 05, a generated route), held out
from the fit.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from dmlo.simulator import simulate_sequence
from dmlo.simulator.reflectance import (
    RANGE_BANDS,
    ROWS,
    TABLE,
    ReflectanceModel,
    RowStatistics,
    agreement,
    image_rows,
    kitti_hdl64e,
    row_statistics,
    wasserstein,
    _histogram,
)
from dmlo.simulator.sensor import HDL64E

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
# (seed, KITTI trajectory, first pose, frames): the fit's drives, the recipe's training seeds and places.
FIT_DRIVES = ((11, "00", 0, 3), (11, "00", 100, 3), (12, "02", 500, 3), (13, "05", 200, 3), (14, "08", 1000, 3),
              (15, "01", 100, 3), (16, "06", 0, 3), (17, None, 0, 3))
# Held out from the fit: the odometry benchmark's drives (seed 1 along 07, 3 along 05) and a generated route.
CHECK_DRIVES = ((1, "07", 0, 4), (1, "07", 60, 3), (3, "05", 0, 4), (3, "05", 100, 3), (2, None, 0, 4))


@dataclass
class Recorder:
    """A stand-in reflectance model for `simulate_sequence`: keeps the simulator's returns, changes nothing."""

    lasers: int = HDL64E.beams
    parts: list[tuple[npt.NDArray[np.float64], ...]] = field(default_factory=list)

    def apply(self, reflectance, ranges, cos_incidence, lasers):  # type: ignore[no-untyped-def]
        self.parts.append((np.asarray(reflectance, float), np.asarray(ranges, float),
                           np.asarray(cos_incidence, float), np.asarray(lasers, np.int64)))
        return reflectance


@dataclass
class Returns:
    """Simulated returns before the reflectance model: value, range, cos θ, laser, image row."""

    reflectance: npt.NDArray[np.float64]
    ranges: npt.NDArray[np.float64]
    cos: npt.NDArray[np.float64]
    lasers: npt.NDArray[np.int64]
    rows: npt.NDArray[np.int64]


def laser_rows() -> npt.NDArray[np.int64]:
    """The image row of each of the simulated HDL-64E's lasers (its rays have no tilt: one row each)."""
    elevation = np.radians(HDL64E.elevations())
    return image_rows(np.stack([np.cos(elevation), np.zeros_like(elevation), np.sin(elevation)], axis=1))


def simulated_returns(drives, poses: Path) -> Returns:  # type: ignore[no-untyped-def]
    recorder = Recorder()
    with tempfile.TemporaryDirectory() as folder:
        for index, (seed, sequence, start, frames) in enumerate(drives):
            trajectory = poses / f"{sequence}.txt" if sequence is not None else None
            if trajectory is not None and not trajectory.is_file():
                trajectory, start = None, 0
            simulate_sequence(Path(folder) / f"drive{index}", frames=frames, seed=seed, trajectory=trajectory,
                              start=start if trajectory is not None else 0, progress=False,
                              reflectance=recorder)  # type: ignore[arg-type]
    reflectance, ranges, cos, lasers = (np.concatenate(p) for p in zip(*recorder.parts))
    return Returns(reflectance, ranges, cos, lasers, laser_rows()[lasers])


def statistics_of(returns: Returns, model: ReflectanceModel | None) -> RowStatistics:
    """Statistics of the returns with `model` (None: the simulator's own values), as the scans would have them."""
    values = returns.reflectance if model is None else model.apply(returns.reflectance, returns.ranges, returns.cos,
                                                                   returns.lasers)
    # `row_statistics` reads points: one per return at its row's central elevation and its range.
    elevation = np.radians(2.0 - 0.4 * (returns.rows + 0.5))
    points = np.stack([returns.ranges * np.cos(elevation), np.zeros_like(elevation),
                       returns.ranges * np.sin(elevation), values], axis=1)
    return row_statistics([points])


def real_statistics(data: Path) -> tuple[RowStatistics, int]:
    scans = [np.fromfile(path, dtype=np.float32).reshape(-1, 4)
             for folder in sorted((data / "kitti_real").iterdir()) if folder.is_dir()
             for path in sorted((folder / "velodyne").glob("*.bin"))]
    if not scans:
        sys.exit(f"no real scans under {data / 'kitti_real'}")
    return row_statistics(scans), len(scans)


def loss(real: RowStatistics, simulated: RowStatistics) -> float:
    """What the fit minimises: the mean per-row distance plus the mean per-range-band distance."""
    result = agreement(real, simulated)
    return result.mean_row_distance + result.mean_band_distance


def fit(real: RowStatistics, returns: Returns, start: ReflectanceModel | None = None, rounds: int = 2) -> ReflectanceModel:
    """Global fade, grazing and floor parameters with one gain and offset for all lasers (Nelder–Mead), then
    each laser's gain and offset against the real histogram of its image row, then the global parameters
    again (`rounds` times). From scratch, or refining `start`."""
    from scipy.optimize import minimize

    lasers = HDL64E.beams
    rows_of = laser_rows()

    def model_of(globals_: npt.NDArray[np.float64], gains: npt.NDArray[np.float64],
                 offsets: npt.NDArray[np.float64]) -> ReflectanceModel:
        scale, power, graze, width, floor = globals_
        return ReflectanceModel(tuple(gains), tuple(offsets), range_scale=float(max(scale, 1.0)),
                                range_power=float(np.clip(power, 0.5, 12.0)), grazing_cos=float(np.clip(graze, 0.0, 0.3)),
                                grazing_width=float(max(width, 1e-3)), zero_below=float(np.clip(floor, 0.0, 0.3)))

    if start is None:
        gains, offsets = np.full(lasers, 1.3), np.full(lasers, 0.02)
        globals_ = np.array([45.0, 3.0, 0.03, 0.05, 0.0])
    else:  # refine a table: its lasers as they are, a detection floor to find
        gains, offsets = np.array(start.gains), np.array(start.offsets)
        globals_ = np.array([start.range_scale, start.range_power, start.grazing_cos, start.grazing_width,
                             max(start.zero_below, 0.05)])

    def global_loss(x: npt.NDArray[np.float64]) -> float:
        return loss(real, statistics_of(returns, model_of(x[:5], gains * x[5], offsets + x[6])))

    result = minimize(global_loss, np.concatenate([globals_, [1.0, 0.0]]), method="Nelder-Mead",
                      options={"maxiter": 200, "xatol": 1e-3, "fatol": 1e-5})
    globals_ = result.x[:5]
    gains, offsets = gains * result.x[5], offsets + result.x[6]
    print(f"global fit: loss {result.fun:.4f}, range scale {globals_[0]:.1f} m, power {globals_[1]:.2f}, "
          f"grazing cos {globals_[2]:.3f} + {globals_[3]:.3f}, zero below {globals_[4]:.3f}, gain {gains[0]:.3f}, "
          f"offset {offsets[0]:.3f}")

    for _ in range(rounds):
        base = model_of(globals_, np.ones(lasers), np.zeros(lasers))
        for laser in range(lasers):
            mine = returns.lasers == laser
            if mine.sum() < 200 or real.counts[rows_of[laser]] < 500 or rows_of[laser] < 0:
                continue
            target = real.histograms[rows_of[laser]]
            unrounded = returns.reflectance[mine] * base.range_fade(returns.ranges[mine]) * base.grazing_fade(
                returns.cos[mine])

            def laser_loss(x: npt.NDArray[np.float64], unrounded=unrounded, target=target) -> float:
                values = x[0] * unrounded - x[1]
                values = np.where(values < base.zero_below, 0.0, np.clip(np.round(values / 0.01) * 0.01, 0.0, 1.0))
                return wasserstein(_histogram(values), target)

            found = minimize(laser_loss, np.array([gains[laser], offsets[laser]]), method="Nelder-Mead",
                             options={"maxiter": 120, "xatol": 1e-3, "fatol": 1e-6})
            gains[laser], offsets[laser] = found.x

        def refit(x: npt.NDArray[np.float64]) -> float:
            return loss(real, statistics_of(returns, model_of(x, gains, offsets)))

        again = minimize(refit, globals_, method="Nelder-Mead", options={"maxiter": 120, "xatol": 1e-3, "fatol": 1e-5})
        globals_ = again.x
        print(f"per-laser fit: loss {again.fun:.4f}, range scale {globals_[0]:.1f} m, power {globals_[1]:.2f}, "
              f"grazing cos {globals_[2]:.3f} + {globals_[3]:.3f}, zero below {globals_[4]:.3f}")
    return model_of(globals_, gains, offsets)


def _rounded(values: npt.NDArray[np.float64]) -> list[float | None]:
    return [None if np.isnan(v) else round(float(v), 3) for v in values]


def table_extras(real: RowStatistics, after: RowStatistics) -> dict[str, object]:
    """What the table records beside the model: the real per-row medians and zero shares it was fitted to,
    and the calibrated simulator's on the held-out drives (rows with fewer than 500 points: null)."""
    def enough(stats: RowStatistics, values: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        return np.where(stats.counts >= 500, values, np.nan)

    return {
        "about": "benchmarks/reflectance_stats.py --calibrate: a real KITTI HDL-64E's reflectance from the "
                 "simulator's, fitted on the per-row and per-range-band histograms of the shared real scans",
        "real_row_medians": _rounded(enough(real, real.medians)),
        "real_row_zero_shares": _rounded(enough(real, real.zeros)),
        "row_medians": _rounded(enough(after, after.medians)),
        "row_zero_shares": _rounded(enough(after, after.zeros)),
    }


def describe(name: str, real: RowStatistics, simulated: RowStatistics) -> dict[str, float]:
    result = agreement(real, simulated)
    figures = {"row_wasserstein": result.mean_row_distance, "median_abs_diff": result.mean_abs_median_difference,
               "zero_share_abs_diff": result.mean_abs_zero_difference, "band_wasserstein": result.mean_band_distance}
    print(f"{name}: per-row Wasserstein {figures['row_wasserstein']:.4f}, |median difference| "
          f"{figures['median_abs_diff']:.4f}, |zero share difference| {figures['zero_share_abs_diff']:.4f}, "
          f"per-range-band Wasserstein {figures['band_wasserstein']:.4f} ({len(result.rows)} rows)")
    return figures


def print_rows(real: RowStatistics, before: RowStatistics, after: RowStatistics) -> None:
    print("\n| row | real n | real median / q25–q75 / zeros | simple | kitti |\n|---|---|---|---|---|")
    for row in range(0, ROWS, 3):
        if real.counts[row] < 500:
            continue
        cells = []
        for stats in (real, before, after):
            q = stats.quantiles[row]
            cells.append(f"{q[2]:.2f} / {q[1]:.2f}–{q[3]:.2f} / {100 * stats.zeros[row]:.0f} %")
        print(f"| {row} | {real.counts[row]} | {' | '.join(cells)} |")
    print("\n| range band | real median, zeros | simple | kitti |\n|---|---|---|---|")
    for band, (near, far) in enumerate(RANGE_BANDS):
        cells = []
        for stats in (real, before, after):
            h = stats.band_histograms[band]
            median = np.searchsorted(np.cumsum(h), 0.5) * 0.01 if stats.band_counts[band] else np.nan
            cells.append(f"{median:.2f}, {100 * h[0]:.0f} %")
        print(f"| {near}–{far} m | {' | '.join(cells)} |")


def figure(path: Path, real: RowStatistics, before: RowStatistics, after: RowStatistics) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(12, 8.5))
    rows = np.arange(ROWS)
    styles = (("real KITTI", real, "k"), ("simulated, simple", before, "tab:orange"), ("simulated, kitti", after, "tab:blue"))
    ax = axes[0, 0]
    for label, stats, colour in styles:
        ok = stats.counts >= 500
        ax.plot(rows[ok], stats.medians[ok], color=colour, label=f"{label} median")
        ax.fill_between(rows[ok], stats.quantiles[ok, 1], stats.quantiles[ok, 3], color=colour, alpha=0.15)
    ax.set(xlabel="image row (0.4° each, row 0 at +2°)", ylabel="reflectance", title="per row: median and q25–q75")
    ax.legend(fontsize=8)
    ax = axes[0, 1]
    for label, stats, colour in styles:
        ok = stats.counts >= 500
        ax.plot(rows[ok], 100 * stats.zeros[ok], color=colour, label=label)
    ax.set(xlabel="image row", ylabel="% zeros", title="per row: share of zero reflectance")
    ax.legend(fontsize=8)
    ax = axes[1, 0]
    centres = np.arange(101) * 0.01
    for row, style in ((8, "-"), (30, "--"), (50, ":")):
        for label, stats, colour in styles:
            ax.plot(centres, stats.histograms[row], style, color=colour, lw=1,
                    label=f"row {row}, {label}" if row == 8 or label == "real KITTI" else None)
    ax.set(xlabel="reflectance", ylabel="share", title="histograms of rows 8 (—), 30 (--), 50 (···)", ylim=(0, 0.2))
    ax.legend(fontsize=7)
    ax = axes[1, 1]
    labels = [f"{a}–{b}" for a, b in RANGE_BANDS]
    for label, stats, colour in styles:
        medians = [np.searchsorted(np.cumsum(h), 0.5) * 0.01 if n else np.nan
                   for h, n in zip(stats.band_histograms, stats.band_counts)]
        ax.plot(labels, medians, "o-", color=colour, label=f"{label} median")
        ax.plot(labels, [h[0] for h in stats.band_histograms], "x--", color=colour, label=f"{label} share of zeros")
    ax.set(xlabel="range (m)", ylabel="reflectance / share", title="by range")
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    print(f"figure: {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--calibrate", action="store_true", help="fit the model again and write its table")
    parser.add_argument("--refine", action="store_true", help="with --calibrate: start from the table as it is")
    parser.add_argument("--rounds", type=int, default=2, help="with --calibrate: per-laser rounds (default 2)")
    parser.add_argument("--record", action="store_true",
                        help="write the table's recorded statistics again (real and held-out simulated per-row "
                        "medians and zero shares) without fitting")
    parser.add_argument("--figure", type=Path, default=None, help="a PNG of the per-row statistics")
    args = parser.parse_args()
    poses = args.data / "kitti_gt_poses"
    real, scans = real_statistics(args.data)
    print(f"real: {scans} scans, {real.counts.sum()} points in the image rows")
    if args.calibrate:
        fit_returns = simulated_returns(FIT_DRIVES, poses)
        keep = np.random.default_rng(0).random(len(fit_returns.ranges)) < 0.3  # a lighter fit, the same statistics
        fit_returns = Returns(*(getattr(fit_returns, f)[keep] for f in ("reflectance", "ranges", "cos", "lasers", "rows")))
        print(f"fit: {len(fit_returns.ranges)} simulated returns from {sum(d[3] for d in FIT_DRIVES)} scans")
        describe("fit drives, simple", real, statistics_of(fit_returns, None))
        model = fit(real, fit_returns, kitti_hdl64e() if args.refine else None, args.rounds)
        describe("fit drives, kitti", real, statistics_of(fit_returns, model))
        check = simulated_returns(CHECK_DRIVES, poses)
        after = statistics_of(check, model)
        model.save(TABLE, table_extras(real, after))
        print(f"wrote {TABLE}")
    check = simulated_returns(CHECK_DRIVES, poses)
    print(f"check: {len(check.ranges)} simulated returns from {sum(d[3] for d in CHECK_DRIVES)} scans of drives "
          "held out from the fit")
    before = statistics_of(check, None)
    after = statistics_of(check, kitti_hdl64e())
    describe("check drives, simple (the simulator's own)", real, before)
    describe("check drives, kitti (calibrated)", real, after)
    if args.record:
        kitti_hdl64e().save(TABLE, table_extras(real, after))
        print(f"wrote {TABLE} (the model unchanged)")
    print_rows(real, before, after)
    if args.figure is not None:
        figure(args.figure, real, before, after)


if __name__ == "__main__":
    main()
