"""dmlo — Deep Matching LiDAR Odometry.

A LiDAR scan becomes a cylinder image; a Siamese CNN predicts where every cell lands in the next scan,
with a confidence; the best matches go through NMS and RANSAC around a closed-form SVD rigid solve.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("dmlo")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
