"""Type stubs of the compiled module; checked against it by mypy.stubtest (tests/test_package.py)."""

import numpy as np
import numpy.typing as npt

__all__ = ["__version__"]

__version__: str

# ---- core (issue 2): projection, ground truth, matches, NMS, rigid solve, RANSAC ----------------------



# ---- simulator ray casting (issue 3) ------------------------------------------------------------------



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
    def num_correspondences(self) -> int: ...
    @property
    def score(self) -> float:
        """Mean NDT likelihood per thinned source point (each nearby distribution adds up to 1, far away 0)."""

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
        num_threads: int | None = None,
    ) -> NdtResult:
        """Registers `points` (sensor frame) to the map from `initial_transform` = T_map_source (4×4)."""
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
