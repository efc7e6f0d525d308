#![forbid(unsafe_code)]
//! KITTI's `.bin` scans: N points of four little-endian float32 each (x, y, z in metres in the sensor
//! frame, then reflectance), the layout of KITTI's `velodyne/` folders and of many drives converted
//! from other sensors. What the Rust examples read; Python reads these and other formats itself.

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

const POINT_BYTES: usize = 16;

/// The points of one `.bin` scan. A file whose length is not a whole number of points (a truncated
/// copy) is an error naming it, as is one that cannot be read.
pub fn read_kitti_scan(path: &Path) -> Result<Vec<[f32; 4]>> {
    let bytes = std::fs::read(path).map_err(|e| file_error(path, e.to_string()))?;
    if bytes.len() % POINT_BYTES != 0 {
        return Err(file_error(
            path,
            format!(
                "{} bytes is not a whole number of {POINT_BYTES}-byte points (truncated?)",
                bytes.len()
            ),
        ));
    }
    Ok(bytes
        .chunks_exact(POINT_BYTES)
        .map(|point| {
            let value = |i: usize| {
                f32::from_le_bytes([
                    point[4 * i],
                    point[4 * i + 1],
                    point[4 * i + 2],
                    point[4 * i + 3],
                ])
            };
            [value(0), value(1), value(2), value(3)]
        })
        .collect())
}

/// The `.bin` scans of `folder`, in name order (KITTI numbers them with leading zeros). A folder that
/// cannot be read or holds no `.bin` file is an error naming it.
pub fn kitti_scan_files(folder: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(folder).map_err(|e| file_error(folder, e.to_string()))?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|path| path.extension().is_some_and(|ext| ext == "bin"))
        .collect();
    if files.is_empty() {
        return Err(file_error(folder, "no .bin scans".into()));
    }
    files.sort();
    Ok(files)
}

fn file_error(path: &Path, reason: String) -> Error {
    Error::File {
        path: path.display().to_string(),
        reason,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("dmlo_scan_file_{}_{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn a_scan_reads_back_as_written() {
        let dir = scratch("roundtrip");
        let points = [[1.5f32, -2.25, 0.125, 0.5], [f32::NAN, 3.0, -4.0, 255.0]];
        let bytes: Vec<u8> = points
            .iter()
            .flatten()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let path = dir.join("000000.bin");
        std::fs::write(&path, bytes).unwrap();
        let read = read_kitti_scan(&path).unwrap();
        assert_eq!(read.len(), 2);
        assert_eq!(read[0], points[0]);
        assert!(read[1][0].is_nan());
        assert_eq!(&read[1][1..], &points[1][1..]);
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn truncated_and_missing_files_are_named() {
        let dir = scratch("bad");
        let path = dir.join("000001.bin");
        std::fs::write(&path, [0u8; 20]).unwrap();
        let message = read_kitti_scan(&path).unwrap_err().to_string();
        assert!(
            message.contains("000001.bin") && message.contains("20 bytes"),
            "{message}"
        );
        let missing = dir.join("nothing.bin");
        let message = read_kitti_scan(&missing).unwrap_err().to_string();
        assert!(message.contains("nothing.bin"), "{message}");
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn scan_files_are_the_bin_files_in_name_order() {
        let dir = scratch("files");
        for name in ["000002.bin", "000000.bin", "notes.txt", "000001.bin"] {
            std::fs::write(dir.join(name), []).unwrap();
        }
        let names: Vec<String> = kitti_scan_files(&dir)
            .unwrap()
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["000000.bin", "000001.bin", "000002.bin"]);
        let empty = scratch("empty");
        let message = kitti_scan_files(&empty).unwrap_err().to_string();
        assert!(message.contains("no .bin scans"), "{message}");
        std::fs::remove_dir_all(dir).unwrap();
        std::fs::remove_dir_all(empty).unwrap();
    }
}
