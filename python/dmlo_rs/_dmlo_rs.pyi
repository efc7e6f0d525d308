"""Type stubs of the compiled module; checked against it by mypy.stubtest (tests/test_package.py)."""

import numpy as np
import numpy.typing as npt

__all__ = ["__version__"]

__version__: str

# ---- core (issue 2): projection, ground truth, matches, NMS, rigid solve, RANSAC ----------------------



# ---- simulator ray casting (issue 3) ------------------------------------------------------------------



# ---- NDT scan-to-map refinement (issue 5) -------------------------------------------------------------
