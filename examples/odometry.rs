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
//! order. `MODEL_DIR` (default `python/dmlo/models/default`) is a model folder as `dmlo export` writes it,
//! opened by [`Odometry::open_with_runtime`]: the encoder with its wide window, the range-only model and
//! the moving-object network (whose flagged points are left out as `dmlo run` leaves them out, unless the
//! config's `moving_objects.detect` is false) when the folder has them; `CONFIG.json` is a config as
//! `dmlo run` writes it (default: the defaults). `OUT_DIR` gets `poses_kitti.txt`
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

use dmlo_rs::inference::Runtime;
use dmlo_rs::odometry::config::OdometryConfig;
use dmlo_rs::odometry::motion::Fallback;
use dmlo_rs::odometry::pipeline::{Odometry, Scan};
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
    let runtime = runtime(arguments.onnxruntime.as_deref(), threads)?;
    pool.install(|| drive(&arguments, config, &runtime))
}

/// onnxruntime, from its shared library `library`, when one is given; else tract.
#[cfg(feature = "onnxruntime")]
fn runtime(library: Option<&Path>, threads: usize) -> Result<Runtime, String> {
    Ok(match library {
        None => Runtime::Tract,
        Some(library) => Runtime::Onnxruntime {
            library: library.to_path_buf(),
            threads,
        },
    })
}

#[cfg(not(feature = "onnxruntime"))]
fn runtime(library: Option<&Path>, _threads: usize) -> Result<Runtime, String> {
    match library {
        None => Ok(Runtime::Tract),
        Some(_) => Err("--onnxruntime: built without the `onnxruntime` feature (cargo run --features inference,onnxruntime …)".into()),
    }
}

/// The odometry of the model folder, its graphs run by `runtime`, over every scan of the folder.
fn drive(
    arguments: &Arguments,
    config: OdometryConfig,
    runtime: &Runtime,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    let files = kitti_scan_files(&arguments.scans)?;
    let mut odometry = Odometry::open_with_runtime(&arguments.model, config, runtime)?;
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
        writeln!(poses, "{}", kitti_row(&pose.to_homogeneous()))?;
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
