"""`dmlo eval` and the trajectory plot."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from dmlo import poses as P
from dmlo.cli import main
from dmlo.plot import PlotUnavailable, plot_trajectories, view_axes


def run_eval(capsys, *args: str) -> tuple[int, str, str]:
    code = main(["eval", *args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def drive(count: int, step: float = 1.0, seed: int = 0) -> np.ndarray:
    """A gently curving LiDAR-frame drive in the x–y plane."""
    yaw = np.cumsum(np.full(count, 0.01))
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, 0, 0], poses[:, 0, 1] = np.cos(yaw), -np.sin(yaw)
    poses[:, 1, 0], poses[:, 1, 1] = np.sin(yaw), np.cos(yaw)
    poses[:, 0, 3] = np.cumsum(step * np.cos(yaw))
    poses[:, 1, 3] = np.cumsum(step * np.sin(yaw))
    return poses


def test_eval_json_on_kitti_00(shared_data: Path, capsys) -> None:
    folder = shared_data / "kitti_metric_reference"
    code, out, err = run_eval(
        capsys, str(folder / "KITTI_00_gt.txt"), str(folder / "KITTI_00_ORB.txt"), "--json"
    )
    assert code == 0 and err == ""
    result = json.loads(out)
    assert {"t_rel", "r_rel", "ate_rmse", "rpe_t_mean", "rpe_r_mean"} <= set(result)
    assert result["segments"] == 3283 and result["poses"] == 4541
    assert result["t_rel"] == pytest.approx(0.699733, abs=5e-7)
    assert round(result["r_rel"], 6) == pytest.approx(0.253352, abs=1e-12)  # deg/100 m; see test_metrics
    assert result["ate_rmse"] == pytest.approx(1.3034497, abs=5e-7)
    assert result["note"] is None


def test_eval_table_and_plot(shared_data: Path, tmp_path: Path, capsys) -> None:
    folder = shared_data / "kitti_metric_reference"
    plot = tmp_path / "plots" / "00.png"
    code, out, _ = run_eval(
        capsys, str(folder / "KITTI_00_gt.txt"), str(folder / "KITTI_00_SPTAM.txt"), "--plot", str(plot)
    )
    assert code == 0
    assert "t_rel          1.4870 %" in out and "ATE rmse       3.7385 m" in out
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert plot.stat().st_size > 20_000


def test_eval_short_sequence_has_null_kitti_metrics(tmp_path: Path, capsys) -> None:
    gt = drive(30)
    est = gt.copy()
    est[:, :3, 3] *= 1.05
    P.write_kitti_poses(tmp_path / "gt.txt", gt)
    P.write_kitti_poses(tmp_path / "est.txt", est)
    code, out, _ = run_eval(capsys, str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--json")
    result = json.loads(out)
    assert code == 0 and result["t_rel"] is None and result["r_rel"] is None and result["segments"] == 0
    assert "shorter than the 100 m" in result["note"]
    assert result["rpe_t_mean"] == pytest.approx(0.05, rel=1e-6)
    code, out, _ = run_eval(capsys, str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"))
    assert "t_rel          n/a %" in out and "note: ground-truth path is 29.0 m" in out


def test_eval_tum_files_and_sim3(tmp_path: Path, capsys) -> None:
    gt = drive(300)
    est = gt.copy()
    est[:, :3, 3] *= 0.5  # a monocular-like scale error: Sim(3) alignment removes it
    P.write_tum_poses(tmp_path / "gt.tum", gt, np.arange(300) * 0.1)
    P.write_tum_poses(tmp_path / "est.tum", est, np.arange(300) * 0.1)
    code, out, _ = run_eval(
        capsys, str(tmp_path / "gt.tum"), str(tmp_path / "est.tum"), "--format", "tum", "--align", "sim3", "--json"
    )
    result = json.loads(out)
    assert code == 0 and result["ate_rmse"] == pytest.approx(0.0, abs=1e-6)
    assert result["ate_scale"] == pytest.approx(2.0, rel=1e-6)
    assert 40.0 < result["t_rel"] < 55.0  # half the distance travelled: about 50 % drift


def test_eval_calib_converts_lidar_estimate(shared_data: Path, tmp_path: Path, capsys) -> None:
    calib = shared_data / "kitti_gt_poses" / "calib_00-02.txt"
    gt_cam = P.read_kitti_poses(shared_data / "kitti_gt_poses" / "00.txt")[:1500]
    est_lidar = P.camera_to_lidar(gt_cam, P.read_kitti_calib(calib)["Tr"])
    P.write_kitti_poses(tmp_path / "gt.txt", gt_cam)
    P.write_kitti_poses(tmp_path / "est.txt", est_lidar)
    _, out, _ = run_eval(capsys, str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--json")
    assert json.loads(out)["rpe_r_mean"] > 0.001  # frames differ: wrong without the calibration
    _, out, _ = run_eval(
        capsys, str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--calib", str(calib), "--json"
    )
    result = json.loads(out)
    assert result["t_rel"] == pytest.approx(0.0, abs=1e-6)
    assert result["rpe_r_mean"] == pytest.approx(0.0, abs=1e-5)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda d: (d / "missing.txt", d / "est.txt"), "ground-truth file not found"),
        (lambda d: (d / "gt.txt", d / "short.txt"), "has 20 poses but .*short.txt has 19"),
        (lambda d: (d / "gt.txt", d / "broken.txt"), r"broken.txt:3: expected 12 numbers"),
        (lambda d: (d / "gt.txt", d / "words.txt"), r"words.txt:1: 'a' is not a number"),
        (lambda d: (d / "gt.txt", d / "singular.txt"), r"singular.txt:3: the rotation is not orthonormal"),
        (lambda d: (d / "scaled.txt", d / "est.txt"), r"scaled.txt:5: the rotation is not orthonormal"),
    ],
)
def test_eval_user_errors_are_one_line(tmp_path: Path, capsys, make, message: str) -> None:
    P.write_kitti_poses(tmp_path / "gt.txt", drive(20))
    P.write_kitti_poses(tmp_path / "est.txt", drive(20))
    P.write_kitti_poses(tmp_path / "short.txt", drive(19))
    lines = (tmp_path / "est.txt").read_text().splitlines()
    (tmp_path / "broken.txt").write_text("\n".join(lines[:2] + [lines[2] + " 1"] + lines[3:]) + "\n")
    (tmp_path / "words.txt").write_text("a b c d e f g h i j k l\n")
    singular = drive(20)
    singular[2, 1, :3] = 0.0  # a rotation with a zero row: no inverse
    P.write_kitti_poses(tmp_path / "singular.txt", singular)
    scaled = drive(20)
    scaled[4, :3, :3] *= 2.0  # invertible, but no rotation: metrics would be silently wrong
    P.write_kitti_poses(tmp_path / "scaled.txt", scaled)
    gt, est = make(tmp_path)
    code, out, err = run_eval(capsys, str(gt), str(est))
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("dmlo eval: error: ")
    assert __import__("re").search(message, err)


def test_eval_bad_options(tmp_path: Path, capsys) -> None:
    P.write_kitti_poses(tmp_path / "gt.txt", drive(20))
    code, _, err = run_eval(capsys, str(tmp_path / "gt.txt"), str(tmp_path / "gt.txt"), "--delta", "0")
    assert code == 2 and "--delta must be at least 1" in err
    code, _, err = run_eval(capsys, str(tmp_path / "gt.txt"), str(tmp_path / "gt.txt"), "--calib", "nope.txt")
    assert code == 2 and "calibration file not found" in err
    code, out, _ = run_eval(capsys, str(tmp_path / "gt.txt"), str(tmp_path / "gt.txt"), "--delta", "25", "--json")
    assert code == 0 and json.loads(out)["rpe_t_mean"] is None


# ---------------------------------------------------------------------------------------------------
# Plot


def test_view_axes_follow_the_ground_plane(shared_data: Path) -> None:
    camera = P.read_kitti_poses(shared_data / "kitti_gt_poses" / "00.txt")
    assert view_axes(camera) == (0, 2)  # camera frame: y points down, the ground is x–z
    tr = P.read_kitti_calib(shared_data / "kitti_gt_poses" / "calib_00-02.txt")["Tr"]
    assert view_axes(P.camera_to_lidar(camera, tr)) == (0, 1)  # LiDAR frame: z up, the ground is x–y


def test_plot_trajectories_writes_a_png(tmp_path: Path) -> None:
    matplotlib_image = pytest.importorskip("matplotlib.image")
    gt = drive(200)
    est = gt.copy()
    est[:, 1, 3] += np.linspace(0, 5, 200)
    path = plot_trajectories(gt, est, tmp_path / "a" / "plot.png", title="test drive", dpi=50)
    image = matplotlib_image.imread(path)
    assert image.shape[:2] == (350, 350)
    # Something was drawn: the black ground-truth line and the red estimate are both present.
    rgb = image[..., :3]
    assert np.any(np.all(rgb < 0.2, axis=-1))
    assert np.any((rgb[..., 0] > 0.7) & (rgb[..., 1] < 0.3) & (rgb[..., 2] < 0.3))
    only_estimate = plot_trajectories(None, est, tmp_path / "b.png", axes=(0, 2))
    assert only_estimate.is_file()
    with pytest.raises(ValueError, match="two different axis indices"):
        plot_trajectories(None, est, tmp_path / "c.png", axes=(1, 1))
    with pytest.raises(ValueError, match=r"estimate must have shape \(N, 4, 4\)"):
        plot_trajectories(None, np.zeros((3, 3)), tmp_path / "c.png")


def test_eval_without_matplotlib_prints_the_metrics_and_skips_the_plot_with_a_notice(
    tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Plots are the optional `plot` extra: without matplotlib the metrics still come, the plot is skipped
    # and one line says how to get it.
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` raises ImportError
    with pytest.raises(PlotUnavailable, match=r"pip install 'dmlo\[plot\]'"):
        plot_trajectories(None, drive(5), tmp_path / "direct.png")
    P.write_kitti_poses(tmp_path / "gt.txt", drive(30))
    plot = tmp_path / "plot.png"
    code, out, err = run_eval(capsys, str(tmp_path / "gt.txt"), str(tmp_path / "gt.txt"), "--plot", str(plot))
    assert code == 0 and "ATE rmse" in out and "plot " not in out
    assert err.strip() == "dmlo eval: warning: --plot skipped: plots need matplotlib: pip install 'dmlo[plot]'"
    assert not plot.exists() and not list(tmp_path.glob("*.png"))


def test_eval_help_describes_the_metrics(capsys) -> None:
    with pytest.raises(SystemExit) as info:
        main(["eval", "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert "t_rel" in out and "--plot FILE" in out and "--format {kitti,tum}" in out
