"""Points on moving objects found without labels: the learned moving-object network (`dmlo.model.moving`).

Vehicles that keep pace with the ego car (a lead car in a jam, cars beside it) or pass it can outnumber
the static scene's matches and capture the consensus: the odometry then follows them, not the road.
With labels (a SemanticKITTI drive) their moving points are known; on real drives the network beside the
model (`moving.onnx`) predicts, cell by cell of the scan's cylinder image, the probability of a moving
object, and every point in a cell above the threshold is left out of matching and of the map, as labelled
moving points are (§III-D-c).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

import dmlo_rs

def range_and_height(
    cloud: npt.NDArray[np.float32], cylinder: dmlo_rs.CylinderConfig
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """The network's input images of an N×4 scan — range `[H, W]` (0 = empty) and height z of each cell's kept
    point `[H, W]` (0 = empty) — as the crate makes them (`odometry::moving::network_images`): one function
    for training (`dmlo.train.moving`), this detector and the crate's odometry, so that all see the same
    input."""
    ranges, height = dmlo_rs.moving_network_images(np.ascontiguousarray(cloud, dtype=np.float32), cylinder)
    return np.asarray(ranges), np.asarray(height)


def moving_objects_graph(model_graph: Path) -> Path | None:
    """The moving-object network beside a model's `frame.onnx`, if the model has one."""
    graph = model_graph.with_name(dmlo_rs.ModelFolder.MOVING_OBJECTS)
    return graph if graph.is_file() else None


class MovingObjectDetector:
    """The network in onnxruntime: `probability(range, height)` is what the crate's odometry calls (it
    flags the points itself, `odometry::moving`); `mask(cloud)`: True for the points of an N×4 scan that the
    network puts on moving objects."""

    def __init__(self, graph: Path, threshold: float = 0.5, threads: int = 0) -> None:
        from dmlo.odometry.matcher import _open_session, session_options

        self._session: Any = _open_session(graph, session_options(threads), ["CPUExecutionProvider"])
        metadata = self._session.get_modelmeta().custom_metadata_map
        self.cylinder = dmlo_rs.moving_graph_cylinder(metadata, str(graph))
        self.path = graph
        self.threshold = threshold

    def probability(self, ranges: npt.NDArray[np.float32], height: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        """Each cell's probability of a moving object `[H, W]` from the network's two images."""
        (probability,) = self._session.run(None, {"range": ranges[None], "height": height[None]})
        return np.ascontiguousarray(probability[0], dtype=np.float32)

    def mask(self, cloud: npt.NDArray[np.float32]) -> npt.NDArray[np.bool_]:
        """True for the points of an N×4 scan on moving objects, by the crate's rule
        (`odometry::moving::flagged_points`), as its odometry applies it."""
        if len(cloud) == 0:
            return np.zeros(0, bool)
        probability = self.probability(*range_and_height(cloud, self.cylinder))
        return np.asarray(dmlo_rs.flagged_points(cloud, probability, self.cylinder, self.threshold))
