"""Registration errors as the paper's Table IV defines them.

For a ground-truth transform ``(R̄, t̄)`` and an estimate ``(R, t)``: translation error ``‖t − t̄‖₂`` (m) and
angular error ``θ = 2·asin(‖R − R̄‖_F / (2√2))`` (degrees), which equals the geodesic angle of ``Rᵀ R̄``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "RegistrationErrors",
    "registration_errors",
    "rotation_error_axes_deg",
    "rotation_error_deg",
    "translation_error",
]


def _as_transforms(transforms: ArrayLike, name: str) -> NDArray[np.float64]:
    array = np.asarray(transforms, dtype=np.float64)
    if array.shape == (4, 4):
        array = array[None]
    if array.ndim != 3 or array.shape[1:] != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4) or (N, 4, 4), got {np.shape(transforms)}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return array


def rotation_error_deg(rotation_est: ArrayLike, rotation_gt: ArrayLike) -> NDArray[np.float64]:
    """``2·asin(‖R − R̄‖_F / (2√2))`` in degrees for ``(…, 3, 3)`` rotations."""
    r = np.asarray(rotation_est, dtype=np.float64)
    r_gt = np.asarray(rotation_gt, dtype=np.float64)
    if r.shape[-2:] != (3, 3) or r.shape != r_gt.shape:
        raise ValueError(f"rotations must both be (…, 3, 3), got {r.shape} and {r_gt.shape}")
    frobenius = np.linalg.norm(r - r_gt, axis=(-2, -1))
    return np.degrees(2.0 * np.arcsin(np.clip(frobenius / (2.0 * np.sqrt(2.0)), 0.0, 1.0)))


def rotation_error_axes_deg(rotation_est: ArrayLike, rotation_gt: ArrayLike) -> NDArray[np.float64]:
    """The signed error of ``(…, 3, 3)`` rotations about each axis, ``(…, 3)`` degrees: the rotation vector
    of ``R̄ᵀ R`` (x, y, z components; for small errors roll, pitch and yaw in the frame of ``R̄``).

    Its norm is :func:`rotation_error_deg`; its components, averaged over many pairs, show a bias that the
    unsigned angle hides (an estimate that tilts the same way every frame)."""
    r = np.asarray(rotation_est, dtype=np.float64)
    r_gt = np.asarray(rotation_gt, dtype=np.float64)
    if r.shape[-2:] != (3, 3) or r.shape != r_gt.shape:
        raise ValueError(f"rotations must both be (…, 3, 3), got {r.shape} and {r_gt.shape}")
    error = np.swapaxes(r_gt, -1, -2) @ r
    skew = np.stack(
        [error[..., 2, 1] - error[..., 1, 2], error[..., 0, 2] - error[..., 2, 0], error[..., 1, 0] - error[..., 0, 1]],
        axis=-1,
    )
    sine = 0.5 * np.linalg.norm(skew, axis=-1, keepdims=True)
    cosine = 0.5 * (np.trace(error, axis1=-2, axis2=-1)[..., None] - 1.0)
    angle = np.arctan2(sine, cosine)
    # angle / sin(angle), → 1 for small angles; rotations near 180° have no well-defined sign anyway.
    scale = np.where(sine > 1e-12, angle / np.maximum(sine, 1e-300), 1.0)
    return np.degrees(0.5 * skew * scale)


def translation_error(translation_est: ArrayLike, translation_gt: ArrayLike) -> NDArray[np.float64]:
    """``‖t − t̄‖₂`` for ``(…, 3)`` translations."""
    t = np.asarray(translation_est, dtype=np.float64)
    t_gt = np.asarray(translation_gt, dtype=np.float64)
    if t.shape[-1:] != (3,) or t.shape != t_gt.shape:
        raise ValueError(f"translations must both be (…, 3), got {t.shape} and {t_gt.shape}")
    return np.linalg.norm(t - t_gt, axis=-1)


@dataclass(frozen=True)
class RegistrationErrors:
    """Per-pair and summary errors: angles in degrees, translations in metres."""

    angular_mean: float
    angular_max: float
    translation_mean: float
    translation_max: float
    angular: NDArray[np.float64] = field(repr=False)
    translation: NDArray[np.float64] = field(repr=False)


def registration_errors(transforms_est: ArrayLike, transforms_gt: ArrayLike) -> RegistrationErrors:
    """Errors of ``(N, 4, 4)`` (or one ``(4, 4)``) estimated transforms against the ground truth."""
    est = _as_transforms(transforms_est, "transforms_est")
    gt = _as_transforms(transforms_gt, "transforms_gt")
    if len(est) != len(gt):
        raise ValueError(f"transforms_est has {len(est)} transforms but transforms_gt has {len(gt)}")
    if len(est) == 0:
        raise ValueError("no transforms")
    angular = rotation_error_deg(est[:, :3, :3], gt[:, :3, :3])
    translation = translation_error(est[:, :3, 3], gt[:, :3, 3])
    return RegistrationErrors(
        angular_mean=float(angular.mean()),
        angular_max=float(angular.max()),
        translation_mean=float(translation.mean()),
        translation_max=float(translation.max()),
        angular=angular,
        translation=translation,
    )
