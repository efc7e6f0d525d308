"""Type stubs of the compiled module; checked against it by mypy.stubtest (tests/test_package.py)."""

import numpy as np
import numpy.typing as npt

__all__ = ["__version__"]

__version__: str

# ---- core (issue 2): projection, ground truth, matches, NMS, rigid solve, RANSAC ----------------------



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
