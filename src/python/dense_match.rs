//! Binding of the network's matching stage on cached features (`dmlo_rs.match_features`).

use numpy::{
    IntoPyArray, PyArray2, PyArray3, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::dense_match::{
    self, DenseMatchConfig, FeatureMap, OffsetRule, ScanFeatures, NETWORK_STRIDE,
};

use super::convert::{count, floats, flow_array, image_array, shape_error, Floats, Int};
use super::pool::{run, threads};

/// Flow `[2, H, W]` and confidence `[H, W]` as numpy arrays.
type FlowArrays<'py> = (Bound<'py, PyArray3<f32>>, Bound<'py, PyArray2<f32>>);

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(match_features, m)?)?;
    Ok(())
}

/// A feature array as the network outputs it, `(1, C, h, w)` or `(C, h, w)` float32/float64, and its
/// `(C, h, w)`.
fn feature_array<'py>(name: &str, obj: &Bound<'py, PyAny>) -> PyResult<(Floats<'py>, [usize; 3])> {
    let array = floats(name, obj)?;
    let shape = match *array.shape() {
        [1, c, h, w] | [c, h, w] => [c, h, w],
        ref other => return Err(shape_error(name, "(1, C, h, w) or (C, h, w)", other)),
    };
    Ok((array, shape))
}

fn offset_rule(name: &str) -> PyResult<OffsetRule> {
    OffsetRule::from_name(name).ok_or_else(|| {
        PyValueError::new_err(format!(
            "refine_offset: expected 'window' or 'peak_centroid', got {name:?}"
        ))
    })
}

/// The network's matching stage on the CPU: the flow of every reference cell into the target and its
/// confidence, from both scans' cached features (what `match.onnx` computes, `Matcher.match` in
/// `dmlo.model`). Features `(1, C, h, w)` or `(C, h, w)`: coarse at `stride`, refine at full resolution.
/// `coarse_scale` / `refine_scale` are the model's learned softmax temperatures (`exp` of its log
/// scales); `refine_offset` is "window" (Eq. 11) or "peak_centroid"; `stride` (rows, cols) of the coarse
/// features, None: the network's 4 × 8. `cells` (bool `[H, W]`): match only the marked reference cells
/// (the others get a NaN flow and confidence 0); None: every cell. `guide` (float32 `[H, W, 2]`): each
/// cell's expected flow (Δrow, Δcol; NaN: none), e.g. where a predicted motion takes the cell's point;
/// each coarse window is then centred where its block's cells are expected to land (their median), so
/// that the flow may exceed the window; None: every window centred on its own cell.
/// → (flow float32 `[2, H, W]` (Δrow, Δcol), confidence float32 `[H, W]`).
#[pyfunction]
#[pyo3(signature = (ref_coarse, ref_refine, tgt_coarse, tgt_refine, *, coarse_window, refine_window,
                    coarse_scale, refine_scale, refine_offset = "window", stride = None,
                    cells = None, guide = None, num_threads = None))]
#[allow(clippy::too_many_arguments)]
fn match_features<'py>(
    py: Python<'py>,
    ref_coarse: &Bound<'py, PyAny>,
    ref_refine: &Bound<'py, PyAny>,
    tgt_coarse: &Bound<'py, PyAny>,
    tgt_refine: &Bound<'py, PyAny>,
    coarse_window: Int,
    refine_window: Int,
    coarse_scale: f32,
    refine_scale: f32,
    refine_offset: &str,
    stride: Option<(Int, Int)>,
    cells: Option<PyReadonlyArray2<'py, bool>>,
    guide: Option<PyReadonlyArray3<'py, f32>>,
    num_threads: Option<Int>,
) -> PyResult<FlowArrays<'py>> {
    let coarse_window = count("coarse_window", coarse_window)?;
    let refine_window = count("refine_window", refine_window)?;
    let stride = match stride {
        Some((rows, cols)) => [count("stride", rows)?, count("stride", cols)?],
        None => NETWORK_STRIDE,
    };
    let config = DenseMatchConfig {
        coarse_window,
        refine_window,
        stride,
        coarse_scale,
        refine_scale,
        refine_offset: offset_rule(refine_offset)?,
    };
    let arrays = [
        feature_array("ref_coarse", ref_coarse)?,
        feature_array("ref_refine", ref_refine)?,
        feature_array("tgt_coarse", tgt_coarse)?,
        feature_array("tgt_refine", tgt_refine)?,
    ];
    let data: Vec<_> = arrays.iter().map(|(array, _)| array.f32_data()).collect();
    let maps: Vec<FeatureMap<'_>> = data
        .iter()
        .zip(&arrays)
        .map(|(values, (_, [channels, height, width]))| FeatureMap {
            data: values,
            channels: *channels,
            height: *height,
            width: *width,
        })
        .collect();
    let reference = ScanFeatures {
        coarse: maps[0],
        refine: maps[1],
    };
    let target = ScanFeatures {
        coarse: maps[2],
        refine: maps[3],
    };
    let [_, height, width] = arrays[1].1;
    let marks = match &cells {
        Some(cells) if cells.shape() != [height, width] => {
            return Err(shape_error(
                "cells",
                &format!("({height}, {width}) bool"),
                cells.shape(),
            ))
        }
        Some(cells) => Some(cells.as_array().iter().copied().collect::<Vec<bool>>()),
        None => None,
    };
    let expected = match &guide {
        Some(guide) if guide.shape() != [height, width, 2] => {
            return Err(shape_error(
                "guide",
                &format!("({height}, {width}, 2) float32"),
                guide.shape(),
            ))
        }
        Some(guide) => {
            let values: Vec<f32> = guide.as_array().iter().copied().collect();
            Some(
                values
                    .chunks_exact(2)
                    .map(|pair| [pair[0], pair[1]])
                    .collect::<Vec<[f32; 2]>>(),
            )
        }
        None => None,
    };
    let result = run(py, threads(num_threads)?, || match (&marks, &expected) {
        (_, Some(expected)) => dense_match::match_features_guided(
            &reference,
            &target,
            &config,
            marks.as_deref(),
            expected,
        ),
        (Some(marks), None) => {
            dense_match::match_features_of_cells(&reference, &target, &config, marks)
        }
        (None, None) => dense_match::match_features(&reference, &target, &config),
    })?;
    let (height, width) = (result.height, result.width);
    let flow = flow_array(height, width, result.flow)?;
    let confidence = image_array(height, width, result.confidence)?;
    Ok((flow.into_pyarray(py), confidence.into_pyarray(py)))
}
