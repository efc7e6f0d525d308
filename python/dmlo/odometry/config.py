"""The odometry's settings: small typed sections with the paper's defaults, saved beside every result."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args

from dmlo.odometry.reflectance import check_mode as check_reflectance_mode


@dataclass
class MatchingConfig:
    """Which network predictions become 3D matches (§III-D-a)."""

    min_confidence: float = 0.0  # Q* below this is dropped before NMS
    nms_radius: int = 1  # cells; the paper's r = 1
    max_matches: int = 1000  # top N kept after NMS
    # Beyond the paper: also match the new scan back against the previous one (`match.onnx` on both
    # scans' cached features) and take the midpoint of the two motions. The network errs differently in
    # the two directions, so part of its error cancels; it costs one more matching pass and a second
    # coherence pass: 0.55–0.8× the frame rate on the 300-frame drives of the README (12.4–14.2 instead of
    # 17.5–23.2 Hz there).
    symmetric: bool = False
    # With `symmetric`: a cell whose match, followed back by the other direction's flow, lands more than
    # this many pixels from where it started is left out (optical flow's forward–backward check); None: keep all.
    consistency_px: float | None = 1.0
    # Beyond the paper: before NMS, each cell's confidence is multiplied by exp(−d / coherence_px), d the
    # distance (pixels) of its flow from the (separable) median flow of the (2·coherence_radius+1)² cells around it
    # (`dmlo_rs.coherent_confidence`): the scene moves rigidly, a wrong match jumps away from its
    # neighbours. None: the network's confidence as it is (the paper).
    coherence_px: float | None = 0.5
    coherence_radius: int = 2


Refit = Literal["point_to_point", "ray_noise"]
REFITS: tuple[str, ...] = get_args(Refit)


@dataclass
class RansacConfig:
    """RANSAC around the closed-form SVD solve (§III-D-b)."""

    threshold: float = 0.1  # metres; the paper's inlier threshold
    confidence: float = 0.999
    max_iterations: int = 1000
    seed: int = 0
    # How the refits on the inliers solve for the motion: "point_to_point", the closed-form SVD solve
    # (Eq. 12–14, the paper's, isotropic noise), or beyond the paper "ray_noise": that solve refined by
    # Gauss–Newton with each match weighted by its ray (`dmlo_rs.ray_noise_refit`): the network errs in
    # bearing, so a match's error grows with range across its ray, while its range, read from the target
    # scan, stays precise along it. Over five simulated 300-frame drives (docs/measurements.md): t_rel
    # 7–45 % lower on every one, r_rel 20–38 % lower on four and 32 % higher on the sparsest. It assumes
    # every point lies on a ray from one sensor origin: skewed sweeps need `deskew` (not deskewed, it
    # drifts 1.4–2.5× more than "point_to_point" on the README's skewed drives; deskewed, less).
    refit: Refit = "ray_noise"
    # With "ray_noise": range noise over bearing noise, σ_r / σ_b in metres (per radian) …
    ray_range_ratio: float = 4.0
    # … and the refits' inliers within `threshold` along the target's ray and, across it, within the
    # threshold or this angle's width at the match's range (0.2°: a column of the KITTI image), whichever is larger.
    ray_bearing_threshold_deg: float = 0.2
    # Beyond the paper: a match's vote in a hypothesis's consensus is the horizontal part of the normal of
    # the surface under its reference cell (`dmlo_rs.horizontal_votes`: ≈ 0 on the road, 1 on a wall), at
    # least `min_vote`, instead of 1 each. The road's rings look alike from scan to scan, so at speed its
    # matches lock onto the same rings and agree on no motion at all; counted one each they outvote the
    # few matches on posts and signs that see the car move (a feature-poor highway, reported standing
    # still). The refits still solve on every inlier, road matches included. Consecutive scans only: large-motion
    # registration (`large_motion`, re-matching) compares its starts by inlier counts. False: one vote each (the paper).
    vote_by_tilt: bool = True
    min_vote: float = 0.05
    # Beyond the paper, for consecutive scans: each match's vote divided by the square root of how many matches
    # share its cube of this many metres in the reference scan. A car a few metres away fills much of the image
    # and holds hundreds of matches; in a traffic jam the cars keeping pace with the ego outvoted the static
    # scene and the car was reported standing still. None: no such division.
    vote_voxel: float | None = 2.0


@dataclass
class MotionModelConfig:
    """Constant-velocity fallback when too few matches agree (§III-D-c) or their motion is implausible."""

    min_inliers: int = 10  # the paper's 10
    # Beyond the paper, with `ransac.vote_by_tilt`: RANSAC's inliers must vote at least this much above the
    # floor (a match on a wall adds about 1, on the road about 0): a consensus resting on the road alone cannot
    # tell where the car went horizontally (an empty lot), and the prediction is taken instead.
    min_inlier_votes: float = 5.0
    # Beyond the paper: a RANSAC motion further than this (m, °; per frame, at 10 Hz a 3 g change of speed)
    # from the constant-velocity prediction is a wrong consensus. The matches that agree with the
    # prediction (within twice the RANSAC threshold) are solved instead when they are a consensus of their
    # own — at least `min_inliers` and `guided_fraction` of RANSAC's — otherwise the prediction is taken.
    max_deviation: float = 0.3
    max_deviation_deg: float = 3.0
    # A prediction measured from a wrong pair still finds a few agreeing matches (ground rings look
    # stationary); a true static scene outvoted by a passing car or a repeated facade is nearly as large.
    guided_fraction: float = 0.5
    # Beyond the paper: a pair spanning this many frames or more (scans missing between them) and a pair
    # whose own motion would give way to the prediction (too few inliers, or implausible) are matched again
    # from the prediction: the previous scan moved by it, projected again and matched in rounds
    # (`large_motion.max_rounds`, `min_step`, `min_step_deg`), once started by the model's own window and once
    # by the wide one (when the model has `frame_wide.onnx`), the more inliers winning. The re-matched motion
    # is taken when it has more inliers than the pair's own, or when the pair's own would give way. Across
    # 7–11 missing scans the paper's fallback errs 0.16–0.69 m and 1.1–6.0° on average, re-matching 2–3 cm
    # and 0.1–0.3° (README, "Missing scans"). None: never (the paper).
    rematch_gap: int | None = 2
    # Across more frames than this (2 s at 10 Hz: a paused log, a stop at a light while no scans came) the
    # prediction is a guess: no motion is judged implausible against it, NDT does not start from it, and the
    # wide window of the re-matching also starts from the large-motion starts (`large_motion.search_ahead_m`).
    prediction_horizon: int = 20


@dataclass
class DeskewConfig:
    """Beyond the paper: motion compensation of every sweep before it is projected.

    A spinning sensor measures its columns one after the other while the vehicle moves (a 10 Hz sweep at
    15 m/s ends 1.5 m from where it began); raw KITTI and most live sensors deliver such skewed sweeps.
    With `enabled`, every scan after the first measured motion is moved into the sensor frame of one
    moment — the one its pose refers to — by the constant-velocity prediction (`dmlo_rs.deskew`), before
    projection, matching and mapping. The points' times come from `register(..., point_times=)` or else
    from the azimuth: a sensor turning `clockwise` seen from above (Velodyne, KITTI), the pose at the
    moment it looks at `reference_azimuth_deg` (0: forward, as KITTI and `dmlo simulate
    --motion-distortion`). Off by default: a sweep that is already one snapshot (the simulator's
    default ones, a driver's or a dataset's motion-compensated scans) would be skewed by it. Skewed sweeps
    left as they are suit the default `ransac.refit` ("ray_noise") worst: 2.5 % drift on the README's skewed
    drives against 1.0–1.8 % with "point_to_point" and 0.6–0.7 % deskewed.
    """

    enabled: bool = False
    clockwise: bool = True
    reference_azimuth_deg: float = 0.0


@dataclass
class MappingConfig:
    """Optional scan-to-map NDT refinement over a local submap of recent scans."""

    enabled: bool = False
    voxel_size: float = 1.0
    max_scans: int = 10  # keyframes the local map keeps
    # A scan enters the map only once it moved this far (metres) or turned this much (degrees) from the
    # newest map scan; 0 and 0 put every scan in.
    keyframe_distance: float = 2.0
    keyframe_angle_deg: float = 5.0
    # When the DMLO pose is this far (m, °) from the constant-velocity prediction, NDT also starts from the
    # prediction and the better-scoring alignment wins (a wrong RANSAC consensus is caught by the map).
    motion_model_start_distance: float = 0.3
    motion_model_start_angle_deg: float = 1.5
    downsample: float = 0.75
    max_iterations: int = 30
    # Translations (rotations) with less than this fraction of the best-constrained translation's
    # (rotation's) information keep the DMLO estimate instead of the map's pull; 0 turns the test off.
    degeneracy_threshold: float = 0.05
    rotation_degeneracy_threshold: float = 0.01


@dataclass
class LargeMotionConfig:
    """`register_pair(..., large_motion=True)`: scans far apart, no initial guess (§IV-D).

    The wide-window graph matches the pair, as in the paper. Beyond the paper, it does so from several
    starts — the reference scan moved as if the target lay `search_ahead_m` metres along the reference's
    x axis (a vehicle's heading; negative: behind) and turned by `search_yaw_deg` degrees (counter-
    clockwise seen from above), every combination — and the start whose matches have the most RANSAC
    inliers goes on. The wide window reaches 6–7 m of translation on the held-out drives, so starts
    6 m apart cover ±15 m along the road; yaw starts 30° apart, `tuple(range(0, 360, 30))`, register loop
    closures at any heading, at 12× the cost. Then the reference is moved by the estimate so far, projected
    again and matched again with the model's own (narrower, cheaper) window, until a round corrects less
    than both steps below; a round with fewer than `motion_model.min_inliers` inliers keeps the estimate
    before it. `search_ahead_m=(0.0,)` and `max_rounds=1` are the paper's single pass."""

    search_ahead_m: tuple[float, ...] = (0.0, -6.0, 6.0, -12.0, 12.0)
    search_yaw_deg: tuple[float, ...] = (0.0,)
    max_rounds: int = 4  # matching rounds from the best start, the wide pass included
    min_step: float = 0.05  # metres …
    min_step_deg: float = 0.1  # … and degrees


@dataclass
class OdometryConfig:
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    ransac: RansacConfig = field(default_factory=RansacConfig)
    motion_model: MotionModelConfig = field(default_factory=MotionModelConfig)
    deskew: DeskewConfig = field(default_factory=DeskewConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    large_motion: LargeMotionConfig = field(default_factory=LargeMotionConfig)
    threads: int = 0  # onnxruntime's (and the crate's matching stage's) threads; 0 lets them choose
    # Where the network's correlation and window decoding run (`dmlo.odometry.matcher`): "crate" (the
    # Rust crate on cached features, 2.6–4.4× faster than onnxruntime on the CPUs measured), "graph"
    # (inside the ONNX graph, e.g. on a GPU), "auto": the crate when onnxruntime runs on the CPU and the
    # model allows it.
    matching_stage: str = "auto"
    min_points: int = 1000  # scans with fewer finite points are bridged by the motion model
    # The scans' reflectance scale (`dmlo.odometry.reflectance`): "auto" decides from the first scan's values
    # (max ≤ 1: [0, 1]; ≤ 255: 0–255; ≤ 65535: 0–65535; absent, one value everywhere or none of these: no
    # usable reflectance); "unit", "0-255", "0-65535" say it; "none" ignores it. Without usable reflectance
    # the range-only model beside the model runs (`range_only/`).
    reflectance: str = "auto"

    def __post_init__(self) -> None:
        check_reflectance_mode(self.reflectance)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> OdometryConfig:
        return _build(cls, data, "config")

    def save(self, path: Path) -> None:
        path.write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: Path) -> OdometryConfig:
        return cls.from_dict(json.loads(path.read_text()))


T = TypeVar("T")


def _build(cls: type[T], data: dict[str, Any], where: str) -> T:
    """Builds a config section, rejecting unknown keys by name rather than ignoring typos."""
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a mapping, got {type(data).__name__}")
    known = {f.name: f for f in fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ValueError(f"{where}: unknown setting(s) {', '.join(unknown)}")
    values: dict[str, Any] = {}
    for name, value in data.items():
        default = getattr(cls(), name)
        if is_dataclass(default):
            value = _build(type(default), value, f"{where}.{name}")
        elif isinstance(default, tuple) and isinstance(value, list):
            value = tuple(value)  # JSON has lists only
        values[name] = value
    return cls(**values)
