//! Registers two KITTI `.bin` scans with DMLO from Rust alone, no Python (feature `inference`): the
//! model folder opened by [`Odometry::open`] (its encoder run by tract), and [`dmlo_rs::odometry::pipeline::Odometry::register_pair`] — what
//! `dmlo register A B` does: the network's flow, the pair's back end (coherence, decoding with NMS, tilt
//! and crowding votes, RANSAC around the SVD solve), then NDT against A as a one-scan map; with
//! `--large-motion`, for scans far apart, the wide window (`frame_wide.onnx` beside the encoder) from
//! the configured search starts, then rounds of the model's own window.
//!
//! ```text
//! cargo run --release --features inference --example register_pair -- \
//!     python/dmlo/models/default A.bin B.bin [--large-motion] [--no-mapping] [--move-b YAW_DEG TX TY TZ]
//! ```
//!
//! The learned matcher needs no initial guess within the network's window (the paper's point).
//! `--move-b` first moves B's points by a known motion (yaw about z, then translation), so the printed
//! estimate can be checked against it.

use std::path::Path;
use std::process::ExitCode;

use dmlo_rs::odometry::config::OdometryConfig;
use dmlo_rs::odometry::pipeline::{Odometry, Scan};
use dmlo_rs::scan_file::read_kitti_scan;
use nalgebra::{Isometry3, Point3, Vector3};

const USAGE: &str = "usage: register_pair MODEL_DIR A.bin B.bin [--large-motion] [--no-mapping] \
                     [--move-b YAW_DEG TX TY TZ]";

struct Options {
    large_motion: bool,
    mapping: bool,
    known_motion: Option<Isometry3<f64>>,
}

fn parse_options(mut args: &[String]) -> Result<Options, String> {
    let mut options = Options {
        large_motion: false,
        mapping: true,
        known_motion: None,
    };
    while let [flag, rest @ ..] = args {
        args = rest;
        match flag.as_str() {
            "--large-motion" => options.large_motion = true,
            "--no-mapping" => options.mapping = false,
            "--move-b" if rest.len() >= 4 => {
                let v: Vec<f64> = rest[..4]
                    .iter()
                    .map(|s| {
                        s.parse::<f64>()
                            .map_err(|e| format!("--move-b: {s:?}: {e}"))
                    })
                    .collect::<Result<_, _>>()?;
                options.known_motion = Some(Isometry3::new(
                    Vector3::new(v[1], v[2], v[3]),
                    Vector3::z() * v[0].to_radians(),
                ));
                args = &rest[4..];
            }
            _ => return Err(USAGE.into()),
        }
    }
    Ok(options)
}

fn run(args: &[String]) -> Result<(), Box<dyn std::error::Error>> {
    let [model, a_path, b_path, rest @ ..] = args else {
        return Err(USAGE.into());
    };
    let options = parse_options(rest)?;
    let scan_a = read_kitti_scan(Path::new(a_path))?;
    let mut scan_b = read_kitti_scan(Path::new(b_path))?;
    if let Some(motion) = &options.known_motion {
        for p in &mut scan_b {
            let q = motion * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            p[..3].copy_from_slice(&[q.x as f32, q.y as f32, q.z as f32]);
        }
    }

    let mut config = OdometryConfig::default();
    config.mapping.enabled = options.mapping;
    let mut odometry = Odometry::open(model, config)?;
    let start = std::time::Instant::now();
    let pair =
        odometry.register_pair(Scan::new(&scan_a), Scan::new(&scan_b), options.large_motion)?;
    println!(
        "{} matches, {} RANSAC inliers, {} matching round(s), NDT {}, {:.0} ms",
        pair.matches.source.len(),
        pair.matches.num_inliers,
        pair.rounds,
        match pair.map_refined {
            Some(true) => "converged",
            Some(false) => "did not converge",
            None => "not run",
        },
        start.elapsed().as_secs_f64() * 1e3
    );

    // p_B = T · p_A.
    let t_b_a = pair.transform;
    println!("T_B_A (p_B = T · p_A):\n{t_b_a}");
    let rotation =
        nalgebra::Rotation3::from_matrix_unchecked(t_b_a.fixed_view::<3, 3>(0, 0).into());
    let (roll, pitch, yaw) = rotation.euler_angles();
    println!(
        "translation {:.4} {:.4} {:.4} m, roll/pitch/yaw {:.4}/{:.4}/{:.4} deg",
        t_b_a[(0, 3)],
        t_b_a[(1, 3)],
        t_b_a[(2, 3)],
        roll.to_degrees(),
        pitch.to_degrees(),
        yaw.to_degrees()
    );
    if let Some(motion) = options.known_motion {
        let error = motion.inverse().to_homogeneous() * t_b_a;
        let angle =
            nalgebra::Rotation3::from_matrix_unchecked(error.fixed_view::<3, 3>(0, 0).into())
                .angle();
        println!(
            "vs the applied motion: {:.4} m, {:.4} deg",
            error.fixed_view::<3, 1>(0, 3).norm(),
            angle.to_degrees()
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
