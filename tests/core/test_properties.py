"""Property-based tests of the public entry points (issue 25): random and adversarial scans, configs and
pose files give a valid result or a clear error (`ValueError`, `TypeError`, or a subclass such as
`RegistrationError`, `PoseFileError`, `DatasetError`), never a crash, a hang or another exception.

Kept fast for CI: few examples each (fewer where the network runs), no deadline (a shared machine),
derandomised so that every run tries the same cases, and no example database written into the tree.
To hunt for bugs, `DMLO_PROPERTY_SCALE=50` runs fifty times as many examples, drawn at random.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, event, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import dmlo_rs
from dmlo import poses as pose_files
from dmlo.cli import main
from dmlo.odometry import Odometry, OdometryConfig

CLEAR_ERRORS = (ValueError, TypeError)


SCALE = float(os.environ.get("DMLO_PROPERTY_SCALE", "1"))


def fast(examples: int) -> settings:
    return settings(
        max_examples=max(1, int(examples * SCALE)),
        deadline=None,
        derandomize=SCALE == 1,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture, HealthCheck.data_too_large],
    )


# ---------------------------------------------------------------------------------------------------------
# Strategies

# Coordinates a scan may hold: ordinary ones, and the values that break arithmetic.
ADVERSARIAL = [0.0, -0.0, 1e-45, 1e-30, 1e15, -1e15, 1e30, 3.4e38, -3.4e38, math.nan, math.inf, -math.inf]
coordinates = st.one_of(
    st.floats(-120.0, 120.0, allow_nan=False, width=32),
    st.sampled_from(ADVERSARIAL),
    st.floats(width=32),
)


@st.composite
def scans(draw: st.DrawFn, max_points: int = 300) -> Any:
    """N×3 or N×4 arrays of many dtypes and layouts, and some that are not scans at all."""
    kind = draw(st.sampled_from(["scan", "scan", "scan", "shape", "dtype", "strided", "list"]))
    columns = draw(st.sampled_from([3, 4]))
    n = draw(st.integers(0, max_points))
    array = draw(hnp.arrays(np.float64, (n, columns), elements=coordinates))
    if kind == "scan":
        return array.astype(draw(st.sampled_from([np.float32, np.float64])))
    if kind == "shape":
        shape = draw(st.sampled_from([(n,), (n, 1), (n, 2), (n, 5), (n, 4, 1), (0,), (), (1, 0)]))
        return np.zeros(shape, dtype=np.float32) if shape != () else np.float32(1.0)
    if kind == "dtype":
        dtype = draw(st.sampled_from([np.float16, np.int32, np.int64, np.uint8, np.bool_, np.complex64, object]))
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return np.nan_to_num(array).astype(dtype)
    if kind == "strided":  # every other row of a wider array: not contiguous
        wide = np.repeat(array.astype(np.float32), 2, axis=0)
        return wide[::2]
    return array.tolist()


def well_conditioned(n: int, seed: int, scale: float = 10.0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-scale, scale, (n, 3))


def random_rigid(seed: int, translation: float = 5.0) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(rng.uniform(-0.5, 0.5, 3)).as_matrix()
    transform[:3, 3] = rng.uniform(-translation, translation, 3)
    return transform


def assert_rigid(transform: np.ndarray) -> None:
    assert transform.shape == (4, 4) and transform.dtype == np.float64
    assert np.all(np.isfinite(transform)), transform
    rotation = transform[:3, :3]
    assert np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6), transform
    assert np.linalg.det(rotation) > 0
    assert np.array_equal(transform[3], [0.0, 0.0, 0.0, 1.0])


# ---------------------------------------------------------------------------------------------------------
# dmlo_rs: projection, rigid solve, RANSAC

KITTI = dmlo_rs.CylinderConfig.kitti()


@fast(60)
@given(points=scans())
def test_project_gives_a_consistent_image_or_a_clear_error(points: Any) -> None:
    try:
        projection = dmlo_rs.project(points, KITTI, num_threads=1)
    except CLEAR_ERRORS as err:
        event(f"refused: {type(err).__name__}")
        return
    event("result")
    n = len(points)
    assert projection.range.shape == projection.index.shape == (KITTI.height, KITTI.width)
    assert np.all(np.isfinite(projection.range)) and np.all(projection.range >= 0)
    kept = projection.index[projection.index >= 0]
    assert np.all(kept < n) and len(np.unique(kept)) == len(kept)
    assert np.array_equal(projection.range > 0, projection.index >= 0)
    assert projection.num_non_finite + projection.num_out_of_view + len(kept) <= n


def plausible_or(plausible: st.SearchStrategy[Any], *adversarial: Any) -> st.SearchStrategy[Any]:
    """Mostly `plausible` values (9 in 10, so that valid inputs are common), else one of `adversarial`."""
    return st.sampled_from([False] * 9 + [True]).flatmap(lambda odd: st.sampled_from(adversarial) if odd else plausible)


def test_a_point_beyond_a_float32_range_is_out_of_view() -> None:
    """Found by the property above: finite coordinates near float32's largest gave an infinite range."""
    points = np.array([[3.4e38, 3.4e38, 0.0, 0.5], [10.0, 0.0, 0.0, 0.5]], dtype=np.float32)
    projection = dmlo_rs.project(points, KITTI, num_threads=1)
    assert np.all(np.isfinite(projection.range))
    assert (np.count_nonzero(projection.index >= 0), projection.num_out_of_view) == (1, 1)


@fast(40)
@given(
    fov_up=plausible_or(st.floats(-5, 30), math.nan, math.inf, 90.0, 91.0, 1e300),
    fov_span=plausible_or(st.floats(1, 40), math.nan, -math.inf, 0.0, -1.0, 180.0, 181.0),
    vertical=plausible_or(st.floats(0.1, 2.0), 0.0, -0.4, math.nan, math.inf, 1e-300, 1e-7),
    horizontal=plausible_or(st.floats(0.1, 5.0), 0.0, -0.2, math.nan, 180.0, 181.0, 1e-5),
    height=plausible_or(st.floats(0.0, 1.0), 0, -1, 2**31, 2**63 - 1, 2**64),  # a float: a share of the grid's rows
    width=plausible_or(st.floats(0.0, 1.0), 0, -2, 30_000_000, 2**40),
    points=scans(200),
)
def test_cylinder_configs_are_valid_or_refused(
    fov_up: float, fov_span: float, vertical: float, horizontal: float, height: float, width: float, points: Any
) -> None:
    fov_down = fov_up - fov_span
    with np.errstate(all="ignore"):
        if isinstance(height, float):
            rows = fov_span / vertical + 1 if vertical > 0 else 1
            height = int(max(1, height * rows)) if math.isfinite(rows) else 1
        if isinstance(width, float):
            columns = 360 / horizontal if horizontal > 0 else 1
            width = int(max(1, width * columns)) if math.isfinite(columns) else 1
    try:
        config = dmlo_rs.CylinderConfig(
            fov_up_deg=fov_up, fov_down_deg=fov_down, vertical_resolution_deg=vertical,
            horizontal_resolution_deg=horizontal, height=height, width=width,
        )
    except (*CLEAR_ERRORS, OverflowError) as err:  # pyo3 refuses an int beyond the Rust type as OverflowError
        event(f"refused: {type(err).__name__}")
        return
    event("config")
    assert 1 <= config.height <= config.full_height and 1 <= config.width <= config.full_width
    assert config.height * config.width <= 2**26
    try:
        projection = dmlo_rs.project(points, config, num_threads=1)
    except CLEAR_ERRORS:
        return
    event("projected")
    kept = projection.index[projection.index >= 0]
    assert projection.range.shape == (config.height, config.width)
    assert np.all(kept < len(points)) and len(np.unique(kept)) == len(kept)


@st.composite
def point_pairs(draw: st.DrawFn) -> tuple[Any, Any, np.ndarray | None]:
    """Pairs `dst ≈ T·src` (N×3) of many scales and offsets, degenerate ones (one point, collinear,
    coplanar), some values corrupted or some pairs outliers; sometimes arrays that are no point sets.
    Returns (src, dst, outlier mask or None)."""
    if draw(st.integers(0, 6)) == 0:
        return draw(scans(40)), draw(scans(40)), None
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    n = draw(plausible_or(st.integers(3, 60), 0, 1, 2))
    scale = draw(st.sampled_from([1e-3, 1.0, 10.0, 10.0, 1e3, 1e100]))
    offset = draw(st.sampled_from([0.0, 0.0, 1e6, 5e6, 1e7]))
    src = rng.uniform(-scale, scale, (n, 3)) + offset
    shape = draw(st.sampled_from(["general", "general", "general", "one point", "collinear", "coplanar"]))
    if shape == "one point":
        src[:] = src[:1] if n else src
    elif shape == "collinear":
        src = offset + np.outer(rng.uniform(-scale, scale, n), rng.normal(size=3))
    elif shape == "coplanar":
        src[:, 2] = offset
    truth = random_rigid(int(rng.integers(2**16)))
    dst = src @ truth[:3, :3].T + truth[:3, 3]
    outliers = rng.random(n) < draw(st.sampled_from([0.0, 0.0, 0.2, 0.6]))
    dst[outliers] += rng.uniform(1, 20, (int(outliers.sum()), 3))
    if draw(st.integers(0, 4)) == 0:  # a few corrupted values in either array
        target = draw(st.sampled_from([src, dst]))
        target[rng.random(target.shape) < 0.05] = draw(st.sampled_from(ADVERSARIAL))
    dtype = draw(st.sampled_from([np.float64, np.float64, np.float32]))
    return src.astype(dtype), dst.astype(dtype), outliers


@fast(60)
@given(pair=point_pairs(), weights=plausible_or(st.sampled_from([None, "random"]), "zeros", "nan", "negative", "short"))
def test_rigid_transform_is_rigid_or_a_clear_error(pair: tuple[Any, Any, Any], weights: str | None) -> None:
    src, dst, _ = pair
    n = len(src) if np.ndim(src) else 0
    w = {
        None: None, "random": np.random.default_rng(n).random(n), "zeros": np.zeros(n), "nan": np.full(n, np.nan),
        "negative": -np.ones(n), "short": np.ones(max(n - 1, 0)),
    }[weights]
    try:
        transform = dmlo_rs.rigid_transform(src, dst, w)
    except CLEAR_ERRORS as err:
        event(f"refused: {type(err).__name__}")
        return
    event("result")
    assert_rigid(transform)


@fast(25)
@given(
    n=st.integers(3, 60), seed=st.integers(0, 2**16),
    offset=st.sampled_from([0.0, 1e3, 1e6, 5e6]), outliers=st.floats(0.0, 0.3),
)
def test_rigid_transform_and_ransac_recover_a_motion_anywhere(n: int, seed: int, offset: float, outliers: float) -> None:
    """Exact pairs (and, for RANSAC, a share of outliers), even at UTM-like offsets (issue 25, item 8)."""
    truth = random_rigid(seed)
    src = well_conditioned(n, seed) + offset
    dst = src @ truth[:3, :3].T + truth[:3, 3]
    solved = dmlo_rs.rigid_transform(src, dst)
    assert np.allclose(solved @ np.append(src[0], 1.0), np.append(dst[0], 1.0), atol=1e-4 * max(1.0, offset / 1e4))
    bad = np.random.default_rng(seed).random(n) < outliers
    assume(np.count_nonzero(~bad) >= 3)
    dst[bad] += np.random.default_rng(seed + 1).uniform(5, 20, (np.count_nonzero(bad), 3))
    result = dmlo_rs.ransac_rigid(src, dst, threshold=0.05, max_iterations=300, num_threads=1)
    assert result.num_inliers == np.count_nonzero(result.inliers) >= np.count_nonzero(~bad)
    assert not np.any(result.inliers & bad)


@fast(80)
@given(
    pair=point_pairs(),
    threshold=plausible_or(st.floats(1e-3, 1.0), 0.0, -1.0, math.nan, math.inf, 1e300),
    confidence=plausible_or(st.floats(0.5, 0.9999), 0.0, 1.0, 1.5, -0.1, math.nan),
    # Not 2**63: a valid bound that RANSAC honours on data without a consensus (minutes per 10**7 hypotheses)
    max_iterations=plausible_or(st.integers(1, 300), 0, -1, 2**64 + 5),
    seed=plausible_or(st.integers(0, 2**32), -1, 2**64),
    refit=plausible_or(st.sampled_from(["point_to_point", "ray_noise"]), "nonsense", ""),
    refine_iterations=plausible_or(st.integers(0, 10), -1, 2**64),
    votes=plausible_or(st.sampled_from([None, "random"]), "zeros", "nan", "negative", "short"),
)
def test_ransac_gives_a_consistent_result_or_a_clear_error(
    pair: tuple[Any, Any, Any], threshold: float, confidence: float, max_iterations: int, seed: int, refit: str,
    refine_iterations: int, votes: str | None,
) -> None:
    src, dst, outliers = pair
    n = len(src) if np.ndim(src) else 0
    weights = {
        None: None, "random": np.random.default_rng(n).random(n), "zeros": np.zeros(n), "nan": np.full(n, np.nan),
        "negative": -np.ones(n), "short": np.ones(max(n - 1, 0)),
    }[votes]
    try:
        result = dmlo_rs.ransac_rigid(
            src, dst, threshold, confidence, max_iterations, seed, refine_iterations=refine_iterations,
            refit=refit, votes=weights, num_threads=1,  # type: ignore[arg-type]
        )
    except CLEAR_ERRORS as err:
        event(f"refused: {type(err).__name__}")
        return
    event("result")
    assert_rigid(result.transform)
    assert result.inliers.shape == (n,) and result.num_inliers == np.count_nonzero(result.inliers)
    assert 1 <= result.num_inliers <= n
    assert math.isfinite(result.rmse) and result.rmse >= 0
    if refit == "point_to_point":  # every inlier lies within the threshold of the answer
        assert result.rmse <= threshold * (1 + 1e-6) + 1e-9
    assert 0 <= result.iterations <= max(max_iterations, 1)


# ---------------------------------------------------------------------------------------------------------
# The odometry: `Odometry.register` and `register_pair` on corrupted real-looking scans (the network runs:
# few examples)


@pytest.fixture(scope="module")
def simulated_scans(tmp_path_factory: pytest.TempPathFactory) -> list[np.ndarray]:
    from dmlo.datasets import open_sequence
    from dmlo.simulator import simulate_sequence

    out = tmp_path_factory.mktemp("property_drive")
    simulate_sequence(out, frames=2, seed=3, progress=False)
    sequence = open_sequence(out)
    return [sequence[i].points for i in range(2)]


@st.composite
def corrupted(draw: st.DrawFn, base: np.ndarray) -> Any:
    """A simulated scan, thinned, with some of its values replaced by adversarial ones, rescaled,
    retyped, or cut to a shape that is not a scan."""
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    keep = draw(plausible_or(st.sampled_from([3000, 20000]), 0, 10, 999, 1000))
    scan = base[rng.permutation(len(base))[: min(keep, len(base))]].astype(np.float64)
    share = draw(plausible_or(st.sampled_from([0.0, 0.01]), 0.3, 1.0))
    value = draw(st.sampled_from(ADVERSARIAL))
    scan[rng.random(scan.shape) < share] = value
    with np.errstate(all="ignore"):  # inf × 0
        scan[:, :3] *= draw(plausible_or(st.just(1.0), 1e-3, 1e3, 1e7))
        scan[:, 3] *= draw(plausible_or(st.sampled_from([1.0, 255.0, 0.0]), -1.0, 1e9))
    form = draw(plausible_or(st.sampled_from(["float32", "float64", "xyz"]), "int", "rows", "list"))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if form == "float32":
            return scan.astype(np.float32)
        if form == "xyz":
            return scan[:, :3].astype(np.float32)
        if form == "int":
            return np.nan_to_num(scan).astype(np.int32)
        if form == "rows":
            return scan.T.astype(np.float32)
        if form == "list":
            return scan[:50].tolist()
    return scan


@fast(10)
@given(data=st.data())
def test_register_gives_a_pose_or_a_clear_error(simulated_scans: list[np.ndarray], data: st.DataObject) -> None:
    odometry = Odometry.from_default()
    for index in range(3):
        scan = data.draw(corrupted(simulated_scans[min(index, 1)]), label=f"scan {index}")
        before = len(odometry.poses)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # reflectance notices, sensor-mismatch warnings
            try:
                pose = odometry.register(scan)
            except CLEAR_ERRORS as err:
                event(f"refused: {type(err).__name__}")
                assert len(odometry.poses) == before  # a refused scan leaves no trace
                continue
        event("registered" if odometry.diagnostics[-1].fallback is None else f"fallback {odometry.diagnostics[-1].fallback}")
        assert_rigid(np.asarray(pose))
        assert len(odometry.poses) == len(odometry.diagnostics) == before + 1


@fast(8)
@given(data=st.data(), large_motion=st.booleans())
def test_register_pair_gives_a_motion_or_a_clear_error(
    simulated_scans: list[np.ndarray], data: st.DataObject, large_motion: bool
) -> None:
    reference = data.draw(corrupted(simulated_scans[0]), label="reference")
    target = data.draw(corrupted(simulated_scans[1]), label="target")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            result = Odometry.from_default().register_pair(reference, target, large_motion=large_motion)
        except CLEAR_ERRORS as err:
            event(f"refused: {type(err).__name__}")
            return
    event("result")
    assert_rigid(np.asarray(result.T_tgt_ref))
    assert 0 <= result.num_inliers <= result.num_matches


# ---------------------------------------------------------------------------------------------------------
# The config loader

json_values = st.recursive(
    st.one_of(
        st.none(), st.booleans(), st.integers(-(2**70), 2**70), st.floats(), st.text(max_size=8),
        st.sampled_from(["false", "true", "0", "1e3", "nan", "auto", "crate", "unit", "none"]),
    ),
    lambda children: st.one_of(st.lists(children, max_size=4), st.dictionaries(st.text(max_size=6), children, max_size=3)),
    max_leaves=8,
)


def _paths(tree: dict[str, Any], prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    found = []
    for key, value in tree.items():
        found.append((*prefix, key))
        if isinstance(value, dict):
            found.extend(_paths(value, (*prefix, key)))
    return found


DEFAULTS = OdometryConfig().to_dict()
KEY_PATHS = _paths(DEFAULTS)


def like(default: Any) -> st.SearchStrategy[Any]:
    """Values of the default's own type, in and out of range (so that more configs get past the types)."""
    if isinstance(default, bool):
        return st.booleans()
    if isinstance(default, int):
        return st.one_of(st.integers(-3, 5000), st.sampled_from([0, 1, 2**31, 2**63, -(2**63) - 1, 10**30]))
    if isinstance(default, float):
        return st.one_of(st.floats(-1.0, 100.0), st.sampled_from([0.0, 1.0, 1e-300, 1e300, math.nan, math.inf, -math.inf]))
    if isinstance(default, str):
        return st.sampled_from(["auto", "crate", "graph", "unit", "0-255", "0-65535", "none", "ray_noise", "point_to_point", "", "AUTO"])
    if isinstance(default, list):
        return st.lists(st.one_of(st.floats(-20, 20), st.sampled_from([math.nan, 1e300])), max_size=6)
    return json_values


@st.composite
def configs(draw: st.DrawFn) -> Any:
    """The default config with some keys given random JSON values, deleted or added; or any JSON value."""
    if draw(st.integers(0, 9)) == 0:
        return draw(json_values)
    config = json.loads(json.dumps(DEFAULTS))
    for _ in range(draw(plausible_or(st.just(1), 2, 4))):
        path = draw(st.sampled_from(KEY_PATHS))
        parent = config
        for key in path[:-1]:
            parent = parent.get(key) if isinstance(parent, dict) else None
        if not isinstance(parent, dict):
            continue
        action = draw(st.sampled_from(["typed", "typed", "value", "delete", "unknown"]))
        if action == "typed":
            parent[path[-1]] = draw(like(parent.get(path[-1])))
        elif action == "value":
            parent[path[-1]] = draw(json_values)
        elif action == "delete":
            parent.pop(path[-1], None)
        else:
            parent[draw(st.text(min_size=1, max_size=6))] = draw(json_values)
    return config


@fast(150)
@given(data=configs())
def test_config_loader_gives_a_config_or_a_clear_error(data: Any) -> None:
    try:
        config = OdometryConfig.from_dict(data)
    except ValueError as err:
        event(f"refused: {type(err).__name__}")
        return
    event("result")
    assert isinstance(config, OdometryConfig)
    assert OdometryConfig.from_dict(config.to_dict()) == config  # what a run saves reads back the same


@fast(40)
@given(text=st.one_of(st.binary(max_size=200), configs().map(lambda c: json.dumps(c).encode())))
def test_config_files_load_or_give_a_clear_error(tmp_path: Path, text: bytes) -> None:
    path = tmp_path / "config.json"
    path.write_bytes(text)
    try:
        OdometryConfig.load(path)
    except ValueError:
        pass


# ---------------------------------------------------------------------------------------------------------
# Pose files and `dmlo eval`

NUMBERS = ["0", "1", "-1", "0.5", "1e-9", "1e308", "1e400", "-1e400", "nan", "inf", "-inf", "0x10", "1_0", "abc", "1,2", ",", "∞", "１"]


def damaged(line: str, draw: st.DrawFn) -> str:
    """A pose line with a token replaced, dropped or added."""
    tokens = line.split()
    token = draw(st.sampled_from(NUMBERS))
    position = draw(st.integers(0, len(tokens)))
    action = draw(st.sampled_from(["replace", "drop", "add"]))
    if action == "replace" and position < len(tokens):
        tokens[position] = token
    elif action == "drop" and position < len(tokens):
        del tokens[position]
    else:
        tokens.insert(position, token)
    return draw(st.sampled_from([" ", "\t", ", "])).join(tokens)


@st.composite
def pose_file_pair(draw: st.DrawFn) -> tuple[str, str]:
    """Two pose files, KITTI or TUM, of poses along a random drive: mostly the same number of poses, now
    and then a line damaged, comments and blank lines between; or bytes of no format at all."""
    texts = []
    n = draw(plausible_or(st.integers(1, 25), 0, 40))
    for _ in range(2):
        if draw(plausible_or(st.just(False), True)):
            texts.append(draw(st.binary(max_size=120)).decode("latin-1"))
            continue
        fmt = draw(st.sampled_from(["kitti", "tum"]))
        count = n if draw(plausible_or(st.just(True), False)) else draw(st.integers(0, 30))
        seed = draw(st.integers(0, 2**16))
        motions = np.stack([random_rigid(seed + i, 2.0) for i in range(count - 1)]) if count > 1 else np.zeros((0, 4, 4))
        poses = pose_files.accumulate_motions(motions)[:count]
        lines = []
        for index, pose in enumerate(poses):
            if draw(plausible_or(st.just(False), True)):
                lines.append(draw(st.sampled_from(["", "# a comment", "   "])))
            if fmt == "kitti":
                values = pose[:3].reshape(-1).tolist()
            else:
                values = [index * 0.1, *pose[:3, 3], *pose_files.matrix_to_quaternion(pose[:3, :3])[0]]
            lines.append(" ".join(repr(float(v)) for v in values))
        if lines and draw(plausible_or(st.just(False), True)):
            at = draw(st.integers(0, len(lines) - 1))
            lines[at] = damaged(lines[at], draw)
        texts.append("\n".join(lines))
    return texts[0], texts[1]


pose_file_texts = pose_file_pair().map(lambda pair: pair[0])


@fast(150)
@given(text=pose_file_texts)
def test_pose_readers_give_poses_or_a_clear_error(tmp_path: Path, text: str) -> None:
    path = tmp_path / "poses.txt"
    path.write_bytes(text.encode("utf-8", "surrogatepass"))
    for reader in (pose_files.read_kitti_poses, pose_files.read_tum_poses, pose_files.read_poses, pose_files.read_kitti_calib):
        try:
            result = reader(path)
        except ValueError as err:  # PoseFileError among them
            event(f"{reader.__name__} refused: {type(err).__name__}")
            continue
        event(f"{reader.__name__} read")
        if reader is pose_files.read_kitti_calib:
            assert all(matrix.shape == (4, 4) and np.all(np.isfinite(matrix)) for matrix in result.values())
            continue
        array = result[1] if isinstance(result, tuple) else result
        assert array.ndim == 3 and array.shape[1:] == (4, 4) and len(array) >= 1
        assert np.all(np.isfinite(array))
        rotations = array[:, :3, :3]
        assert np.allclose(np.einsum("nji,njk->nik", rotations, rotations), np.eye(3), atol=1e-2)


@fast(30)
@given(n=st.integers(1, 20), seed=st.integers(0, 2**16), fmt=st.sampled_from(["kitti", "tum"]))
def test_pose_files_round_trip(tmp_path: Path, n: int, seed: int, fmt: str) -> None:
    poses = pose_files.accumulate_motions(np.stack([random_rigid(seed + i) for i in range(n - 1)]) if n > 1 else [])
    timestamps = np.arange(n) * 0.1 + seed
    pose_files.write_poses(tmp_path / "p.txt", poses, fmt, timestamps)  # type: ignore[arg-type]
    stamps, read = pose_files.read_poses(tmp_path / "p.txt")
    np.testing.assert_allclose(read, poses, atol=1e-6 * max(1.0, np.abs(poses).max()))
    if fmt == "tum":
        np.testing.assert_allclose(stamps, timestamps, atol=1e-6)  # type: ignore[arg-type]


@fast(40)
@given(
    files=pose_file_pair(),
    extra=plausible_or(st.sampled_from([[], ["--align", "sim3"], ["--align", "none"], ["--delta", "3"]]), ["--delta", "0"], ["--delta", "100"]),
)
def test_eval_gives_metrics_or_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], files: tuple[str, str], extra: list[str]
) -> None:
    ground_truth, estimate = files
    gt, est = tmp_path / "gt.txt", tmp_path / "est.txt"
    gt.write_bytes(ground_truth.encode("utf-8", "surrogatepass"))
    est.write_bytes(estimate.encode("utf-8", "surrogatepass"))
    capsys.readouterr()
    code = main(["eval", str(gt), str(est), "--json", *extra])
    out, err = capsys.readouterr()
    event(f"exit {code}")
    if code == 0:
        assert json.loads(out)["poses"] >= 1
    else:
        assert code == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err


def test_eval_refuses_poses_beyond_any_drive_instead_of_spinning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Found by the property above: a translation of 1e308 (finite, so read) made the alignment's SVD
    spin forever on the infinities of its covariance."""
    path = tmp_path / "poses.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1e308 0 1 0 0 0 0 1 0\n1 0 0 2 0 1 0 0 0 0 1 0\n")
    assert main(["eval", str(path), str(path)]) == 2
    assert "poses_gt: pose 1 lies 1e+308 m from the origin" in capsys.readouterr().err
    from dmlo.metrics.trajectory import umeyama_alignment

    with pytest.raises(ValueError, match="covariance overflows"):
        umeyama_alignment([[0, 0, 0], [1e200, 0, 0]], [[0, 0, 0], [1e200, 0, 0]])
