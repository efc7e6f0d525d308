"""The odometry's settings: small typed sections with the paper's defaults, saved beside every result.

Every setting's type and range is declared here, on its field, and nowhere else: pydantic checks the
whole config against these declarations when it is loaded (`OdometryConfig.from_dict`, `load`) and when
an odometry is built from it (`OdometryConfig.validate`, since fields may be changed after loading), so a
bad value fails before the first scan, as one `ConfigError` naming each bad key:
``ransac.threshold: must be a number > 0, got 'abc'``. The checks are strict: JSON's ``"false"`` or ``1``
is not a boolean, ``"0.1"`` and ``null`` are not numbers (null only where a setting is optional), NaN is
refused, and infinity too except for a limit (no limit).
"""

from __future__ import annotations

import difflib
import functools
import json
import math
import types
import typing
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Union, get_args, get_origin

# annotated-types comes with pydantic: the constraints that pydantic reads from `Annotated`.
from annotated_types import Ge, Gt, Le, Lt, MinLen
from pydantic import AllowInfNan, ConfigDict, Strict, TypeAdapter, ValidationError, with_config

import dmlo_rs


class ConfigError(ValueError):
    """A config that does not fit the schema: one line naming every bad key."""


# Strict: no coercion (JSON's "false" stays a string, 1 stays an integer); an integer is accepted where a
# number is asked for. NaN and infinities are refused (`allow_inf_nan` below), except that a `Limit` may be
# infinite: no limit.
_U64_MAX = 2**64 - 1  # settings that reach the crate as unsigned integers
Flag = Annotated[bool, Strict()]
Finite = Annotated[float, Strict()]
NonNegative = Annotated[float, Strict(), Ge(0)]
Limit = Annotated[float, Strict(), Ge(0), AllowInfNan(True)]
Positive = Annotated[float, Strict(), Gt(0)]
Fraction = Annotated[float, Strict(), Ge(0), Le(1)]
Count = Annotated[int, Strict(), Ge(0), Le(_U64_MAX)]
AtLeastOne = Annotated[int, Strict(), Ge(1), Le(_U64_MAX)]
AtLeastThree = Annotated[int, Strict(), Ge(3), Le(_U64_MAX)]  # a rigid motion needs three matches
Starts = Annotated[tuple[Finite, ...], MinLen(1)]

Refit = Literal["point_to_point", "ray_noise"]
REFITS: tuple[str, ...] = get_args(Refit)
MatchingStage = Literal["auto", "crate", "graph"]
# `dmlo.odometry.reflectance.MODES` (a test keeps them equal).
Reflectance = Literal["auto", "unit", "0-255", "0-65535", "none"]

_SCHEMA = ConfigDict(extra="forbid", allow_inf_nan=False)


@with_config(_SCHEMA)
@dataclass
class MatchingConfig:
    """Which network predictions become 3D matches (§III-D-a)."""

    min_confidence: Fraction = 0.0  # Q* (in (0, 1]) below this is dropped before NMS
    nms_radius: Count = 1  # cells; the paper's r = 1
    max_matches: AtLeastThree = 1000  # top N kept after NMS
    # Beyond the paper: also match the new scan back against the previous one (`match.onnx` on both
    # scans' cached features) and take the midpoint of the two motions. The network errs differently in
    # the two directions, so part of its error cancels; it costs one more matching pass and a second
    # coherence pass every frame.
    symmetric: Flag = False
    # With `symmetric`: a cell whose match, followed back by the other direction's flow, lands more than
    # this many pixels from where it started is left out (optical flow's forward–backward check); None: keep all.
    consistency_px: Limit | None = 1.0
    # Beyond the paper: before NMS, each cell's confidence is multiplied by exp(−d / coherence_px), d the
    # distance (pixels) of its flow from the (separable) median flow of the (2·coherence_radius+1)² cells around it
    # (`dmlo_rs.coherent_confidence`): the scene moves rigidly, a wrong match jumps away from its
    # neighbours. None: the network's confidence as it is (the paper).
    coherence_px: Positive | None = 0.5
    coherence_radius: Annotated[int, Strict(), Ge(0), Le(dmlo_rs.MAX_COHERENCE_RADIUS)] = 2


@with_config(_SCHEMA)
@dataclass
class RansacConfig:
    """RANSAC around the closed-form SVD solve (§III-D-b)."""

    threshold: Positive = 0.1  # metres; the paper's inlier threshold
    confidence: Annotated[float, Strict(), Gt(0), Lt(1)] = 0.999
    # At most a million: the hypotheses run in the crate, where Ctrl-C cannot stop them, and a scene without
    # a consensus runs every one.
    max_iterations: Annotated[int, Strict(), Ge(1), Le(1_000_000)] = 1000
    seed: Count = 0
    # How the refits on the inliers solve for the motion: "point_to_point", the closed-form SVD solve
    # (Eq. 12–14, the paper's, isotropic noise), or beyond the paper "ray_noise": that solve refined by
    # Gauss–Newton with each match weighted by its ray (`dmlo_rs.ray_noise_refit`): the network errs in
    # bearing, so a match's error grows with range across its ray, while its range, read from the target
    # scan, stays precise along it (docs/measurements.md compares the two). It assumes every point lies on a
    # ray from one sensor origin: a skewed sweep breaks that, so skewed sweeps need `deskew`.
    refit: Refit = "ray_noise"
    # With "ray_noise": range noise over bearing noise, σ_r / σ_b in metres (per radian) …
    ray_range_ratio: Positive = 4.0
    # … and the refits' inliers within `threshold` along the target's ray and, across it, within the
    # threshold or this angle's width at the match's range (0.2°: a column of the KITTI image), whichever is larger.
    ray_bearing_threshold_deg: Annotated[float, Strict(), Ge(0), Lt(90)] = 0.2
    # Beyond the paper: a match's vote in a hypothesis's consensus is the horizontal part of the normal of
    # the surface under its reference cell (`dmlo_rs.horizontal_votes`: ≈ 0 on the road, 1 on a wall), at
    # least `min_vote`, instead of 1 each. The road's rings look alike from scan to scan, so at speed its
    # matches lock onto the same rings and agree on no motion at all; counted one each they outvote the
    # few matches on posts and signs that see the car move (a feature-poor highway, reported standing
    # still). The refits still solve on every inlier, road matches included. Consecutive scans only: large-motion
    # registration (`large_motion`, re-matching) compares its starts by inlier counts. False: one vote each (the paper).
    vote_by_tilt: Flag = True
    min_vote: Annotated[float, Strict(), Gt(0), Le(1)] = 0.05  # at most a wall's vote
    # Beyond the paper, for consecutive scans: each match's vote divided by the square root of how many matches
    # share its cube of this many metres in the reference scan. A car a few metres away fills much of the image
    # and holds hundreds of matches; in a traffic jam the cars keeping pace with the ego outvoted the static
    # scene and the car was reported standing still. None: no such division.
    vote_voxel: Positive | None = 2.0


@with_config(_SCHEMA)
@dataclass
class MotionModelConfig:
    """Constant-velocity fallback when too few matches agree (§III-D-c) or their motion is implausible."""

    min_inliers: AtLeastThree = 10  # the paper's 10
    # Beyond the paper, with `ransac.vote_by_tilt`: RANSAC's inliers must vote at least this much above the
    # floor (a match on a wall adds about 1, on the road about 0): a consensus resting on the road alone cannot
    # tell where the car went horizontally (an empty lot), and the prediction is taken instead.
    min_inlier_votes: NonNegative = 5.0
    # Beyond the paper: a RANSAC motion further than this (m, °; per frame, at 10 Hz a 3 g change of speed)
    # from the constant-velocity prediction is a wrong consensus. The matches that agree with the
    # prediction (within twice the RANSAC threshold) are solved instead when they are a consensus of their
    # own — at least `min_inliers` and `guided_fraction` of RANSAC's — otherwise the prediction is taken.
    max_deviation: Limit = 0.3
    max_deviation_deg: Limit = 3.0
    # A prediction measured from a wrong pair still finds a few agreeing matches (ground rings look
    # stationary); a true static scene outvoted by a passing car or a repeated facade is nearly as large.
    guided_fraction: Fraction = 0.5
    # Beyond the paper: a pair spanning this many frames or more (scans missing between them) and a pair
    # whose own motion would give way to the prediction (too few inliers, or implausible) are matched again
    # from the prediction: the previous scan moved by it, projected again and matched in rounds
    # (`large_motion.max_rounds`, `min_step`, `min_step_deg`), once started by the model's own window and once
    # by the wide one (when the model has `frame_wide.onnx`), the more inliers winning. The re-matched motion
    # is taken when it has more inliers than the pair's own, or when the pair's own would give way. Across
    # missing scans the prediction alone errs by whatever the vehicle did meanwhile; re-matching measures it
    # (BENCHMARKS.md, "Missing scans"). None: never (the paper).
    rematch_gap: AtLeastOne | None = 2
    # Across more frames than this (2 s at 10 Hz: a paused log, a stop at a light while no scans came) the
    # prediction is a guess: no motion is judged implausible against it, NDT does not start from it, and the
    # wide window of the re-matching also starts from the large-motion starts (`large_motion.search_ahead_m`).
    prediction_horizon: AtLeastOne = 20
    # Beyond the paper: when the prediction moves the car further than this (m) since the reference scan,
    # the near scene's flow leaves the network's window (highway speeds), so the pair is matched from the
    # prediction at once — the reference moved by it, projected again and matched in rounds as above, its
    # matches voted as `ransac.vote_by_tilt` says — instead of from the identity first. Below it, matching
    # from the identity is the more accurate (a moved reference loses the cells it occludes). None: never.
    match_from_prediction_m: Positive | None = 1.5
    # Matching rounds from the prediction at most (each projects, encodes and matches the moved reference
    # again): the first carries the pair within the window, later ones refine while the correction exceeds
    # `large_motion.min_step`. None: 1 with mapping, whose NDT takes out what a second round would, and 2
    # without.
    prediction_rounds: AtLeastOne | None = None
    # Beyond the paper: match from the prediction first by placing each coarse window where the prediction takes
    # its block's points (the reference's own features, nothing encoded again); the rounds of the moved
    # reference run only when that pair has too few inliers or a motion far from the prediction. None: with
    # mapping only (its NDT takes out the centimetres by which frame-to-frame DMLO is better off with the moved
    # reference's rounds); False: always the rounds.
    guided_windows: Flag | None = None
    # Beyond the paper: before a velocity is measured (the first pair, matched from the identity), the pair is
    # also matched from the reference moved this far (m) ahead and behind along its x axis, one round each; a
    # motion of its own there (`min_inliers`, `min_inlier_votes`) further than `max_deviation` from the
    # frame's flags the frame (`FrameDiagnostics.ambiguous_start`): a drive that starts at speed past evenly
    # spaced posts can match an alias as well as the truth, and the chain would inherit it. The frame keeps
    # its motion unless `start_max_reverse_m` (below) prefers a start's. None: never.
    start_check_m: Positive | None = 3.0
    # Beyond the paper: a flagged first pair (above) whose motion drives backwards along the sensor's x axis
    # (the way KITTI's and the simulator's sensors face) further than this (m a frame) while a start's motion
    # drives forward as far takes the forward motion (`FrameDiagnostics.fallback == "forward_start"`): at
    # highway speed the aliases of evenly spaced posts reversed and the truth drove forward, and no vehicle
    # reverses at such speeds. None: the frame keeps its motion (a sensor mounted facing another way).
    start_max_reverse_m: Positive | None = 0.5


@with_config(_SCHEMA)
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
    left as they are suit the default `ransac.refit` ("ray_noise") worst, since it trusts each point's ray
    from one sensor origin.
    """

    enabled: Flag = False
    clockwise: Flag = True
    reference_azimuth_deg: Finite = 0.0


@with_config(_SCHEMA)
@dataclass
class MappingConfig:
    """Scan-to-map NDT refinement of every pose over a local map of recent scans (§III-D-c), on by default:
    the network's matches bring each scan within NDT's basin with no initial guess, and NDT against many
    scans in one frame, fitting every point rather than a few hundred matches, takes out the error the
    matches leave and the drift that frame-to-frame estimates pile up. `Odometry.register_pair` refines a
    consecutive pair against the reference scan alone (`dmlo_rs.LocalMap.refine_pair`). `enabled = False` is the
    paper's frame-to-frame DMLO."""

    enabled: Flag = True
    voxel_size: Positive = 1.0
    max_scans: AtLeastOne = 10  # keyframes the local map keeps
    # A scan enters the map only once it moved this far (metres) or turned this much (degrees) from the
    # newest map scan; 0 and 0 put every scan in.
    keyframe_distance: Limit = 2.0
    keyframe_angle_deg: Limit = 5.0
    # Within this distance (m) of the newest keyframe the horizontal motion and heading come from the scan's
    # upright surfaces alone: the ground rings sit at fixed ranges from the sensor, so the rings of a keyframe
    # taken nearby lie where the scan's own would if the car stood still, and they hold a creeping car in
    # place (`register_pair` treats a pair that moved less the same way); a car standing at the keyframe is
    # aligned to it by point-to-plane ICP. 0 turns both off.
    ring_lock_distance: Limit = 0.5
    # When the DMLO pose is this far (m, °) from the constant-velocity prediction, NDT also starts from the
    # prediction and the better-scoring alignment wins (a wrong RANSAC consensus is caught by the map).
    motion_model_start_distance: Limit = 0.3
    motion_model_start_angle_deg: Limit = 1.5
    # Voxel (m) of the scan aligned to the map, within `far_range` metres of the sensor and beyond it; 0: every
    # point. Near the sensor every surface is sampled densely and the nearest objects, often vehicles keeping
    # pace, fill much of the scan: the coarser voxel keeps them from outweighing the static scene. Farther
    # out the finer voxel keeps the sparse scene's structure (a far point's lever arm constrains rotation).
    downsample: NonNegative = 0.75
    downsample_far: NonNegative = 0.4
    far_range: Limit = 15.0
    # The height, roll and pitch come from a second, two-step NDT of the points within `far_range` and the far
    # ones off upright surfaces (the ground, told by the slope to the next ring): seen from the keyframes
    # behind, far walls, poles and trees tilt the scan nose-down a little every frame, and each keyframe would
    # carry the tilt into the map (docs/measurements.md).
    level_without_far_upright: Flag = True
    max_iterations: AtLeastOne = 30
    # Translations (rotations) with less than this fraction of the best-constrained translation's
    # (rotation's) information keep the DMLO estimate instead of the map's pull; 0 turns the test off.
    degeneracy_threshold: Annotated[float, Strict(), Ge(0), Lt(1)] = 0.05
    rotation_degeneracy_threshold: Annotated[float, Strict(), Ge(0), Lt(1)] = 0.01


@with_config(_SCHEMA)
@dataclass
class LargeMotionConfig:
    """`register_pair(..., large_motion=True)`: scans far apart, no initial guess (§IV-D).

    The wide-window graph matches the pair, as in the paper. Beyond the paper, it does so from several
    starts — the reference scan moved as if the target lay `search_ahead_m` metres along the reference's
    x axis (a vehicle's heading; negative: behind) and turned by `search_yaw_deg` degrees (counter-
    clockwise seen from above), every combination — and the start whose matches have the most RANSAC
    inliers goes on. The wide window reaches a few metres of translation, so starts spaced within its reach
    cover a stretch of road ahead and behind; yaw starts 30° apart, `tuple(range(0, 360, 30))`, register
    loop closures at any heading, at 12 times the starts. Then the reference is moved by the estimate so far,
    projected again and matched again with the model's own (narrower, cheaper) window, until a round
    corrects less than both steps below; a round with fewer than `motion_model.min_inliers` inliers keeps
    the estimate before it. `search_ahead_m=(0.0,)` and `max_rounds=1` are the paper's single pass."""

    search_ahead_m: Starts = (0.0, -6.0, 6.0, -12.0, 12.0)
    search_yaw_deg: Starts = (0.0,)
    max_rounds: AtLeastOne = 4  # matching rounds from the best start, the wide pass included
    min_step: Limit = 0.05  # metres …
    min_step_deg: Limit = 0.1  # … and degrees


@with_config(_SCHEMA)
@dataclass
class MovingObjectsConfig:
    """Points on moving objects when no labels say which they are (`dmlo.odometry.moving`): the moving-object
    network beside the model (`moving.onnx`) predicts them, and they are left out of matching and of the map
    like labelled moving points. `detect = False` keeps every point not labelled moving (`--keep-moving`
    keeps those too); a model without the network keeps every point."""

    detect: Flag = True
    threshold: Annotated[float, Strict(), Gt(0), Lt(1)] = 0.5  # a cell's moving probability above it drops its points


@with_config(_SCHEMA)
@dataclass
class OdometryConfig:
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    ransac: RansacConfig = field(default_factory=RansacConfig)
    motion_model: MotionModelConfig = field(default_factory=MotionModelConfig)
    deskew: DeskewConfig = field(default_factory=DeskewConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    large_motion: LargeMotionConfig = field(default_factory=LargeMotionConfig)
    moving_objects: MovingObjectsConfig = field(default_factory=MovingObjectsConfig)
    # onnxruntime's (and the crate's matching stage's) threads; 0 lets them choose. More than the machine's
    # cores are bounded to them, with a warning (`dmlo.odometry.matcher.usable_threads`).
    threads: Count = 0
    # Where the network's correlation and window decoding run (`dmlo.odometry.matcher`): "crate" (the
    # Rust crate on cached features: on a CPU it computes each window directly instead of through the
    # graph's gathered tensors), "graph" (inside the ONNX graph, e.g. on a GPU), "auto": the crate when
    # onnxruntime runs on the CPU and the model allows it.
    matching_stage: MatchingStage = "auto"
    min_points: Count = 1000  # scans with fewer finite points are bridged by the motion model
    # The scans' reflectance scale (`dmlo.odometry.reflectance`): "auto" decides from the first scan's values
    # (max ≤ 1: [0, 1]; ≤ 255: 0–255; ≤ 65535: 0–65535; absent, one value everywhere or none of these: no
    # usable reflectance); "unit", "0-255", "0-65535" say it; "none" ignores it. Without usable reflectance
    # the range-only model beside the model runs (`range_only/`).
    reflectance: Reflectance = "auto"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Any) -> OdometryConfig:
        """The config a mapping of settings describes (JSON's lists for tuples), checked against the schema."""
        return _validated(data)

    def validate(self) -> None:
        """Checks every setting as it is now (fields may have been changed since loading): `ConfigError`."""
        for name, hint in typing.get_type_hints(OdometryConfig).items():
            if isinstance(hint, type) and is_dataclass(hint) and not isinstance(getattr(self, name), hint):
                raise ConfigError(f"{name}: must be a {hint.__name__}, got {_shown(getattr(self, name))}")
        _validated(self.to_dict())

    def save(self, path: Path) -> None:
        path.write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: Path) -> OdometryConfig:
        """A config file (JSON); `ConfigError` for settings out of the schema, ValueError for bad JSON,
        OSError when it cannot be read."""
        return cls.from_dict(json.loads(path.read_text()))


@functools.cache
def _adapter() -> TypeAdapter[OdometryConfig]:
    return TypeAdapter(OdometryConfig)


def _validated(data: Any) -> OdometryConfig:
    if not isinstance(data, dict):
        raise ConfigError(f"config: must be a mapping of settings, got {_shown(data)}")
    try:
        return _adapter().validate_python(data)
    except ValidationError as err:
        messages: dict[str, str] = {}  # one per key, in the schema's order of finding them
        for error in err.errors():
            key, message = _explain(error, data)
            messages.setdefault(key, message)
        raise ConfigError("; ".join(messages.values())) from None


def _explain(error: Any, data: dict[str, Any]) -> tuple[str, str]:
    """`(key, message)` for one pydantic error: what the key must be, from its declaration, and what it is."""
    section: type = OdometryConfig
    path: list[str] = []
    hint: Any = None
    value: Any = data
    for part in error["loc"]:
        if not isinstance(part, str):  # an item of a list: the list is named
            break
        hints = typing.get_type_hints(section, include_extras=True)
        if part not in hints:
            where = ".".join(path)
            close = difflib.get_close_matches(part, list(hints), n=1)
            hint_text = f" (did you mean {'.'.join([*path, close[0]])}?)" if close else ""
            known = f"; {where or 'config'} has {', '.join(hints)}" if not close else ""
            key = ".".join([*path, part])
            return key, f"{key}: no such setting{hint_text}{known}"
        path.append(part)
        hint = hints[part]
        value = value.get(part) if isinstance(value, dict) else None
        if isinstance(hint, type) and is_dataclass(hint):
            section = hint
    key = ".".join(path) or "config"
    if hint is None or error["type"] == "dataclass_type":
        return key, f"{key}: must be a mapping of settings, got {_shown(value)}"
    description = _describe(hint, value)
    if isinstance(value, float) and not math.isfinite(value) and description.startswith("a number") and not _allows_inf(hint):
        description = "a finite" + description[1:]
    return key, f"{key}: must be {description}, got {_shown(value)}"


def _describe(hint: Any, value: Any = None) -> str:
    """What a declared type accepts, in words: "a number > 0", "an integer from 0 to 15", "true or false".
    The crate's integer limit (2^64 - 1) is named only to a `value` beyond it."""
    origin = get_origin(hint)
    if origin is Annotated:
        base, *constraints = get_args(hint)
        if any(isinstance(c, MinLen) for c in constraints):
            return "a non-empty list of finite numbers"
        lower = [(">", c.gt) for c in constraints if isinstance(c, Gt)] + [(">=", c.ge) for c in constraints if isinstance(c, Ge)]
        upper = [("<", c.lt) for c in constraints if isinstance(c, Lt)] + [("<=", c.le) for c in constraints if isinstance(c, Le)]
        if upper == [("<=", _U64_MAX)] and not (isinstance(value, int) and value > _U64_MAX):
            upper = []
        what = _describe(base)
        if base is int and lower and upper and lower[0][0] == ">=" and upper[0][0] == "<=":
            return f"{what} from {lower[0][1]} to {_bound(upper[0][1])}"
        bounds = [f"{op} {_bound(limit)}" for op, limit in lower + upper]
        if not bounds:
            return "a finite number" if base is float else what
        return f"{what} {' and '.join(bounds)}"
    if origin is Union or isinstance(hint, types.UnionType):
        options = [_describe(a, value) for a in get_args(hint) if a is not type(None)]
        return " or ".join([*options, "null"])
    if origin is Literal:
        return "one of " + ", ".join(str(a) for a in get_args(hint))
    if hint is bool:
        return "true or false"
    if hint is int:
        return "an integer"
    if hint is float:
        return "a number"
    return str(hint)


def _allows_inf(hint: Any) -> bool:
    return any(isinstance(a, AllowInfNan) and a.allow_inf_nan for a in get_args(hint)) or any(
        _allows_inf(a) for a in get_args(hint) if get_origin(a) is Annotated
    )


def _bound(limit: object) -> str:
    return "2^64 - 1" if limit == _U64_MAX else str(limit)


def _shown(value: Any) -> str:
    """A value as the user wrote it, JSON's names for JSON's values, cut short when long."""
    if value is None or isinstance(value, bool):
        return {None: "null", True: "true", False: "false"}[value]
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
