"""Ego motion for the simulator: KITTI pose files (camera frame ↔ LiDAR frame) and generated drives."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

# KITTI odometry calibration of sequences 00–02 (velodyne → left camera): the default `Tr` when no
# calibration file is given. Row-major 3×4.
KITTI_TR = np.array(
    [
        [4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03, -1.198459927713e-02],
        [-7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01, -5.403984729748e-02],
        [9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03, -2.921968648686e-01],
        [0.0, 0.0, 0.0, 1.0],
    ]
)

FRAME_RATE_HZ = 10.0


def read_kitti_poses(path: str | Path) -> npt.NDArray[np.float64]:
    """Reads a KITTI pose file (12 floats a line, row-major 3×4) into (N, 4, 4) float64."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory: no such file {path}")
    rows = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            values = [float(v) for v in line.split()]
        except ValueError as err:
            raise ValueError(f"trajectory {path}: line {number} is not numeric: {err}") from None
        if len(values) != 12:
            raise ValueError(f"trajectory {path}: line {number} has {len(values)} values, expected 12")
        rows.append(values)
    if not rows:
        raise ValueError(f"trajectory {path}: no poses")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = np.asarray(rows).reshape(-1, 3, 4)
    if not np.isfinite(poses).all():
        raise ValueError(f"trajectory {path}: non-finite values")
    return poses


def read_kitti_calib_tr(path: str | Path) -> npt.NDArray[np.float64]:
    """The 4×4 velodyne → camera transform from the `Tr:` line of a KITTI `calib.txt`."""
    path = Path(path)
    for line in Path(path).read_text().splitlines():
        key, _, rest = line.partition(":")
        if key.strip() == "Tr":
            values = [float(v) for v in rest.split()]
            if len(values) != 12:
                raise ValueError(f"calib {path}: Tr has {len(values)} values, expected 12")
            tr = np.eye(4)
            tr[:3, :] = np.asarray(values).reshape(3, 4)
            return tr
    raise ValueError(f"calib {path}: no 'Tr:' line")


def orthonormalize(poses: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Projects the rotation of each (N,4,4) pose onto SO(3) (pose files keep ~7 digits, so their
    rotations are orthonormal only to ~1e-7)."""
    u, _, vt = np.linalg.svd(poses[:, :3, :3])
    fixed = poses.copy()
    fixed[:, :3, :3] = u @ vt
    fixed[:, 3, :] = (0.0, 0.0, 0.0, 1.0)
    return fixed


def camera_to_lidar_poses(
    camera_poses: npt.NDArray[np.float64], tr: npt.NDArray[np.float64] = KITTI_TR
) -> npt.NDArray[np.float64]:
    """KITTI camera-frame poses → `T_world_lidar` with the world at the first LiDAR frame.

    `T_world_lidar = Tr⁻¹ · P_cam · Tr`, then re-based so frame 0 is the identity.
    """
    tr_inv = np.linalg.inv(tr)
    lidar = tr_inv @ camera_poses @ tr
    return np.linalg.inv(lidar[0]) @ lidar


def lidar_to_camera_poses(
    lidar_poses: npt.NDArray[np.float64], tr: npt.NDArray[np.float64] = KITTI_TR
) -> npt.NDArray[np.float64]:
    """`T_world_lidar` → KITTI camera-frame poses `Tr · T_world_lidar · Tr⁻¹` (frame 0 stays identity
    when the LiDAR poses start at identity)."""
    return tr @ lidar_poses @ np.linalg.inv(tr)


def _rotation_z_y(yaw: float, pitch: float) -> npt.NDArray[np.float64]:
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    return rz @ ry


def generate_drive(frames: int, seed: int, rate_hz: float = FRAME_RATE_HZ) -> npt.NDArray[np.float64]:
    """A KITTI-like urban drive as (frames, 4, 4) `T_world_lidar`, frame 0 at identity.

    Manoeuvres are drawn from the seed: cruising at 6–20 m/s with gentle curves, ~90° turns at
    intersection speed, and stops (brake, wait, pull away), with accelerations within ±2.5 m/s² and a
    slowly varying road grade (≤ 3 %) that pitches the car.
    """
    if frames < 1:
        raise ValueError(f"frames: must be at least 1, got {frames}")
    rng = np.random.default_rng([seed, 0x7A1])
    dt = 1.0 / rate_hz
    speed = float(rng.uniform(4.0, 12.0))
    x = y = z = yaw = 0.0
    distance = 0.0
    grade_waves = [
        (rng.uniform(0.005, 0.015), rng.uniform(150.0, 600.0), rng.uniform(0, 2 * np.pi)) for _ in range(2)
    ]
    poses = np.empty((frames, 4, 4))
    manoeuvre_left = 0.0
    target_speed, cruise_yaw_rate, turn_left = speed, 0.0, 0.0
    yaw_rate = 0.0
    for k in range(frames):
        grade = sum(
            a * np.sin(2 * np.pi * distance / wavelength + phase) for a, wavelength, phase in grade_waves
        )
        pitch = -np.arctan(grade)  # nose up (negative rotation about y) when climbing
        pose = np.eye(4)
        pose[:3, :3] = _rotation_z_y(yaw, pitch)
        pose[:3, 3] = (x, y, z)
        poses[k] = pose
        if manoeuvre_left <= 0.0 and turn_left == 0.0:
            kind = rng.choice(["cruise", "turn", "stop"], p=[0.6, 0.25, 0.15])
            cruise_yaw_rate = 0.0
            if kind == "cruise":
                target_speed = float(rng.uniform(6.0, 20.0))
                cruise_yaw_rate = float(rng.normal(0.0, 0.02))
                manoeuvre_left = float(rng.uniform(4.0, 15.0))
            elif kind == "turn":
                target_speed = float(rng.uniform(4.0, 8.0))
                turn_left = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.4, 0.5) * np.pi)
            else:
                target_speed = 0.0
                manoeuvre_left = speed / 2.0 + 1.0 + float(rng.uniform(1.0, 4.0))
        if turn_left != 0.0 and speed <= target_speed + 1.0:
            # Turning radius ~ 10–20 m: yaw rate = speed / radius, eased out over the last 15°.
            desired_yaw_rate = np.sign(turn_left) * speed / 15.0 * min(1.0, abs(turn_left) / 0.26 + 0.2)
        else:
            desired_yaw_rate = cruise_yaw_rate * min(1.0, speed / 4.0)
        yaw_rate += float(np.clip(desired_yaw_rate - yaw_rate, -0.6 * dt, 0.6 * dt))
        if turn_left != 0.0:
            turned = yaw_rate * dt
            turn_left = (
                0.0
                if abs(turned) >= abs(turn_left) or turned * turn_left < 0 and abs(turn_left) < 0.01
                else turn_left - turned
            )
            if turn_left == 0.0:
                target_speed = float(rng.uniform(6.0, 15.0))
                manoeuvre_left = float(rng.uniform(2.0, 6.0))
        accel = float(np.clip((target_speed - speed) / 1.5, -2.5, 2.0))
        speed = max(0.0, speed + accel * dt)
        if target_speed == 0.0 and speed < 0.15:
            speed = 0.0  # standing still, not creeping
        step = speed * dt
        yaw += yaw_rate * dt
        x += step * np.cos(yaw) * np.cos(pitch)
        y += step * np.sin(yaw) * np.cos(pitch)
        z += step * np.sin(-pitch)
        distance += step
        manoeuvre_left -= dt
    return np.linalg.inv(poses[0]) @ poses


def generate_stop_and_go(frames: int, seed: int, rate_hz: float = FRAME_RATE_HZ) -> npt.NDArray[np.float64]:
    """A drive in a traffic jam as (frames, 4, 4) `T_world_lidar`, frame 0 at identity: crawling at
    0.5–3 m/s for 2–5 s, braking to a standstill, standing 2–5 s, pulling away again, along a gently
    curving street; the first stop comes within the first 3 s so that short drives stand too.

    The speeds and accelerations (braking at 1.2, pulling away at 1 m/s²) are those of stop-and-go traffic,
    where a car creeps a few centimetres to a few decimetres a frame and the scene's moving cars outnumber
    its motion.
    """
    if frames < 1:
        raise ValueError(f"frames: must be at least 1, got {frames}")
    rng = np.random.default_rng([seed, 0x57A6])
    dt = 1.0 / rate_hz
    speed = float(rng.uniform(1.0, 3.0))
    target_speed, phase_left = speed, float(rng.uniform(1.0, 3.0))
    standing = False
    yaw_rate = float(rng.normal(0.0, 0.01))
    x = y = yaw = 0.0
    poses = np.empty((frames, 4, 4))
    for k in range(frames):
        pose = np.eye(4)
        pose[:3, :3] = _rotation_z_y(yaw, 0.0)
        pose[:3, 3] = (x, y, 0.0)
        poses[k] = pose
        phase_left -= dt
        if target_speed > 0.0 and phase_left <= 0.0:
            target_speed = 0.0  # brake
        elif target_speed == 0.0 and speed == 0.0 and not standing:
            standing, phase_left = True, float(rng.uniform(2.0, 5.0))
        elif standing and phase_left <= 0.0:
            standing = False
            target_speed, phase_left = float(rng.uniform(0.5, 3.0)), float(rng.uniform(2.0, 5.0))
            yaw_rate = float(rng.normal(0.0, 0.01))
        # Constant braking and pulling away, as in a queue, not an exponential approach.
        rate = 1.2 if target_speed < speed else 1.0
        speed = float(np.clip(target_speed, speed - rate * dt, speed + rate * dt))
        yaw += yaw_rate * speed * dt
        x += speed * dt * np.cos(yaw)
        y += speed * dt * np.sin(yaw)
    return poses


def _rotation_log(rotation: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Axis-angle vector of a 3×3 rotation (angle < π)."""
    angle = np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))
    axis = np.array(
        [rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]]
    )
    if angle < 1e-12:
        return axis / 2.0
    return axis * (angle / (2.0 * np.sin(angle)))


def _rotation_exp(vectors: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Rodrigues: (N,3) axis-angle vectors → (N,3,3) rotations."""
    angle = np.linalg.norm(vectors, axis=1)
    safe = np.where(angle > 1e-12, angle, 1.0)
    k = vectors / safe[:, None]
    kx = np.zeros((len(vectors), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx = kx - kx.transpose(0, 2, 1)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * kx + (1.0 - c) * (kx @ kx)


def sweep_column_poses(
    poses: npt.NDArray[np.float64], index: int, azimuth_count: int
) -> npt.NDArray[np.float64]:
    """(azimuth_count, 4, 4) sensor poses while frame `index` sweeps, for motion distortion.

    The frame's pose holds when the sensor looks straight ahead (the middle column); column `j` fires
    `(j − W/2) / W` of a frame period earlier or later, moving at the frame's constant velocity (towards the
    next frame, or from the previous one for the last frame).
    """
    if len(poses) < 2:
        return np.repeat(poses[index][None], azimuth_count, axis=0)
    a, b = (index, index + 1) if index + 1 < len(poses) else (index - 1, index)
    motion = np.linalg.inv(poses[a]) @ poses[b]  # one frame period of motion in the sensor frame
    fraction = (np.arange(azimuth_count) - azimuth_count / 2) / azimuth_count
    steps = np.tile(np.eye(4), (azimuth_count, 1, 1))
    steps[:, :3, :3] = _rotation_exp(fraction[:, None] * _rotation_log(motion[:3, :3])[None])
    steps[:, :3, 3] = fraction[:, None] * motion[:3, 3][None]
    return poses[index] @ steps
