//! A file that is not the onnxruntime shared library, given to `OrtEncoder::open`: `ort` panics on it, the
//! crate names it. In a process of its own (an integration test binary): `ort` keeps the first library path a
//! process gives it.
#![cfg(feature = "onnxruntime")]

use std::path::PathBuf;

use dmlo_rs::inference::OrtEncoder;

#[test]
fn inference_from_a_file_that_is_not_onnxruntime_is_a_named_error() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let encoder = root.join("python/dmlo/models/default/encoder.onnx");
    let error = OrtEncoder::open(&encoder, root.join("Cargo.toml"), 0).unwrap_err();
    let message = error.to_string();
    assert!(
        message.contains("Cargo.toml: not an onnxruntime library ort can use"),
        "{message}"
    );
}
