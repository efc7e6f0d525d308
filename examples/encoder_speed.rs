//! Times the network's encoder run by tract on one real scan (feature `inference`), for
//! `benchmarks/encoder_runtimes.py`, which times onnxruntime on the same scan in the same run.
//!
//! ```text
//! cargo run --release --features inference --example encoder_speed -- ENCODER.onnx SCAN.bin [REPEATS]
//! ```
//!
//! Prints one JSON line: the median and fastest encode in milliseconds and rayon's thread count.

use std::process::ExitCode;

use dmlo_rs::inference::{Encoder, TractEncoder};
use dmlo_rs::projection::{project_flat, CylinderConfig};

fn run(args: &[String]) -> Result<String, String> {
    let [encoder, scan, rest @ ..] = args else {
        return Err("usage: encoder_speed ENCODER.onnx SCAN.bin [REPEATS]".into());
    };
    let repeats: usize = match rest.first() {
        Some(text) => text
            .parse()
            .map_err(|_| format!("REPEATS: not a count: {text}"))?,
        None => 20,
    };
    let bytes = std::fs::read(scan).map_err(|e| format!("{scan}: {e}"))?;
    if bytes.len() % 16 != 0 {
        return Err(format!("{scan}: {} bytes, not N × 4 float32", bytes.len()));
    }
    let points: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let projection =
        project_flat(&points, 4, &CylinderConfig::kitti()).map_err(|e| e.to_string())?;
    let image = [projection.range, projection.reflectance].concat();
    let encoder = TractEncoder::open(encoder).map_err(|e| e.to_string())?;
    for _ in 0..3 {
        encoder.encode(&image).map_err(|e| e.to_string())?;
    }
    let mut times = Vec::with_capacity(repeats);
    for _ in 0..repeats.max(1) {
        let start = std::time::Instant::now();
        encoder.encode(&image).map_err(|e| e.to_string())?;
        times.push(start.elapsed().as_secs_f64() * 1000.0);
    }
    times.sort_by(f64::total_cmp);
    Ok(format!(
        "{{\"median_ms\": {:.3}, \"min_ms\": {:.3}, \"threads\": {}}}",
        times[times.len() / 2],
        times[0],
        rayon::current_num_threads()
    ))
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match run(&args) {
        Ok(line) => {
            println!("{line}");
            ExitCode::SUCCESS
        }
        Err(message) => {
            eprintln!("encoder_speed: {message}");
            ExitCode::FAILURE
        }
    }
}
