//! Registers two KITTI `.bin` scans with DMLO from Rust alone, no Python (feature `inference`): the
//! network's encoder run by tract on the exported `encoder.onnx`, the crate's matching stage on its
//! features (the flow and confidence of every cell), and the back end of a pair
//! ([`dmlo_rs::pair::match_pair`]: coherence, decoding with NMS, tilt and crowding votes, RANSAC around
//! the SVD solve) — the pure DMLO of `dmlo register --no-mapping` for one pair of consecutive scans.
//!
//! ```text
//! cargo run --release --features inference --example register_pair -- \
//!     python/dmlo/models/default/encoder.onnx A.bin B.bin [--move-b YAW_DEG TX TY TZ]
//! ```
//!
//! The learned matcher needs no initial guess within the network's window (the paper's point); pairs
//! farther apart (`dmlo register`'s large-motion search) are not this example's. `--move-b` first moves
//! B's points by a known motion (yaw about z, then translation), so the printed estimate can be checked
//! against it.

use std::process::ExitCode;

use dmlo_rs::inference::{Encoder, LearnedMatcher, TractEncoder};
use dmlo_rs::pair::{match_pair, PairConfig, PairImages};
use dmlo_rs::projection::{project_flat, CylinderConfig, Projection};
use nalgebra::{Isometry3, Point3, Vector3};

const USAGE: &str = "usage: register_pair ENCODER.onnx A.bin B.bin [--move-b YAW_DEG TX TY TZ]";

fn read_scan(path: &str) -> Result<Vec<f32>, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{path}: {e}"))?;
    if bytes.len() % 16 != 0 {
        return Err(format!(
            "{path}: {} bytes is not a whole number of 16-byte points (truncated?)",
            bytes.len()
        ));
    }
    Ok(bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect())
}

fn parse_motion(args: &[String]) -> Result<Option<Isometry3<f64>>, String> {
    match args {
        [] => Ok(None),
        [flag, values @ ..] if flag == "--move-b" && values.len() == 4 => {
            let v: Vec<f64> = values
                .iter()
                .map(|s| {
                    s.parse::<f64>()
                        .map_err(|e| format!("--move-b: {s:?}: {e}"))
                })
                .collect::<Result<_, _>>()?;
            Ok(Some(Isometry3::new(
                Vector3::new(v[1], v[2], v[3]),
                Vector3::z() * v[0].to_radians(),
            )))
        }
        _ => Err(USAGE.into()),
    }
}

/// Each cell's kept point (`H × W × 3`, NaN where empty): the surfaces under the matches, for the votes.
fn point_image(points: &[f32], projection: &Projection) -> Vec<f32> {
    projection
        .index
        .iter()
        .flat_map(|&i| match usize::try_from(i) {
            Ok(i) => [points[4 * i], points[4 * i + 1], points[4 * i + 2]],
            Err(_) => [f32::NAN; 3],
        })
        .collect()
}

fn run(args: &[String]) -> Result<(), Box<dyn std::error::Error>> {
    let [encoder, a_path, b_path, rest @ ..] = args else {
        return Err(USAGE.into());
    };
    let known_motion = parse_motion(rest)?;
    let scan_a = read_scan(a_path)?;
    let mut scan_b = read_scan(b_path)?;
    if let Some(motion) = &known_motion {
        for p in scan_b.chunks_exact_mut(4) {
            let q = motion * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            p[..3].copy_from_slice(&[q.x as f32, q.y as f32, q.z as f32]);
        }
    }

    let matcher = LearnedMatcher::new(TractEncoder::open(encoder)?)?;
    let cylinder = matcher
        .encoder()
        .metadata()
        .cylinder
        .unwrap_or_else(CylinderConfig::kitti);
    let image_a = project_flat(&scan_a, 4, &cylinder)?;
    let image_b = project_flat(&scan_b, 4, &cylinder)?;
    println!(
        "A: {} points → {} cells; B: {} points → {} cells",
        scan_a.len() / 4,
        image_a.num_valid(),
        scan_b.len() / 4,
        image_b.num_valid()
    );
    let start = std::time::Instant::now();
    let encoded_a = matcher
        .encoder()
        .encode(&[&image_a.range[..], &image_a.reflectance].concat())?;
    let encoded_b = matcher
        .encoder()
        .encode(&[&image_b.range[..], &image_b.reflectance].concat())?;
    let flow = matcher.flow(&encoded_a, &encoded_b)?;
    let points_a = point_image(&scan_a, &image_a);
    let images = PairImages {
        ref_points: Some(&points_a),
        ..PairImages::new(&image_a.range, &image_b.range, &flow.flow, &flow.confidence)
    };
    let pair = match_pair(&images, &cylinder, &PairConfig::default(), true)?;
    println!(
        "{} matches, {} RANSAC inliers, {:.0} ms (two encodes, the matching stage and the back end)",
        pair.source.len(),
        pair.num_inliers,
        start.elapsed().as_secs_f64() * 1e3
    );

    // p_B = T · p_A.
    let t_b_a = pair.transform;
    println!("T_B_A (p_B = T · p_A):\n{}", t_b_a.to_homogeneous());
    let (roll, pitch, yaw) = t_b_a.rotation.euler_angles();
    println!(
        "translation {:.4} {:.4} {:.4} m, roll/pitch/yaw {:.4}/{:.4}/{:.4} deg",
        t_b_a.translation.x,
        t_b_a.translation.y,
        t_b_a.translation.z,
        roll.to_degrees(),
        pitch.to_degrees(),
        yaw.to_degrees()
    );
    if let Some(motion) = known_motion {
        let error = motion.inverse() * t_b_a;
        println!(
            "vs the applied motion: {:.4} m, {:.4} deg",
            error.translation.vector.norm(),
            error.rotation.angle().to_degrees()
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
