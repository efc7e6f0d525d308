"""Training pairs for the matcher: two cylinder images, the ground-truth flow and its validity.

Pairs come from triplets S_{t−1}, S_t, S_{t+1} (§IV-B): [t−1, t], [t, t+1] and [t−1, t+1]. Over a whole
sequence that is every pair of frames 1 apart and every pair 2 apart, each listed once.

A sample is a dict of numpy arrays: ``ref`` and ``tgt`` float32 (2, H, W) (range in metres, 0 where empty;
reflectance), ``flow`` float32 (2, H, W) (Δrow, Δcol) in pixels and ``valid`` bool (H, W).

Augmentations keep the geometry honest:

- *yaw roll*: both images rolled by the same number of columns — the same as turning both scans by one
  yaw angle, so the flow is unchanged; a match that would cross the image's azimuth seam is dropped.
- *crop*: the same window of rows and columns cut from both images; a match whose target leaves the
  window is dropped.
- *mirror* (optional): both images flipped left–right — the scans of the mirror world (y → −y), whose
  flow is the column-negated flow. Every drive then also turns the other way, so the network cannot learn
  a preferred turning direction (a yaw bias that drifts the odometry).
- *laser gains* (optional): each row's reflectance scaled by its own gain, the same in both scans — a real
  sensor's lasers differ in their intensity calibration, so the rings of the road are stripes that stay in
  their rows from scan to scan; a matcher that never saw them follows them and shortens the vertical flow.
- *row dropout* (optional): each row loses its own share of cells, independently in the two scans — a real
  sensor's lasers sit off the image's even row grid, so its rows are partly empty where the simulator's are
  full. Reference cells that lose their point lose their ground truth; the flow is unchanged.
- *reflectance remaps* (optional): a random monotone curve over both scans' reflectance, a fade with range
  and cells whose reflectance is zero — a real sensor's brightness differs from the simulator's in its
  calibration curve, its fall with range and its empty returns; the flow is unchanged.

With ``pose_jacobian=True`` a sample also holds ``pose_jacobian`` float32 (6, 2, H, W): how the ground-truth
flow of every cell moves when the pose changes (see :func:`flow_pose_jacobian`), NaN where a perturbed pose
loses the cell's ground truth. The augmentations move it with the flow (mirror negates its Δcol part), so
the pose loss of `dmlo.model.pose_loss` stays exact on rolled, mirrored and cropped samples.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

Sample = dict[str, NDArray[Any]]


def pair_indices(frames: int, max_gap: int = 2) -> list[tuple[int, int]]:
    """Every (reference, target) pair of frames 1 … ``max_gap`` apart, ordered by reference frame."""
    return [(i, i + gap) for i in range(frames) for gap in range(1, max_gap + 1) if i + gap < frames]


def _target_inside(flow: NDArray[np.float32], height: int, width: int) -> NDArray[np.bool_]:
    """Cells whose target location (row + Δrow, col + Δcol) lies within the image."""
    rows = np.arange(height, dtype=np.float32)[:, None] + flow[0]
    cols = np.arange(width, dtype=np.float32)[None, :] + flow[1]
    return (rows >= 0) & (rows <= height - 1) & (cols >= 0) & (cols <= width - 1)


def roll_columns(sample: Sample, shift: int) -> Sample:
    """Both scans turned by ``shift`` columns (yaw); flow unchanged, seam-crossing matches dropped."""
    rolled = {key: np.roll(value, shift, axis=-1) for key, value in sample.items()}
    height, width = rolled["valid"].shape
    rolled["valid"] = rolled["valid"] & _target_inside(rolled["flow"], height, width)
    return rolled


def mirror_columns(sample: Sample) -> Sample:
    """Both scans of the mirror world (left–right flip): Δcol negated, every match kept."""
    mirrored = {key: np.ascontiguousarray(value[..., ::-1]) for key, value in sample.items()}
    mirrored["flow"][1] *= -1
    if "pose_jacobian" in mirrored:
        mirrored["pose_jacobian"][:, 1] *= -1
    return mirrored


def crop(sample: Sample, top: int, left: int, height: int, width: int) -> Sample:
    """The same window cut from both scans; matches whose target leaves it are dropped."""
    full_height, full_width = sample["valid"].shape
    if not (0 <= top and top + height <= full_height and 0 <= left and left + width <= full_width):
        raise ValueError(f"crop {height}×{width} at ({top}, {left}) exceeds the image {full_height}×{full_width}")
    cut = {key: np.ascontiguousarray(value[..., top : top + height, left : left + width]) for key, value in sample.items()}
    cut["valid"] = cut["valid"] & _target_inside(cut["flow"], height, width)
    return cut


@dataclass(frozen=True)
class Augmentation:
    """Random yaw roll, mirror and crop; ``crop_height`` / ``crop_width`` None keep the full size."""

    crop_height: int | None = None
    crop_width: int | None = None
    yaw_roll: bool = True
    random: bool = True
    """False: no roll, no mirror and a centred crop (validation)."""
    mirror: bool = False
    """Flip half of the samples left–right (drawn after the roll, so runs without it are unchanged)."""
    laser_gain_spread: float = 0.0
    """Largest per-row gain spread S: a sample draws s in [0, S] and each row a gain in [1 − s, 1 + s]; 0: off.
    Drawn after the crop, as is the row dropout, so runs without them are unchanged."""
    row_dropout: float = 0.0
    """Largest share of a row's cells dropped: half the samples draw each row's share in [0, row_dropout]."""
    reflectance_dropout: float = 0.0
    """Share of the samples whose reflectance is zeroed in both scans (the range-only model's input), so that
    the matcher cannot lean on brightness alone; drawn last, so runs without it are unchanged."""
    reflectance_remap: float = 0.0
    """Share of the samples whose reflectance passes through one random monotone curve (the same in both
    scans) and is rounded to KITTI's steps of 0.01: a real sensor's calibration maps brightness to values
    its own way, so only the order of the brightnesses carries over from the simulator. Drawn after the
    reflectance dropout, as are the falloff and the zeros, so runs without them are unchanged."""
    reflectance_falloff: float = 0.0
    """Share of the samples whose reflectance fades to 0 with each cell's own range (from a random range on,
    over a random width), as a real sensor's does far away; a point's brightness then changes between the
    two scans as its range does."""
    reflectance_zeros: float = 0.0
    """Largest share of cells whose reflectance is zeroed, drawn apart in the two scans, as real scans hold
    returns of zero reflectance where the simulator has almost none."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.laser_gain_spread < 1.0:
            raise ValueError(f"laser_gain_spread must be in [0, 1), got {self.laser_gain_spread}")
        if not 0.0 <= self.row_dropout < 1.0:
            raise ValueError(f"row_dropout must be in [0, 1), got {self.row_dropout}")
        for name in ("reflectance_dropout", "reflectance_remap", "reflectance_falloff", "reflectance_zeros"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.crop_height is not None and (self.crop_height <= 0 or self.crop_height % 4):
            raise ValueError(f"crop_height must be a positive multiple of 4, got {self.crop_height}")
        if self.crop_width is not None and (self.crop_width <= 0 or self.crop_width % 8):
            raise ValueError(f"crop_width must be a positive multiple of 8, got {self.crop_width}")

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        height, width = sample["valid"].shape
        if self.random and self.yaw_roll:
            sample = roll_columns(sample, int(rng.integers(0, width)))
        if self.random and self.mirror and rng.random() < 0.5:
            sample = mirror_columns(sample)
        crop_height = self.crop_height or height
        crop_width = self.crop_width or width
        if crop_height > height or crop_width > width:
            raise ValueError(f"crop {crop_height}×{crop_width} is larger than the scans ({height}×{width})")
        if (crop_height, crop_width) != (height, width):
            if self.random:
                top = int(rng.integers(0, height - crop_height + 1))
                left = int(rng.integers(0, width - crop_width + 1))
            else:
                top, left = (height - crop_height) // 2, (width - crop_width) // 2
            sample = crop(sample, top, left, crop_height, crop_width)
        if self.random and self.laser_gain_spread > 0:
            sample = scale_row_reflectance(sample, rng.uniform(0.0, self.laser_gain_spread), rng)
        if self.random and self.row_dropout > 0 and rng.random() < 0.5:
            sample = drop_row_cells(sample, self.row_dropout, rng)
        if self.random and self.reflectance_dropout > 0 and rng.random() < self.reflectance_dropout:
            sample = without_reflectance(sample)
        if self.random and self.reflectance_remap > 0 and rng.random() < self.reflectance_remap:
            sample = remap_reflectance(sample, rng)
        if self.random and self.reflectance_falloff > 0 and rng.random() < self.reflectance_falloff:
            sample = fade_reflectance_with_range(sample, rng)
        if self.random and self.reflectance_zeros > 0:
            sample = zero_reflectance_cells(sample, self.reflectance_zeros, rng)
        return sample


def without_reflectance(sample: Sample) -> Sample:
    """Both scans with their reflectance channel zeroed, as the range-only model sees every scan."""
    zeroed = dict(sample)
    for key in ("ref", "tgt"):
        image = sample[key].copy()
        image[1] = 0.0
        zeroed[key] = image
    return zeroed


# Knots of the random monotone reflectance curve: enough to bend the mid-tones apart from the ends.
_REMAP_SEGMENTS = 5


def remap_reflectance(sample: Sample, rng: np.random.Generator) -> Sample:
    """Both scans' reflectance through one random non-decreasing curve from 0 (0 stays 0, as a real sensor's
    empty returns do) to a random top in [0.5, 1], rounded to steps of 0.01 as KITTI's are."""
    rises = rng.dirichlet(np.full(_REMAP_SEGMENTS, 1.5)) * rng.uniform(0.5, 1.0)
    knots_x = np.linspace(0.0, 1.0, _REMAP_SEGMENTS + 1)
    knots_y = np.concatenate(([0.0], np.cumsum(rises)))
    remapped = dict(sample)
    for key in ("ref", "tgt"):
        image = sample[key].copy()
        image[1] = np.round(np.interp(np.clip(image[1], 0.0, 1.0), knots_x, knots_y) * 100.0) / 100.0
        remapped[key] = image
    return remapped


def fade_reflectance_with_range(sample: Sample, rng: np.random.Generator) -> Sample:
    """Each scan's reflectance times a factor that falls linearly from 1 at a random range in [15, 45] m to
    0 a random [5, 30] m further, by each cell's own range (so a point's brightness changes between the
    scans as its range does)."""
    near = rng.uniform(15.0, 45.0)
    far = near + rng.uniform(5.0, 30.0)
    faded = dict(sample)
    for key in ("ref", "tgt"):
        image = sample[key].copy()
        image[1] = image[1] * np.clip((far - image[0]) / (far - near), 0.0, 1.0)
        faded[key] = image
    return faded


def zero_reflectance_cells(sample: Sample, largest_share: float, rng: np.random.Generator) -> Sample:
    """Each scan loses the reflectance (not the range) of a share in [0, largest_share] of its cells, drawn
    apart in the two scans; the ground truth is unchanged."""
    zeroed = dict(sample)
    for key in ("ref", "tgt"):
        image = sample[key].copy()
        image[1] = np.where(rng.random(image[1].shape) < rng.uniform(0.0, largest_share), 0.0, image[1])
        zeroed[key] = image
    return zeroed


def scale_row_reflectance(sample: Sample, spread: float, rng: np.random.Generator) -> Sample:
    """Each row's reflectance times its own gain in [1 − spread, 1 + spread], the same in both scans, in [0, 1]."""
    height = sample["valid"].shape[0]
    gains = rng.uniform(1.0 - spread, 1.0 + spread, size=(height, 1)).astype(np.float32)
    scaled = dict(sample)
    for key in ("ref", "tgt"):
        image = sample[key].copy()
        image[1] = np.clip(image[1] * gains, 0.0, 1.0)
        scaled[key] = image
    return scaled


def drop_row_cells(sample: Sample, largest_share: float, rng: np.random.Generator) -> Sample:
    """Each row loses a share in [0, largest_share] of its cells, drawn apart in the two scans (range and
    reflectance 0, as empty cells are); a reference cell that loses its point loses its ground truth."""
    height, width = sample["valid"].shape
    shares = rng.uniform(0.0, largest_share, size=(height, 1))
    dropped = dict(sample)
    for key in ("ref", "tgt"):
        keep = rng.random((height, width)) >= shares
        dropped[key] = sample[key] * keep.astype(np.float32)
        if key == "ref":
            dropped["valid"] = sample["valid"] & keep
    return dropped


class Geometry(Protocol):
    """Cylinder projection and ground-truth flow (implemented by `dmlo_rs`)."""

    def project(self, points: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.float32]]: ...

    def ground_truth(
        self,
        ref_range: NDArray[np.float32],
        tgt_range: NDArray[np.float32],
        T_tgt_ref: NDArray[np.float64],
        *,
        max_range_error: float | None = None,
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]: ...


class RustGeometry:
    """`dmlo_rs.project` and `dmlo_rs.ground_truth_flow` (Eq. 4–8) for one cylinder configuration."""

    # Holds only picklable state (no module object), so data-loader workers can receive it.
    def __init__(self, config: Any = None, max_range_error: float = 0.1) -> None:
        import dmlo_rs

        self.config = config if config is not None else dmlo_rs.CylinderConfig.kitti()
        self.max_range_error = max_range_error

    def project(self, points: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        import dmlo_rs

        image = dmlo_rs.project(np.ascontiguousarray(points, dtype=np.float32), self.config)
        return np.asarray(image.range, dtype=np.float32), np.asarray(image.reflectance, dtype=np.float32)

    def ground_truth(
        self,
        ref_range: NDArray[np.float32],
        tgt_range: NDArray[np.float32],
        T_tgt_ref: NDArray[np.float64],
        *,
        max_range_error: float | None = None,
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """Eq. 5–8; ``max_range_error`` (metres) overrides this geometry's for one call."""
        import dmlo_rs

        flow, valid = dmlo_rs.ground_truth_flow(
            ref_range, tgt_range, np.ascontiguousarray(T_tgt_ref, dtype=np.float64), self.config,
            max_range_error=self.max_range_error if max_range_error is None else max_range_error,
        )
        return np.asarray(flow, dtype=np.float32), np.asarray(valid, dtype=bool)


# Perturbation steps of the finite-difference Jacobian, in its units (mrad, mm): large enough that float32
# flows resolve the change (~0.1 px), small enough that the flow is linear in them.
_JACOBIAN_STEP = 1.0


def flow_pose_jacobian(
    geometry: Geometry, ref_range: NDArray[np.float32], tgt_range: NDArray[np.float32], T_tgt_ref: NDArray[np.float64]
) -> NDArray[np.float32]:
    """d(ground-truth flow)/dξ at ``T_tgt_ref``, float32 (6, 2, H, W) in pixels per unit of ξ.

    ξ = (ω in mrad, t in mm) perturbs the motion on the left, T(ξ) = exp(ξ)·T_tgt_ref: an error of the
    estimated motion expressed in the target frame. Forward differences of the ground-truth flow itself
    (Eq. 5–8), so the Jacobian holds whatever the projection does (crops, wrap-around, virtual points).
    NaN where the cell has no ground truth or a perturbed motion moves its match off the image or onto an
    empty cell.
    """
    from scipy.spatial.transform import Rotation

    flow, valid = geometry.ground_truth(ref_range, tgt_range, T_tgt_ref)
    jacobian = np.empty((6, *flow.shape), dtype=np.float32)
    for k in range(6):
        perturbation = np.eye(4)
        if k < 3:
            perturbation[:3, :3] = Rotation.from_rotvec(np.eye(3)[k] * _JACOBIAN_STEP * 1e-3).as_matrix()
        else:
            perturbation[k - 3, 3] = _JACOBIAN_STEP * 1e-3
        # The location Φ(T p'_r) moves smoothly with the pose; the range check of the ground truth does not
        # (a step can move the match onto a neighbour cell of another range), so it is off here: it would
        # drop the cells near cell boundaries, which on the ground are most of them.
        moved, moved_valid = geometry.ground_truth(ref_range, tgt_range, perturbation @ T_tgt_ref, max_range_error=1e9)
        change = moved - flow
        # A match crossing the 360° seam changes Δcol by the image width; a 1 mrad / 1 mm step moves it by
        # well under half of it, so the remainder is the true change.
        width = flow.shape[-1]
        change[1] = (change[1] + width / 2) % width - width / 2
        jacobian[k] = np.where(valid & moved_valid, change / _JACOBIAN_STEP, np.nan)
    return jacobian


class PairDataset:
    """Map-style dataset of training pairs over sequences of frames with ground-truth poses.

    ``sequences`` are `dmlo.datasets` sequences (frames with ``.points`` N×4 and ``.pose`` T_world_lidar).
    Randomness is a pure function of ``(seed, epoch, index)``: a resumed run sees the same samples.
    """

    def __init__(
        self,
        sequences: Sequence[Any],
        geometry: Geometry,
        augmentation: Augmentation | None = None,
        max_gap: int = 2,
        seed: int = 0,
        cache_frames: int = 64,
        pose_jacobian: bool = False,
    ) -> None:
        if max_gap < 1:
            raise ValueError(f"max_gap must be >= 1, got {max_gap}")
        self.sequences = list(sequences)
        self.geometry = geometry
        self.augmentation = augmentation or Augmentation()
        self.seed = seed
        self.pose_jacobian = pose_jacobian
        self.epoch = 0
        self.pairs: list[tuple[int, int, int]] = []
        for number, sequence in enumerate(self.sequences):
            poses = getattr(sequence, "poses", None)
            if poses is None:
                raise ValueError(f"sequence {getattr(sequence, 'name', number)!r} has no ground-truth poses")
            self.pairs.extend((number, i, j) for i, j in pair_indices(len(sequence), max_gap))
        if not self.pairs:
            raise ValueError("no training pairs: every sequence has fewer than 2 frames")
        self._cache: OrderedDict[tuple[int, int], tuple[NDArray[np.float32], NDArray[np.float64]]] = OrderedDict()
        self._cache_frames = cache_frames

    @classmethod
    def from_paths(cls, paths: Sequence[str | Path], **kwargs: Any) -> PairDataset:
        from dmlo.datasets import open_sequence

        geometry = kwargs.pop("geometry", None) or RustGeometry(kwargs.pop("cylinder", None))
        return cls([open_sequence(Path(path)) for path in paths], geometry, **kwargs)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.pairs)

    def _scan(self, sequence: int, index: int) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
        key = (sequence, index)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        frame = self.sequences[sequence][index]
        range_image, reflectance = self.geometry.project(frame.points)
        value = (np.stack((range_image, reflectance)).astype(np.float32), np.asarray(frame.pose, dtype=np.float64))
        self._cache[key] = value
        if len(self._cache) > self._cache_frames:
            self._cache.popitem(last=False)
        return value

    def raw_sample(self, index: int) -> Sample:
        sequence, ref_index, tgt_index = self.pairs[index]
        ref, T_world_ref = self._scan(sequence, ref_index)
        tgt, T_world_tgt = self._scan(sequence, tgt_index)
        T_tgt_ref = np.linalg.solve(T_world_tgt, T_world_ref).astype(np.float64)
        flow, valid = self.geometry.ground_truth(ref[0], tgt[0], T_tgt_ref)
        sample = {"ref": ref, "tgt": tgt, "flow": flow.astype(np.float32), "valid": valid.astype(bool)}
        if self.pose_jacobian:
            sample["pose_jacobian"] = flow_pose_jacobian(self.geometry, ref[0], tgt[0], T_tgt_ref)
        return sample

    def __getitem__(self, index: int) -> Sample:
        rng = np.random.default_rng([self.seed, self.epoch, index])
        return self.augmentation(self.raw_sample(index), rng)


class ArrayPairDataset:
    """Training pairs held in memory (tests, synthetic data): the same augmentation and seeding."""

    def __init__(self, samples: Sequence[Sample], augmentation: Augmentation | None = None, seed: int = 0) -> None:
        self.samples = list(samples)
        self.augmentation = augmentation or Augmentation()
        self.seed = seed
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, index: int) -> Sample:
        rng = np.random.default_rng([self.seed, self.epoch, index])
        return self.augmentation(dict(self.samples[index]), rng)


def collate(samples: Sequence[Sample]) -> dict[str, Any]:
    """Stacks samples into a batch of torch tensors."""
    import torch

    return {key: torch.from_numpy(np.stack([sample[key] for sample in samples])) for key in samples[0]}
