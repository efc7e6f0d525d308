//! Times the network's encoder run from Rust on one real scan — by tract (feature `inference`), or with
//! `--onnxruntime LIB` by onnxruntime through `ort` (feature `onnxruntime`, on `THREADS` intra-op threads) — for
//! `benchmarks/encoder_runtimes.py`, which times Python's onnxruntime on the same scan in the same run.
//!
//! ```text
//! cargo run --release --features inference,onnxruntime --example encoder_speed -- \
//!     ENCODER.onnx SCAN.bin [REPEATS] [--onnxruntime LIB THREADS]
//! ```
//!
//! Prints one JSON line: the median and fastest encode in milliseconds and rayon's thread count.

use std::process::ExitCode;

use dmlo_rs::inference::{Encoder, TractEncoder};
use dmlo_rs::projection::{project_flat, CylinderConfig};

const USAGE: &str =
    "usage: encoder_speed ENCODER.onnx SCAN.bin [REPEATS] [--onnxruntime LIB THREADS]";

fn run(args: &[String]) -> Result<String, String> {
    let (args, onnxruntime) = match args.iter().position(|a| a == "--onnxruntime") {
        Some(at) => match &args[at..] {
            [_, library, threads] => {
                let threads: usize = threads
                    .parse()
                    .map_err(|_| format!("THREADS: not a count: {threads}"))?;
                (&args[..at], Some((library.clone(), threads)))
            }
            _ => return Err(USAGE.into()),
        },
        None => (args, None),
    };
    let [encoder, scan, rest @ ..] = args else {
        return Err(USAGE.into());
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
    match onnxruntime {
        None => {
            let encoder = TractEncoder::open(encoder).map_err(|e| e.to_string())?;
            time_encodes(&encoder, &image, repeats)
        }
        Some((library, threads)) => {
            onnxruntime_encodes(encoder, &library, threads, &image, repeats)
        }
    }
}

#[cfg(feature = "onnxruntime")]
fn onnxruntime_encodes(
    encoder: &str,
    library: &str,
    threads: usize,
    image: &[f32],
    repeats: usize,
) -> Result<String, String> {
    let encoder = dmlo_rs::inference::OrtEncoder::open(encoder, library, threads)
        .map_err(|e| e.to_string())?;
    time_encodes(&encoder, image, repeats)
}

#[cfg(not(feature = "onnxruntime"))]
fn onnxruntime_encodes(_: &str, _: &str, _: usize, _: &[f32], _: usize) -> Result<String, String> {
    Err("--onnxruntime: built without the `onnxruntime` feature".into())
}

/// The median and fastest of `repeats` encodes of `image`, after three to warm up.
fn time_encodes(encoder: &impl Encoder, image: &[f32], repeats: usize) -> Result<String, String> {
    for _ in 0..3 {
        encoder.encode(image).map_err(|e| e.to_string())?;
    }
    let mut times = Vec::with_capacity(repeats);
    for _ in 0..repeats.max(1) {
        let start = std::time::Instant::now();
        encoder.encode(image).map_err(|e| e.to_string())?;
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
