//! COLMAP's sparse point cloud (`points3D.bin` / `points3D.txt`): each triangulated point's
//! position and the images that observe it. The `colmap` adapter takes per-view depth bounds
//! from it, as LLFF's `imgs2poses` does.

use std::path::Path;

use sos_core::plugin::dataset::DatasetError;

use crate::colmap::data_lines;
use crate::text::{invalid, number, read_bytes, read_text, Reader};

/// One triangulated point.
#[derive(Debug, Clone, PartialEq)]
pub struct SparsePoint {
    /// Position in COLMAP's world frame.
    pub xyz: [f64; 3],
    /// Ids of the images that observe it (its track; may be empty).
    pub images: Vec<i64>,
}

/// Reads `points3D.bin` (preferred) or `points3D.txt` from the model folder `dir`; `Ok(None)`
/// when neither exists (models may ship without points).
pub fn read_points(dir: &Path) -> Result<Option<Vec<SparsePoint>>, DatasetError> {
    let hint = "the model's sparse point cloud";
    let (bin, txt) = (dir.join("points3D.bin"), dir.join("points3D.txt"));
    if bin.is_file() {
        parse_points_bin(&bin, &read_bytes(&bin, hint)?).map(Some)
    } else if txt.is_file() {
        parse_points_txt(&txt, &read_text(&txt, hint)?).map(Some)
    } else {
        Ok(None)
    }
}

/// Parses `points3D.bin`: a count, then per point its id (u64), position (3 × f64), colour
/// (3 × u8), reprojection error (f64) and track (u64 length, then `(image id, 2-D point
/// index)` pairs of i32).
pub fn parse_points_bin(path: &Path, bytes: &[u8]) -> Result<Vec<SparsePoint>, DatasetError> {
    const MIN_POINT_BYTES: u64 = 8 + 24 + 3 + 8 + 8;
    let mut r = Reader::new(path, bytes);
    let n = r.u64("the point count")?;
    if n > r.remaining() as u64 / MIN_POINT_BYTES {
        return Err(invalid(
            path,
            format!("point count {n} does not fit in the file ({} bytes); re-export the model", bytes.len()),
        ));
    }
    let mut points = Vec::with_capacity(n as usize);
    for i in 0..n {
        let what = format!("point {i}");
        let id = r.u64(&what)?;
        let xyz = [r.f64(&what)?, r.f64(&what)?, r.f64(&what)?];
        r.skip(3 + 8, &what)?;
        let len = r.u64(&what)?;
        let fits = len.checked_mul(8).is_some_and(|b| b <= r.remaining() as u64);
        if !fits {
            return Err(invalid(path, format!("{what}: a track of {len} images does not fit in the file")));
        }
        let mut images = Vec::with_capacity(len as usize);
        for _ in 0..len {
            images.push(r.i32(&what)? as i64);
            r.i32(&what)?;
        }
        points.push(checked(path, &format!("point id {id}"), xyz, images)?);
    }
    if r.remaining() != 0 {
        return Err(invalid(path, format!("{} bytes left after the last point; re-export the model", r.remaining())));
    }
    Ok(points)
}

/// Parses `points3D.txt`: `POINT3D_ID X Y Z R G B ERROR` then `IMAGE_ID POINT2D_IDX` pairs.
pub fn parse_points_txt(path: &Path, text: &str) -> Result<Vec<SparsePoint>, DatasetError> {
    let mut points = Vec::new();
    for (what, t) in data_lines(text) {
        if t.len() < 8 || !(t.len() - 8).is_multiple_of(2) {
            return Err(invalid(
                path,
                format!(
                    "{what}: expected POINT3D_ID X Y Z R G B ERROR then IMAGE_ID POINT2D_IDX pairs, got {} fields",
                    t.len()
                ),
            ));
        }
        let xyz = [number(path, t[1], &what)?, number(path, t[2], &what)?, number(path, t[3], &what)?];
        let images = t[8..]
            .iter()
            .step_by(2)
            .map(|s| s.parse().map_err(|_| invalid(path, format!("{what}: IMAGE_ID must be an integer, got {s:?}"))))
            .collect::<Result<Vec<i64>, _>>()?;
        points.push(checked(path, &what, xyz, images)?);
    }
    Ok(points)
}

fn checked(path: &Path, what: &str, xyz: [f64; 3], images: Vec<i64>) -> Result<SparsePoint, DatasetError> {
    if xyz.iter().any(|v| !v.is_finite()) {
        return Err(invalid(path, format!("{what}: position {xyz:?} is not finite; re-export the model")));
    }
    Ok(SparsePoint { xyz, images })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point_bin(id: u64, xyz: [f64; 3], track: &[(i32, i32)]) -> Vec<u8> {
        let mut b = id.to_le_bytes().to_vec();
        xyz.iter().for_each(|v| b.extend(v.to_le_bytes()));
        b.extend([10, 20, 30]);
        b.extend(0.5f64.to_le_bytes());
        b.extend((track.len() as u64).to_le_bytes());
        track.iter().for_each(|&(i, k)| {
            b.extend(i.to_le_bytes());
            b.extend(k.to_le_bytes());
        });
        b
    }

    #[test]
    fn binary_and_text_agree() {
        let mut bin = 2u64.to_le_bytes().to_vec();
        bin.extend(point_bin(7, [1.0, -2.0, 3.5], &[(1, 0), (4, 12)]));
        bin.extend(point_bin(9, [0.0, 0.25, -1.0], &[]));
        let p = Path::new("points3D.bin");
        let from_bin = parse_points_bin(p, &bin).unwrap();
        let text = "# comment\n7 1 -2 3.5 10 20 30 0.5 1 0 4 12\n\n9 0 0.25 -1 10 20 30 0.5\n";
        let from_txt = parse_points_txt(Path::new("points3D.txt"), text).unwrap();
        assert_eq!(from_bin, from_txt);
        assert_eq!(from_bin[0], SparsePoint { xyz: [1.0, -2.0, 3.5], images: vec![1, 4] });
    }

    #[test]
    fn hostile_files_are_errors_naming_the_point() {
        let p = Path::new("points3D.bin");
        let mut huge = u64::MAX.to_le_bytes().to_vec();
        huge.extend([0u8; 64]);
        assert!(parse_points_bin(p, &huge).unwrap_err().to_string().contains("does not fit"));
        let mut long_track = 1u64.to_le_bytes().to_vec();
        long_track.extend(point_bin(1, [0.0; 3], &[]));
        let at = long_track.len() - 8;
        long_track[at..].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(parse_points_bin(p, &long_track).unwrap_err().to_string().contains("track"));
        let mut nan = 1u64.to_le_bytes().to_vec();
        nan.extend(point_bin(3, [f64::NAN, 0.0, 0.0], &[]));
        assert!(parse_points_bin(p, &nan).unwrap_err().to_string().contains("point id 3"));
        let mut trailing = 1u64.to_le_bytes().to_vec();
        trailing.extend(point_bin(3, [0.0; 3], &[]));
        trailing.push(0);
        assert!(parse_points_bin(p, &trailing).is_err());
        let t = Path::new("points3D.txt");
        assert!(parse_points_txt(t, "1 0 0 0 1 2 3 0.1 5\n").unwrap_err().to_string().contains("line 1"));
        assert!(parse_points_txt(t, "1 0 x 0 1 2 3 0.1\n").is_err());
        assert!(parse_points_txt(t, "1 0 0 0 1 2 3 0.1 a 0\n").unwrap_err().to_string().contains("IMAGE_ID"));
    }
}
