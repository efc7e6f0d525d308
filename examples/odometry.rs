//! DMLO odometry over a folder of KITTI `.bin` scans from Rust alone, no Python (feature `inference`):
//! the network's encoder run by tract (or with `--onnxruntime LIB` by the onnxruntime shared library `LIB`,
//! feature `onnxruntime`), the crate's matching stage and [`dmlo_rs::odometry::pipeline::Odometry`] (the
//! motion model, matching from the prediction, the local map), writing the poses as `dmlo run` does.
//!
//! ```text
//! cargo run --release --features inference --example odometry -- SCANS_DIR --out OUT_DIR \
//!     [--model MODEL_DIR] [--config CONFIG.json] [--threads N] [--onnxruntime LIB] [--encode-ahead]
//! ```
//!
//! `SCANS_DIR` holds the scans (`*.bin`, N × 4 float32: x, y, z, reflectance), registered in name
//! order. `MODEL_DIR` (default `python/dmlo/models/default`) holds `encoder.onnx` (with `frame_wide.onnx`
//! beside it: its wide window for pairs re-matched from the prediction; with `range_only/encoder.onnx`:
//! the range-only model for scans without usable reflectance; with `moving.onnx`: the moving-object
//! network, whose flagged points are left out as `dmlo run` leaves them out, unless the config's
//! `moving_objects.detect` is false); `CONFIG.json` is a
//! config as `dmlo run` writes it (default: the defaults). `OUT_DIR` gets `poses_kitti.txt`
//! (`T_world_lidar`, the first scan the world: one row of 12 numbers a scan, readable by evo) and
//! `diagnostics.jsonl` (one JSON object a scan), both appended and flushed scan by scan, so an interrupted
//! run keeps every scan done. `--threads` sizes rayon's pool (tract and the crate's stages) and onnxruntime's
//! threads; 0 or absent: the config's `threads`, and when that is 0 the runtimes' defaults.
//! `--encode-ahead` encodes each scan on a thread of its own while the scan before it is registered
//! ([`dmlo_rs::odometry::pipeline::EncodeAhead`]: the same poses): faster where the odometry's stages leave
//! cores idle (fewer `--threads` than cores), not when they use every core; the moving-object network flags
//! the scan on that thread too.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use dmlo_rs::inference::{
    graph_metadata, Encoder, LearnedMatcher, TractEncoder, TractMovingObjects,
};
use dmlo_rs::odometry::config::OdometryConfig;
use dmlo_rs::odometry::motion::Fallback;
use dmlo_rs::odometry::moving::MovingObjectNetwork;
use dmlo_rs::odometry::pipeline::{EncodeAhead, Odometry, Scan};
use dmlo_rs::scan_file::{kitti_scan_files, read_kitti_scan};

const USAGE: &str = "usage: odometry SCANS_DIR --out OUT_DIR [--model MODEL_DIR] [--config CONFIG.json] [--threads N] [--onnxruntime LIB] [--encode-ahead]";

struct Arguments {
    scans: PathBuf,
    out: PathBuf,
    model: PathBuf,
    config: Option<PathBuf>,
    threads: Option<usize>,
    onnxruntime: Option<PathBuf>,
    encode_ahead: bool,
}

fn parse(args: &[String]) -> Result<Arguments, String> {
    let mut scans = None;
    let (mut out, mut model, mut config, mut threads, mut onnxruntime) =
        (None, None, None, None, None);
    let mut encode_ahead = false;
    let mut rest = args.iter();
    while let Some(arg) = rest.next() {
        let mut value = |flag: &str| {
            rest.next()
                .cloned()
                .ok_or(format!("{flag}: needs a value\n{USAGE}"))
        };
        match arg.as_str() {
            "--out" => out = Some(PathBuf::from(value("--out")?)),
            "--model" => model = Some(PathBuf::from(value("--model")?)),
            "--config" => config = Some(PathBuf::from(value("--config")?)),
            "--onnxruntime" => onnxruntime = Some(PathBuf::from(value("--onnxruntime")?)),
            "--encode-ahead" => encode_ahead = true,
            "--threads" => {
                let text = value("--threads")?;
                threads = Some(
                    text.parse()
                        .map_err(|e| format!("--threads: {text:?}: {e}"))?,
                );
            }
            flag if flag.starts_with("--") => {
                return Err(format!("unknown option {flag}\n{USAGE}"))
            }
            _ if scans.is_none() => scans = Some(PathBuf::from(arg)),
            _ => return Err(USAGE.into()),
        }
    }
    Ok(Arguments {
        scans: scans.ok_or(USAGE)?,
        out: out.ok_or(USAGE)?,
        model: model.unwrap_or_else(|| PathBuf::from("python/dmlo/models/default")),
        config,
        threads,
        onnxruntime,
        encode_ahead,
    })
}

fn kitti_row(pose: &nalgebra::Matrix4<f64>) -> String {
    let values: Vec<String> = (0..3)
        .flat_map(|row| (0..4).map(move |col| (row, col)))
        .map(|(row, col)| python_exponent(&format!("{:.9e}", pose[(row, col)])))
        .collect();
    values.join(" ")
}

/// Rust's `1.5e-3` written as Python's `%e` writes it (`1.5e-03`), so the files read alike.
fn python_exponent(text: &str) -> String {
    match text.split_once('e') {
        Some((mantissa, exponent)) => {
            let exponent: i32 = exponent.parse().expect("Rust writes an integer exponent");
            let sign = if exponent < 0 { '-' } else { '+' };
            format!("{mantissa}e{sign}{:02}", exponent.abs())
        }
        None => text.to_string(),
    }
}

/// The model in `folder` over `encoder` (its `encoder.onnx` opened by the runtime), with the wide window of
/// `frame_wide.onnx` beside it when there is one.
fn learned_matcher<E: Encoder + Send + Sync + 'static>(
    folder: &Path,
    encoder: impl Fn(&Path) -> dmlo_rs::Result<E>,
) -> dmlo_rs::Result<EncodeAhead<LearnedMatcher<E>>> {
    let mut matcher = LearnedMatcher::new(encoder(&folder.join("encoder.onnx"))?)?;
    let wide = folder.join("frame_wide.onnx");
    if wide.is_file() {
        matcher = matcher.with_wide_window(graph_metadata(&wide)?.coarse_window)?;
    }
    Ok(EncodeAhead::new(matcher))
}

fn run(args: &[String]) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    let arguments = parse(args)?;
    let config = match &arguments.config {
        Some(path) => OdometryConfig::load(path)?,
        None => OdometryConfig::default(),
    };
    let threads = arguments.threads.unwrap_or(config.threads as usize);
    // The loop runs on one of the pool's threads, so that each frame's parallel stages start from inside
    // the pool (the calling thread takes its share) rather than being sent to it and waited for.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    pool.install(|| match &arguments.onnxruntime {
        None => drive(
            &arguments,
            config,
            |path: &Path| TractEncoder::open(path),
            |path: &Path| TractMovingObjects::open(path),
        ),
        Some(library) => with_onnxruntime(&arguments, config, library, threads),
    })
}

#[cfg(feature = "onnxruntime")]
fn with_onnxruntime(
    arguments: &Arguments,
    config: OdometryConfig,
    library: &Path,
    threads: usize,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    use dmlo_rs::inference::{OrtEncoder, OrtMovingObjects};
    drive(
        arguments,
        config,
        |path: &Path| OrtEncoder::open(path, library, threads),
        |path: &Path| OrtMovingObjects::open(path, library, threads),
    )
}

#[cfg(not(feature = "onnxruntime"))]
fn with_onnxruntime(
    _: &Arguments,
    _: OdometryConfig,
    _: &Path,
    _: usize,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    Err("--onnxruntime: built without the `onnxruntime` feature (cargo run --features inference,onnxruntime …)".into())
}

/// The odometry over every scan of the folder, the encoders opened by `encoder` and the moving-object
/// network by `moving_objects`.
fn drive<E, N>(
    arguments: &Arguments,
    config: OdometryConfig,
    encoder: impl Fn(&Path) -> dmlo_rs::Result<E>,
    moving_objects: impl Fn(&Path) -> dmlo_rs::Result<N>,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>>
where
    E: Encoder + Send + Sync + 'static,
    N: MovingObjectNetwork + Send + Sync + 'static,
{
    let files = kitti_scan_files(&arguments.scans)?;
    let detect = config.moving_objects.detect;
    let mut odometry = Odometry::new(learned_matcher(&arguments.model, &encoder)?, config)?;
    let range_only = arguments.model.join("range_only");
    if range_only.join("encoder.onnx").is_file() {
        odometry = odometry.with_range_only(learned_matcher(&range_only, &encoder)?)?;
    }
    let moving = arguments.model.join("moving.onnx");
    if detect && moving.is_file() {
        odometry = odometry.with_moving_objects(moving_objects(&moving)?)?;
    }
    std::fs::create_dir_all(&arguments.out)?;
    let mut poses = BufWriter::new(File::create(arguments.out.join("poses_kitti.txt"))?);
    let mut diagnostics = BufWriter::new(File::create(arguments.out.join("diagnostics.jsonl"))?);
    let start = Instant::now();
    // Each scan is read before the one ahead of it is registered, so that with `--encode-ahead` its
    // encoding can overlap that scan's back end (`register_ahead`; without, one after the other).
    let mut next = files.first().map(|path| read_kitti_scan(path));
    for index in 0..files.len() {
        let scan = next.take().expect("read ahead");
        next = files.get(index + 1).map(|path| read_kitti_scan(path));
        let pose = match &scan {
            Ok(points) => {
                let ahead = match &next {
                    Some(Ok(points)) if arguments.encode_ahead => Some(Scan::new(points)),
                    _ => None,
                };
                odometry.register_ahead(Scan::new(points), ahead)?
            }
            Err(error) => {
                eprintln!("skipped: {error}");
                odometry.predict_skipped(Fallback::UnreadableScan)?
            }
        };
        writeln!(poses, "{}", kitti_row(&pose))?;
        let last = odometry
            .diagnostics()
            .last()
            .expect("a scan was registered");
        writeln!(diagnostics, "{}", serde_json::to_string(last)?)?;
        poses.flush()?;
        diagnostics.flush()?;
    }
    let seconds = start.elapsed().as_secs_f64();
    let fallbacks = odometry
        .diagnostics()
        .iter()
        .filter(|d| d.fallback.is_some())
        .count();
    println!(
        "{} scans in {seconds:.3} s ({:.1} Hz), {fallbacks} on a fallback; poses in {}",
        files.len(),
        files.len() as f64 / seconds,
        arguments.out.join("poses_kitti.txt").display()
    );
    let diagnostics = odometry.diagnostics();
    if diagnostics.iter().any(|d| d.ambiguous_start == Some(true)) {
        let taken = if diagnostics
            .iter()
            .any(|d| d.fallback == Some(Fallback::ForwardStart))
        {
            "the start driving forward was taken over the pair's reversing motion \
             (motion_model.start_max_reverse_m); "
        } else {
            ""
        };
        eprintln!(
            "warning: the first motion is ambiguous (another start explained the scans as well: a drive \
             that began at speed past a repeating scene?); {taken}the trajectory may be off from its start \
             on (diagnostics.jsonl: ambiguous_start)"
        );
    }
    Ok(())
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match run(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error}");
            ExitCode::FAILURE
        }
    }
}
