"""Type stubs of the compiled module; checked against it by mypy.stubtest (tests/cli/test_package.py)."""

import numpy as np
import numpy.typing as npt

__all__ = ["ConfigError", "ModelError", "RegistrationError", "__version__"]

__version__: str

class RegistrationError(ValueError):
    """Valid arguments whose data admit no solution (too few pairs or correspondences, degenerate
    points); wrong arguments raise plain ValueError."""

class ConfigError(ValueError):
    """A config that does not fit the odometry's schema: one message naming every bad key."""

class ModelError(ValueError):
    """A model file that is missing, not a dmlo export, or does not fit the input."""

# ---- core (issue 2): projection, ground truth, matches, NMS, rigid solve, RANSAC ----------------------

from typing import Any, Literal, final

__all__ += [
    "CylinderConfig",
    "Projection",
    "RansacResult",
    "RayRefit",
    "Matches",
    "project",
    "point_cells",
    "moving_network_images",
    "flagged_points",
    "unproject",
    "ground_truth_flow",
    "rigid_transform",
    "ransac_rigid",
    "ray_noise_refit",
    "refit_rigid",
    "horizontal_votes",
    "steep_to_next_ring",
    "point_to_plane",
    "nms",
    "decode_matches",
    "coherent_confidence",
    "MAX_COHERENCE_RADIUS",
    "match_features",
    "sweep_times",
    "deskew",
]

MAX_COHERENCE_RADIUS: int
"""The largest `radius` coherent_confidence accepts (its median windows live on the stack)."""

@final
class CylinderConfig:
    """Geometry of a cylinder image (degrees). A (sub-pixel) location ``(row, col)`` of the cropped
    image stands for elevation ``(row_of_zero_elevation - row) * vertical_resolution_deg`` and azimuth
    ``(col_of_zero_azimuth - col) * horizontal_resolution_deg``; integers are cell centres, row 0 is the
    highest elevation, columns grow clockwise seen from above. An image has at most 2^26 cells
    (height × width): larger ones, and resolutions whose full grid exceeds that, raise ValueError."""

    def __new__(
        cls,
        *,
        fov_up_deg: float = 2.0,
        fov_down_deg: float = ...,  # -24.9
        vertical_resolution_deg: float = 0.4,
        horizontal_resolution_deg: float = 0.2,
        height: int = 64,
        width: int = 1792,
    ) -> CylinderConfig: ...
    @staticmethod
    def kitti() -> CylinderConfig: ...
    @staticmethod
    def argoverse() -> CylinderConfig: ...
    @property
    def fov_up_deg(self) -> float: ...
    @property
    def fov_down_deg(self) -> float: ...
    @property
    def vertical_resolution_deg(self) -> float: ...
    @property
    def horizontal_resolution_deg(self) -> float: ...
    @property
    def height(self) -> int: ...
    @property
    def width(self) -> int: ...
    @property
    def full_height(self) -> int: ...
    @property
    def full_width(self) -> int: ...
    @property
    def crop_top(self) -> int: ...
    @property
    def crop_left(self) -> int: ...
    @property
    def row_of_zero_elevation(self) -> float: ...
    @property
    def col_of_zero_azimuth(self) -> float: ...
    @property
    def wraps_azimuth(self) -> bool: ...
    def __getnewargs_ex__(self) -> tuple[tuple[()], dict[str, float | int]]: ...
    def __eq__(self, value: object, /) -> bool: ...
    def __ne__(self, value: object, /) -> bool: ...

@final
class Projection:
    """A scan's cylinder image: ``range``/``reflectance`` H×W float32 (0 = empty), ``index`` H×W int64
    (kept point, -1 = empty), and the counts of dropped points."""

    @property
    def range(self) -> npt.NDArray[np.float32]: ...
    @property
    def reflectance(self) -> npt.NDArray[np.float32]: ...
    @property
    def index(self) -> npt.NDArray[np.int64]: ...
    @property
    def num_non_finite(self) -> int: ...
    @property
    def num_out_of_view(self) -> int: ...

@final
class RansacResult:
    @property
    def transform(self) -> npt.NDArray[np.float64]: ...
    @property
    def inliers(self) -> npt.NDArray[np.bool_]: ...
    @property
    def num_inliers(self) -> int: ...
    @property
    def iterations(self) -> int: ...
    @property
    def rmse(self) -> float: ...

@final
class RayRefit:
    @property
    def transform(self) -> npt.NDArray[np.float64]: ...
    @property
    def iterations(self) -> int: ...
    @property
    def converged(self) -> bool: ...
    @property
    def cost(self) -> float: ...

@final
class Matches:
    @property
    def source(self) -> npt.NDArray[np.float64]: ...
    @property
    def target(self) -> npt.NDArray[np.float64]: ...
    @property
    def confidence(self) -> npt.NDArray[np.float32]: ...
    @property
    def cells(self) -> npt.NDArray[np.int64]: ...
    def __len__(self) -> int: ...

def project(
    points: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    config: CylinderConfig,
    *,
    num_threads: int | None = None,
) -> Projection:
    """Cylinder projection (Eq. 1) of an N×4 (x, y, z, reflectance) or N×3 scan; float64 is converted
    to float32. Each cell keeps its closest point; NaN/Inf points are dropped and counted."""

def point_cells(
    points: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    config: CylinderConfig,
    *,
    num_threads: int | None = None,
) -> npt.NDArray[np.int64]:
    """Each point's flat cell index (row · width + col) by the rule `project` uses; −1 outside the image,
    at the origin or non-finite."""

def moving_network_images(
    points: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    config: CylinderConfig,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """The moving-object network's input images of an N×4 scan: range and height z of each cell's kept point,
    `[H, W]` float32, 0 where empty (`odometry::moving::network_images`)."""

def flagged_points(
    points: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    probability: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    config: CylinderConfig,
    threshold: float,
) -> npt.NDArray[np.bool_]:
    """The points in cells whose moving probability (`[H, W]`) exceeds `threshold` (in float32); points
    outside the image, at the origin or non-finite are not flagged."""

def unproject(
    rows: npt.NDArray[np.floating],
    cols: npt.NDArray[np.floating],
    ranges: npt.NDArray[np.floating],
    config: CylinderConfig,
) -> npt.NDArray[np.float64]:
    """Inverse projection (Eq. 4) of continuous (row, col) locations at ranges → N×3 float64."""

def ground_truth_flow(
    ref_range: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    tgt_range: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    T_tgt_ref: npt.NDArray[np.float64] | npt.NDArray[np.float32],
    config: CylinderConfig,
    max_range_error: float = 0.1,
    *,
    num_threads: int | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.bool_]]:
    """Training flow (Eq. 5-8) → (flow[2, H, W] float32 (Δrow, Δcol), valid[H, W] bool)."""

def rigid_transform(
    src: npt.NDArray[np.floating],
    dst: npt.NDArray[np.floating],
    weights: npt.NDArray[np.floating] | None = None,
) -> npt.NDArray[np.float64]:
    """Weighted closed-form rigid solve (Eq. 12-14) → 4×4 float64 T with dst ≈ T·src."""

def ransac_rigid(
    src: npt.NDArray[np.floating],
    dst: npt.NDArray[np.floating],
    threshold: float = 0.1,
    confidence: float = 0.999,
    max_iterations: int = 1000,
    seed: int = 0,
    *,
    refine_iterations: int = 10,
    refit: Literal["point_to_point", "ray_noise"] = "point_to_point",
    range_ratio: float = 4.0,
    bearing_threshold_deg: float = 0.2,
    votes: npt.NDArray[np.floating] | None = None,
    num_threads: int | None = None,
) -> RansacResult:
    """RANSAC (samples of 3) around the rigid solve; deterministic for a seed whatever num_threads.

    With `votes` (one per match, finite, >= 0, not all 0) a hypothesis's consensus is the sum of its
    inliers' votes instead of their count, and samples draw each match in proportion to its vote.

    The answer is a least-squares refit on the inliers, repeated on the refit's inliers until they stop
    changing (at most `refine_iterations` times; 0: the best minimal-sample hypothesis itself). Each
    refit is the closed-form solve ("point_to_point"), or that solve refined by `ray_noise_refit` with
    `range_ratio` ("ray_noise"; `dst` then in its sensor's frame), whose inliers lie within `threshold`
    along the target's ray and within max(threshold, r·tan(bearing_threshold_deg)) across it.

    Raises RegistrationError for fewer than 3 pairs, when every sample is collinear, or when no match
    lies within `threshold` of the answer (num_inliers is therefore at least 1)."""

def ray_noise_refit(
    src: npt.NDArray[np.floating],
    dst: npt.NDArray[np.floating],
    initial: npt.NDArray[np.floating],
    range_ratio: float = 4.0,
    max_iterations: int = 20,
) -> RayRefit:
    """Gauss-Newton refit of `initial` (4×4, dst ≈ T·src) minimising Σ eᵀΩe, e = T·src − dst, with
    Ω = (I − nnᵀ)/r² + nnᵀ/range_ratio² for each target point at range r along the unit ray n from its
    sensor's origin: bearing noise across the ray, range noise (range_ratio metres per radian) along it."""

def refit_rigid(
    src: npt.NDArray[np.floating],
    dst: npt.NDArray[np.floating],
    *,
    refit: Literal["point_to_point", "ray_noise"] = "point_to_point",
    range_ratio: float = 4.0,
) -> npt.NDArray[np.float64]:
    """The motion (4×4 float64, dst ≈ T·src) of pairs taken as inliers, solved as one of `ransac_rigid`'s
    refits: the closed-form solve (Eq. 12-14), then for "ray_noise" `ray_noise_refit` from it."""

def point_to_plane(
    reference: npt.NDArray[np.floating],
    target: npt.NDArray[np.floating],
    start: npt.NDArray[np.floating],
    config: CylinderConfig,
    *,
    iterations: int = 10,
    max_distance: float = 0.3,
    huber: float = 0.02,
    min_information: float = 1e-5,
    edge_range_ratio: float = 0.1,
    num_threads: int | None = None,
) -> npt.NDArray[np.float64] | None:
    """`T_tgt_ref` refined by projective point-to-plane ICP of the `target` point image's points against the
    `reference` point image (both [H, W, 3] of `config`'s image, NaN where empty), from `start` (4x4):
    each target point against the plane of the reference cell it falls in. None when the first round finds
    fewer than six correspondences."""

def horizontal_votes(
    points: npt.NDArray[np.floating],
    rows: npt.NDArray[np.integer],
    cols: npt.NDArray[np.integer],
    config: CylinderConfig,
    *,
    floor: float = 0.0,
) -> npt.NDArray[np.float64]:
    """Per reference cell (rows[i], cols[i]): its match's vote for a horizontal motion, the horizontal part
    of the normal of the plane through the scan's points around it in `points` ([H, W, 3], each cell's
    kept point, NaN where empty): ~0 on level ground, 1 on a wall; at least `floor` (0..1), and 1 where
    no plane fits (too few neighbours, or one ring's)."""

def steep_to_next_ring(
    points: npt.NDArray[np.floating],
    rows: npt.NDArray[np.integer],
    cols: npt.NDArray[np.integer],
    config: CylinderConfig,
    *,
    min_sine: float = 0.5,
) -> npt.NDArray[np.bool_]:
    """Per cell (rows[i], cols[i]) of `points` ([H, W, 3], NaN where empty): whether it lies on an upright
    surface, told from the segment to the next point of its column above or below alone (either rising at
    least as steeply as a surface whose normal's horizontal part is `min_sine`, 0..1), without
    horizontal_votes' plane fit; True for an empty cell and where its column holds no other point within four
    rows."""

def nms(
    rows: npt.NDArray[np.integer],
    cols: npt.NDArray[np.integer],
    scores: npt.NDArray[np.floating],
    radius: int = 1,
    top_n: int | None = None,
    *,
    config: CylinderConfig | None = None,
) -> npt.NDArray[np.int64]:
    """Greedy NMS in a (2r+1)² window on the grid → kept indices (int64), best first. With the
    image's config, cells must lie in it, and a 360° image's columns wrap (the seam suppresses)."""

def decode_matches(
    ref_range: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    tgt_range: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    flow: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    confidence: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    config: CylinderConfig,
    min_confidence: float = 0.0,
    mask: npt.NDArray[np.bool_] | None = None,
    *,
    max_relative_range_spread: float = 0.1,
    top_n: int | None = None,
    nms_radius: int = 1,
    num_threads: int | None = None,
) -> Matches:
    """Network output (flow[2, H, W], confidence[H, W]) → 3D matches; mask True = exclude the cell.
    With top_n, NMS (nms_radius) is fused in: only the kept matches are decoded, best first, exactly
    nms(..., config=config) of the full output (wrapping round the seam of a 360° image)."""

def coherent_confidence(
    flow: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    confidence: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    ref_range: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    config: CylinderConfig,
    *,
    radius: int = 2,
    scale_px: float = 0.5,
    num_threads: int | None = None,
) -> npt.NDArray[np.float32]:
    """confidence[H, W] × exp(−d / scale_px), d the pixel distance of a cell's flow from the separable median
    flow of the (2·radius+1)² cells around it (per component: medians down the window's columns over cells
    with a range, then their median across; a 360° image's columns wrap); 0 without a range or finite
    flow; radius ≤ MAX_COHERENCE_RADIUS (15). Beyond the paper: lowers matches that disagree with their neighbours."""

def match_features(
    ref_coarse: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    ref_refine: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    tgt_coarse: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    tgt_refine: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    *,
    coarse_window: int,
    refine_window: int,
    coarse_scale: float,
    refine_scale: float,
    refine_offset: Literal["window", "peak_centroid"] = "window",
    stride: tuple[int, int] | None = None,
    cells: npt.NDArray[np.bool_] | None = None,
    guide: npt.NDArray[np.float32] | None = None,
    num_threads: int | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """The network's matching stage on the CPU (what match.onnx computes from two scans' cached features):
    (flow float32 [2, H, W] (Δrow, Δcol), confidence float32 [H, W] Q*). Features (1, C, h, w) or (C, h, w),
    coarse at `stride`, refine at full resolution; the scales are the model's learned softmax temperatures
    (the exported graphs' dmlo.similarity_scales); windows odd ≥ 3; stride None: the network's (4, 8);
    non-finite features are refused. `cells` (bool [H, W]): only the marked reference cells are matched, the
    others get a NaN flow and confidence 0. `guide` (float32 [H, W, 2]): each reference cell's expected flow
    (NaN: none), e.g. where a predicted motion takes its point; each coarse window is centred where its
    block's cells are expected to land (their median), so the flow may exceed the window."""

def sweep_times(
    points: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    *,
    clockwise: bool = True,
    reference_azimuth_deg: float = 0.0,
    num_threads: int | None = None,
) -> npt.NDArray[np.float64]:
    """Sweep times (N,) of points N×4 or N×3 from their azimuth, in sensor periods: 0 when the sensor looks
    at reference_azimuth_deg (x forward = 0), −0.25 a quarter turn before on a clockwise sensor (KITTI's
    HDL-64E); within [−0.5, 0.5]; 0 for a non-finite point."""

def deskew(
    points: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    motion: npt.NDArray[np.float64] | npt.NDArray[np.float32],
    times: npt.NDArray[np.float64] | npt.NDArray[np.float32] | None = None,
    *,
    clockwise: bool = True,
    reference_azimuth_deg: float = 0.0,
    num_threads: int | None = None,
) -> npt.NDArray[np.float32]:
    """Motion compensation: points N×4 or N×3 (reflectance copied) moved from the sensor frame of the moment
    each was measured into that of the sweep's reference moment, float32. motion (4×4) is the sensor's motion
    over one sweep period, T_reference_next (the inverse of the odometry's T_tgt_ref; at most 90° of
    rotation); times (N) the points' sweep times, or None for sweep_times(points) with the same pattern.
    Between the reference and time s the sensor turns by s × the rotation vector and moves by s × the
    translation."""



# ---- simulator ray casting (issue 3) ------------------------------------------------------------------

from typing import final as _final

__all__ += ["RayScene", "lidar_scan_directions"]

@_final
class RayScene:
    """Analytic primitives behind a BVH; primitives numbered triangles, boxes, cylinders, ellipsoids."""

    def __new__(
        cls,
        triangles: npt.NDArray[np.float64] | None = None,
        boxes: npt.NDArray[np.float64] | None = None,
        cylinders: npt.NDArray[np.float64] | None = None,
        ellipsoids: npt.NDArray[np.float64] | None = None,
    ) -> RayScene: ...
    def __len__(self) -> int: ...
    def cast(
        self,
        origins: npt.NDArray[np.float64],
        directions: npt.NDArray[np.float64],
        max_range: float,
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64], npt.NDArray[np.float32]]: ...
    def cast_scan(
        self,
        pose: npt.NDArray[np.float64],
        elevations_deg: npt.NDArray[np.float64],
        azimuth_count: int,
        max_range: float,
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64], npt.NDArray[np.float32]]: ...

def lidar_scan_directions(
    elevations_deg: npt.NDArray[np.float64], azimuth_count: int
) -> npt.NDArray[np.float64]: ...



# ---- NDT scan-to-map refinement (issue 5) -------------------------------------------------------------

from typing import final as _final

__all__ += ["NdtMap", "NdtResult"]

@_final
class NdtResult:
    """The outcome of `NdtMap.align`."""

    @property
    def transform(self) -> npt.NDArray[np.float64]:
        """`T_map_source` as a 4×4 float64 array."""
    @property
    def converged(self) -> bool: ...
    @property
    def iterations(self) -> int: ...
    @property
    def num_correspondences(self) -> int:
        """Thinned source points near a map distribution at `transform`, or where the last step started when
        that step was below the tolerances (it is taken unchecked)."""
    @property
    def score(self) -> float:
        """Mean NDT likelihood per thinned source point (each nearby distribution adds up to 1, far away 0),
        taken where `num_correspondences` is."""
    @property
    def degenerate_directions(self) -> int:
        """Directions of the pose held at the initial estimate because the map does not constrain them."""
    @property
    def translation_eigenvalues(self) -> npt.NDArray[np.float64]:
        """Information about the translation (rotation marginalised) at the initial pose: 3 eigenvalues,
        ascending, divided by the largest; those below `degeneracy_threshold` are degenerate."""
    @property
    def rotation_eigenvalues(self) -> npt.NDArray[np.float64]:
        """The same for the rotation (translation marginalised), against `rotation_degeneracy_threshold`."""

@_final
class NdtMap:
    """A local NDT submap of the most recent `max_scans` scans and scan-to-map registration against it."""

    def __new__(
        cls,
        voxel_size: float = 1.0,
        max_scans: int = 10,
        min_points_per_voxel: int = 5,
        min_eigenvalue_ratio: float = 0.01,
    ) -> NdtMap: ...
    def insert(self, points_world: npt.NDArray[np.floating], *, num_threads: int | None = None) -> None:
        """Adds a scan in map coordinates (N×3 or N×4 float32/float64); evicts the oldest beyond max_scans."""
    def insert_scan(
        self,
        points: npt.NDArray[np.floating],
        transform: npt.NDArray[np.floating],
        *,
        num_threads: int | None = None,
    ) -> None:
        """Adds a scan in its sensor frame at the pose `transform` (T_map_sensor, 4×4): the map `insert`
        builds from the transformed points, without building them in numpy."""
    def clear(self) -> None: ...
    def align(
        self,
        points: npt.NDArray[np.floating],
        initial_transform: npt.NDArray[np.floating],
        *,
        max_iterations: int = 30,
        translation_epsilon: float = 1e-4,
        rotation_epsilon_deg: float = 1e-3,
        outlier_ratio: float = 0.55,
        source_voxel_size: float = 0.5,
        neighbours: str = "direct7",
        max_step_translation: float = 0.5,
        max_step_rotation_deg: float = 5.0,
        min_correspondences: int = 20,
        degeneracy_threshold: float = 0.05,
        rotation_degeneracy_threshold: float = 0.01,
        num_threads: int | None = None,
    ) -> NdtResult:
        """Registers `points` (sensor frame) to the map from `initial_transform` = T_map_source (4×4).

        Translations (rotations) with less than `degeneracy_threshold` (`rotation_degeneracy_threshold`)
        of the best-constrained one's information at the initial pose keep their initial value (0: off)."""
    @property
    def num_voxels(self) -> int: ...
    @property
    def num_occupied_voxels(self) -> int: ...
    @property
    def num_scans(self) -> int: ...
    @property
    def voxel_size(self) -> float: ...
    @property
    def max_scans(self) -> int: ...

__all__ += ["PairMotion", "match_pair"]

@_final
class PairMotion:
    """A pair's motion from `match_pair` and the matches it rests on."""

    @property
    def transform(self) -> npt.NDArray[np.float64]: ...
    @property
    def source(self) -> npt.NDArray[np.float64]: ...
    @property
    def target(self) -> npt.NDArray[np.float64]: ...
    @property
    def cells(self) -> npt.NDArray[np.int64]: ...
    @property
    def inliers(self) -> npt.NDArray[np.bool_]: ...
    @property
    def num_inliers(self) -> int: ...
    @property
    def inlier_votes(self) -> float | None: ...

def match_pair(
    ref_range: npt.NDArray[np.floating],
    tgt_range: npt.NDArray[np.floating],
    flow: npt.NDArray[np.floating],
    confidence: npt.NDArray[np.floating],
    config: CylinderConfig,
    *,
    ref_points: npt.NDArray[np.floating] | None = None,
    leave_out: npt.NDArray[np.bool_] | None = None,
    tilt_votes: bool = True,
    min_confidence: float = 0.0,
    nms_radius: int = 1,
    max_matches: int = 1000,
    coherence_px: float | None = ...,  # 0.5
    coherence_radius: int = 2,
    threshold: float = 0.1,
    confidence_level: float = 0.999,
    max_iterations: int = 1000,
    seed: int = 0,
    refit: Literal["point_to_point", "ray_noise"] = "ray_noise",
    range_ratio: float = 4.0,
    bearing_threshold_deg: float = 0.2,
    tilt_vote_floor: float | None = ...,  # 0.05
    vote_voxel: float | None = ...,  # 2.0
    num_threads: int | None = None,
) -> PairMotion:
    """A pair's motion `T_tgt_ref` from the matcher's `flow` [2, H, W] and `confidence` [H, W] (§III-D), the
    chain `dmlo.Odometry` runs on every pair: the confidence weighted by the flow's coherence
    (`coherence_px` None: not), the matches decoded to 3D with NMS fused in (`leave_out` [H, W] cells left
    out), with `tilt_votes` each match's vote from the tilt of the surface under it in `ref_points`
    [H, W, 3] (None: the cells' virtual points; at least `tilt_vote_floor`, None: one vote each) divided by
    the square root of its `vote_voxel` cube's crowding (None: not), and RANSAC as `ransac_rigid`. Matches
    that give no motion: the identity with no inliers."""

__all__ += ["FrameClock", "MotionModel", "odometry_config_json", "odometry_config_schema"]

def odometry_config_json(text: str | None = None) -> str:
    """The odometry's config as the crate reads it: `text` (a config file's JSON, Python's `Infinity`
    included) parsed and checked by the crate and written back with every key; None: the crate's defaults.
    ConfigError names every bad key."""

def odometry_config_schema() -> str:
    """The schema of the odometry's config as JSON: every section and setting with its type, rule, default
    and doc, from the crate's one declaration of each."""

@_final
class FrameClock:
    """Frame numbers from scan timestamps: one per scan, or as many sensor periods as a scan's timestamp lies
    after the last timestamped one (the period: the median of the recent intervals between consecutive
    scans)."""

    def __new__(cls) -> FrameClock: ...
    @property
    def frame(self) -> int:
        """The newest scan's frame number, −1 before the first."""
    @property
    def period(self) -> float | None:
        """The sensor period in the timestamps' unit; None until two consecutive scans had timestamps."""
    def advance(self, timestamp: float | None = None) -> tuple[int, bool]:
        """The next scan's frame number, and whether its timestamp was not after the previous one's (then it
        is taken for the next frame). A timestamp that is not finite raises ValueError and changes nothing."""

@_final
class MotionModel:
    """The constant-velocity motion model (§III-D-c) and the judgement of each pair's motion against it."""

    def __new__(
        cls,
        *,
        min_inliers: int = 10,
        min_inlier_votes: float = 5.0,
        max_deviation: float = 0.3,
        max_deviation_deg: float = 3.0,
        guided_fraction: float = 0.5,
        prediction_horizon: int = 20,
        threshold: float = 0.1,
        refit: Literal["point_to_point", "ray_noise"] = "point_to_point",
        range_ratio: float = 4.0,
    ) -> MotionModel: ...
    @property
    def velocity(self) -> npt.NDArray[np.float64]:
        """The per-frame motion `T_tgt_ref` last measured (the identity before any)."""
    @property
    def measured(self) -> bool:
        """Whether a velocity was measured; until then the prediction is "standing still", a guess."""
    @property
    def gated_last(self) -> bool:
        """Whether the last judged motion was replaced by the prediction as implausible."""
    def predicted(self, frames: int) -> npt.NDArray[np.float64]:
        """The constant-velocity motion `T_tgt_ref` across `frames` frames."""
    def update(self, reference_pose: npt.NDArray[np.floating], pose: npt.NDArray[np.floating], frames: int) -> None:
        """Measures the velocity from two poses `T_world_lidar` `frames` frames apart (consecutive only)."""
    def implausible(self, motion: npt.NDArray[np.floating], predicted: npt.NDArray[np.floating], gap: int) -> bool:
        """Whether `motion` lies further from `predicted` than `gap` frames of a car's change of speed allow."""
    def judge(
        self,
        motion: npt.NDArray[np.floating],
        num_inliers: int,
        inlier_votes: float | None,
        source: npt.NDArray[np.floating],
        target: npt.NDArray[np.floating],
        predicted: npt.NDArray[np.floating],
        gap: int,
    ) -> tuple[npt.NDArray[np.float64], str | None]:
        """The motion `T_tgt_ref` a frame `gap` frames after its reference takes from its pair, and the
        fallback taken: None (the pair's own), "constant_velocity", "degenerate_scene", "guided_consensus" or
        "implausible_motion"."""

__all__ += ["LocalMap", "MapRefinement", "heading_and_level", "upright_points"]

@_final
class MapRefinement:
    """What the local map made of a pose (`LocalMap.refine`)."""

    @property
    def pose(self) -> npt.NDArray[np.float64]:
        """The refined pose `T_map_lidar`, or the one given when no alignment converged."""
    @property
    def converged(self) -> bool: ...
    @property
    def degenerate_directions(self) -> int | None:
        """Pose directions the map did not constrain (kept as given); None when no alignment ran."""
    @property
    def upright_only(self) -> bool:
        """Near the newest keyframe: the horizontal motion and heading came from the upright surfaces."""
    @property
    def start(self) -> Literal["dmlo", "motion_model", "standing"] | None:
        """The start whose alignment won; None when none converged."""

@_final
class LocalMap:
    """The local map of the most recent keyframes (scan-to-map NDT, §III-D-c), with the odometry's `mapping`
    settings."""

    def __new__(
        cls,
        cylinder: CylinderConfig,
        *,
        voxel_size: float = 1.0,
        max_scans: int = 10,
        keyframe_distance: float = 2.0,
        keyframe_angle_deg: float = 5.0,
        ring_lock_distance: float = 0.5,
        motion_model_start_distance: float = 0.3,
        motion_model_start_angle_deg: float = 1.5,
        downsample: float = 0.75,
        downsample_far: float = 0.4,
        far_range: float = 15.0,
        level_without_far_upright: bool = True,
        max_iterations: int = 30,
        degeneracy_threshold: float = 0.05,
        rotation_degeneracy_threshold: float = 0.01,
    ) -> LocalMap: ...
    @property
    def last_keyframe(self) -> npt.NDArray[np.float64] | None:
        """The newest keyframe's pose, None before the first."""
    @property
    def num_scans(self) -> int: ...
    def is_keyframe(self, pose: npt.NDArray[np.floating]) -> bool:
        """Whether a scan at `pose` moved or turned far enough from the newest keyframe to enter the map."""
    def insert(
        self, cloud: npt.NDArray[np.floating], pose: npt.NDArray[np.floating], points: npt.NDArray[np.floating]
    ) -> None:
        """Adds a scan (`cloud` N×3/N×4 in its sensor frame, `points` its point image [H, W, 3]) at `pose`."""
    def restart(
        self, cloud: npt.NDArray[np.floating], pose: npt.NDArray[np.floating], points: npt.NDArray[np.floating]
    ) -> None:
        """Empties the map and starts it again from one scan."""
    def refine(
        self,
        cloud: npt.NDArray[np.floating],
        points: npt.NDArray[np.floating],
        pose: npt.NDArray[np.floating],
        prediction: npt.NDArray[np.floating] | None,
    ) -> MapRefinement:
        """The `pose` of a scan refined against the map: near the newest keyframe by point-to-plane ICP (a
        standing car) or the upright surfaces' split, else NDT from `pose` and, when it lies far from it, from
        the constant-velocity `prediction`, the better score winning."""
    def refine_pair(
        self,
        reference: npt.NDArray[np.floating],
        target: npt.NDArray[np.floating],
        reference_points: npt.NDArray[np.floating],
        target_points: npt.NDArray[np.floating],
        t_tgt_ref: npt.NDArray[np.floating],
    ) -> npt.NDArray[np.float64] | None:
        """`t_tgt_ref` of a consecutive pair refined against the reference scan alone; None when it fails."""

def upright_points(points: npt.NDArray[np.floating], config: CylinderConfig, voxel: float) -> npt.NDArray[np.float64]:
    """The upright surfaces of a point image [H, W, 3]: kept points whose surface's normal is mostly horizontal,
    one cell per `voxel` m (0: every cell) → N×3."""

def heading_and_level(horizontal: npt.NDArray[np.floating], level: npt.NDArray[np.floating]) -> npt.NDArray[np.float64]:
    """A pose with the horizontal position and heading of `horizontal` and the height, roll and pitch of
    `level`."""

__all__ += ["Odometry"]

@_final
class Odometry:
    """DMLO odometry run by the crate (`dmlo_rs::odometry::pipeline::Odometry`: projection, the pair's back
    end, the motion model, matching from the prediction, the local map, diagnostics), the network by
    `matcher`: an object with `cylinder` (CylinderConfig), `encode(image)` → features (any object; `image`
    [2, H, W] float32: range, reflectance), `match(reference, target)` → (flow [2, H, W], confidence [H, W])
    float32, and optionally `uses_reflectance` (bool), `match_cells(reference, target, cells)` (the flow of the
    reference cells marked in `cells`, bool [H, W]: those that hold a point; other cells' values are not read)
    and `wide_match(reference, target, target_image)` — as `dmlo.odometry.matcher.FrameMatcherAdapter`. An exception
    the matcher raises comes through unchanged. `config_json`: `dmlo run`'s config.json text (None: the
    defaults; a bad setting raises ConfigError naming it); `range_only`: the range-only model's matcher, run
    from the first scan without usable reflectance on; `allow_zero_reflectance`: without a range-only model,
    such scans run the model on zero reflectance (its poses then cannot be trusted) instead of raising;
    `moving_objects`: a moving-object network, an object with `cylinder` and `probability(range, height)` →
    [H, W] float32 (both images [H, W] float32), whose flagged points are left out of scans given without a
    mask. Each frame's diagnostics carry the notices said at it (`notices`: kind and message)."""

    def __new__(
        cls,
        matcher: object,
        config_json: str | None = None,
        num_threads: int | None = None,
        range_only: object | None = None,
        allow_zero_reflectance: bool = False,
        moving_objects: object | None = None,
    ) -> Odometry: ...
    def register(
        self,
        points: npt.NDArray[np.floating],
        moving: npt.NDArray[np.bool_] | None = None,
        timestamp: object | None = None,
        point_times: npt.NDArray[np.floating] | None = None,
    ) -> npt.NDArray[np.float64]:
        """Adds the next scan (N×4: x, y, z, reflectance, or N×3 without it) and returns its pose
        `T_world_lidar` (4×4); `moving`: one flag per point, left out; `timestamp`: the scan's time (a finite
        number), dropped scans counted from it; `point_times`: with `deskew.enabled`, each point's time in
        sensor periods (None: from its azimuth)."""
    def register_pair(
        self,
        reference: npt.NDArray[np.floating],
        target: npt.NDArray[np.floating],
        large_motion: bool = False,
        reference_moving: npt.NDArray[np.bool_] | None = None,
        target_moving: npt.NDArray[np.bool_] | None = None,
    ) -> tuple[npt.NDArray[np.float64], PairMotion, bool | None, int, list[tuple[str, str]]]:
        """The motion between two scans (N×4 each, or N×3) with no motion model or initial guess: `(T_tgt_ref
        (4×4), the matches, whether NDT against the reference refined it (None: not tried), matching rounds,
        the notices said (kind, message))`;
        `large_motion`: the wide window from the configured search starts, then rounds of the model's own;
        `*_moving`: one flag per point, left out. The drive's poses are untouched."""
    def predict_skipped(self, reason: str = "unreadable_scan") -> npt.NDArray[np.float64]:
        """Records a scan that could not be read: its pose from the motion model (`reason`: a fallback's
        name)."""
    def reset(self) -> None:
        """Forgets the drive: the next scan is the world again; the matchers and the config stay."""
    @property
    def poses(self) -> npt.NDArray[np.float64]:
        """Every pose so far, (N, 4, 4)."""
    @property
    def diagnostics(self) -> list[FrameDiagnostics]:
        """Every frame's diagnostics (those kept)."""
    @property
    def last_diagnostics(self) -> FrameDiagnostics | None:
        """The newest frame's diagnostics (None before the first scan)."""
    def pose_from_flow(
        self,
        ref_range: npt.NDArray[np.floating],
        tgt_range: npt.NDArray[np.floating],
        flow: npt.NDArray[np.floating],
        confidence: npt.NDArray[np.floating],
        *,
        ref_points: npt.NDArray[np.floating] | None = None,
        leave_out: npt.NDArray[np.bool_] | None = None,
        tilt_votes: bool = True,
    ) -> PairMotion:
        """The back end alone with this odometry's settings: a pair's motion from a flow [2, H, W] and
        confidence [H, W] between two range images."""
    @property
    def reflectance_scale(self) -> str | None:
        """The reflectance scale chosen on the first matched scan ("unit", "0-255", "0-65535", "none")."""
    @property
    def config_json(self) -> str:
        """The config it runs with, as `dmlo run`'s config.json."""
    @property
    def runs_range_only(self) -> bool:
        """Whether the range-only model runs in place of the model."""
    def network_image(
        self, points: npt.NDArray[np.floating]
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """The network's input [2, H, W] (range, reflectance on the scale chosen) and the range image [H, W]
        of a scan's finite points; nothing is decided by it."""
    def __len__(self) -> int: ...

# ---- a model folder's layout and its graphs' metadata ------------------------------------------------

__all__ += ["ModelFolder", "ModelMetadata", "moving_graph_cylinder"]

@final
class ModelMetadata:
    """What a dmlo graph's metadata says about its model, checked whole when made (ModelError naming
    `path` and the key at fault)."""
    def __new__(cls, entries: dict[str, str], path: str) -> ModelMetadata: ...
    @property
    def graph(self) -> str: ...
    @property
    def height(self) -> int: ...
    @property
    def width(self) -> int: ...
    @property
    def coarse_window(self) -> int: ...
    @property
    def refine_window(self) -> int: ...
    @property
    def refine_offset(self) -> Literal["window", "peak_centroid"]: ...
    @property
    def similarity_scales(self) -> tuple[float, float] | None: ...
    @property
    def cylinder(self) -> CylinderConfig: ...
    @property
    def use_reflectance(self) -> bool: ...
    def check_range_only_for(self, model: ModelMetadata, path: str, model_path: str) -> None:
        """ModelError unless this graph is a range-only model taking `model`'s images."""
    def check_export_of(
        self,
        graph: str,
        model: ModelMetadata,
        path: str,
        model_path: str,
        *,
        ignore_matching_stage: bool = False,
        ignored: list[str] = ...,
    ) -> None:
        """ModelError unless this graph is the `graph` graph of `model`'s weights."""

@final
class ModelFolder:
    """The file names of a model folder's graphs."""
    ENCODER: str
    FRAME: str
    MATCH: str
    WIDE_WINDOW: str
    RANGE_ONLY: str
    MOVING_OBJECTS: str

def moving_graph_cylinder(entries: dict[str, str], path: str) -> CylinderConfig:
    """The cylinder image of a moving-object graph from its metadata entries (ModelError otherwise)."""

# ---- a frame's diagnostics ----------------------------------------------------------------------------

__all__ += ["FrameDiagnostics"]

@final
class FrameDiagnostics:
    """What happened to one scan, the crate's record: its fields are attributes, `to_dict()` its line of
    diagnostics.jsonl."""
    def __new__(cls, *args: object, **fields: object) -> FrameDiagnostics: ...
    # Its fields by name (a slot of the compiled class: tests/cli/stubtest_allowlist.txt).
    def __getattr__(self, name: str) -> Any: ...
    def to_dict(self) -> dict[str, Any]: ...
