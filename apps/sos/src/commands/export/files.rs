//! The 3D files `sos export` writes: binary PLY (little endian) for the point cloud and the
//! mesh, Wavefront OBJ for the mesh. Each file is written to a temporary name and renamed into
//! place, so an interrupted export never leaves half a file.
//!
//! The layouts are fixed and small, so they are written directly:
//! - point cloud: `element vertex N` with `float x, y, z` and `uchar red, green, blue`;
//! - mesh: `element vertex N` with `float x, y, z, nx, ny, nz` and `element face F` with
//!   `list uchar int vertex_indices` (triangles, counter-clockwise seen from outside).

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use anyhow::Context;
use sos_core::camera::Vec3;

use super::mesh::Mesh;

/// Writes `path` through a buffered temporary file renamed into place, creating its folder.
pub fn write_atomically(
    path: &Path,
    write: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
) -> anyhow::Result<()> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    }
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = std::path::PathBuf::from(tmp);
    let file = File::create(&tmp).with_context(|| format!("writing {}", tmp.display()))?;
    let mut out = BufWriter::new(file);
    write(&mut out).and_then(|()| out.flush()).with_context(|| format!("writing {}", tmp.display()))?;
    drop(out);
    std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))
}

/// Writes a coloured point cloud as binary PLY.
pub fn write_point_cloud(path: &Path, points: &[Vec3], colours: &[[u8; 3]]) -> anyhow::Result<()> {
    assert_eq!(points.len(), colours.len(), "one colour per point");
    write_atomically(path, |out| {
        write!(
            out,
            "ply\nformat binary_little_endian 1.0\ncomment nerf-sos: the segmented object's rendered surface \
             points\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
             property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
            points.len()
        )?;
        for (p, c) in points.iter().zip(colours) {
            for v in p {
                out.write_all(&v.to_le_bytes())?;
            }
            out.write_all(c)?;
        }
        Ok(())
    })
}

/// Writes a triangle mesh with vertex normals as binary PLY.
pub fn write_mesh_ply(path: &Path, mesh: &Mesh) -> anyhow::Result<()> {
    write_atomically(path, |out| {
        write!(
            out,
            "ply\nformat binary_little_endian 1.0\ncomment nerf-sos: the segmented object's density \
             iso-surface\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
             property float nx\nproperty float ny\nproperty float nz\nelement face {}\n\
             property list uchar int vertex_indices\nend_header\n",
            mesh.positions.len(),
            mesh.faces.len()
        )?;
        for (p, n) in mesh.positions.iter().zip(&mesh.normals) {
            for v in p.iter().chain(n) {
                out.write_all(&v.to_le_bytes())?;
            }
        }
        for face in &mesh.faces {
            out.write_all(&[3])?;
            for &i in face {
                out.write_all(&(i as i32).to_le_bytes())?;
            }
        }
        Ok(())
    })
}

/// Writes a triangle mesh with vertex normals as Wavefront OBJ (1-based indices).
pub fn write_mesh_obj(path: &Path, mesh: &Mesh) -> anyhow::Result<()> {
    write_atomically(path, |out| {
        writeln!(out, "# nerf-sos: the segmented object's density iso-surface")?;
        writeln!(out, "# {} vertices, {} faces", mesh.positions.len(), mesh.faces.len())?;
        for p in &mesh.positions {
            writeln!(out, "v {} {} {}", p[0], p[1], p[2])?;
        }
        for n in &mesh.normals {
            writeln!(out, "vn {} {} {}", n[0], n[1], n[2])?;
        }
        for f in &mesh.faces {
            let [a, b, c] = f.map(|i| i + 1);
            writeln!(out, "f {a}//{a} {b}//{b} {c}//{c}")?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("sos-export-files-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    #[test]
    fn point_cloud_has_its_header_count_and_record_size() {
        let path = temp("points.ply");
        write_point_cloud(&path, &[[1.0, 2.0, 3.0], [-1.0, 0.5, 0.0]], &[[255, 0, 7], [1, 2, 3]]).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let end = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let header = std::str::from_utf8(&bytes[..end]).unwrap();
        assert!(header.contains("element vertex 2\n"), "{header}");
        assert_eq!(bytes.len() - end, 2 * 15);
        assert_eq!(f32::from_le_bytes(bytes[end + 4..end + 8].try_into().unwrap()), 2.0);
        assert_eq!(&bytes[end + 12..end + 15], &[255, 0, 7]);
        assert!(!path.with_extension("ply.tmp").exists());
    }

    #[test]
    fn obj_faces_are_one_based() {
        let mesh = Mesh {
            positions: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            normals: vec![[0.0, 0.0, 1.0]; 3],
            faces: vec![[0, 1, 2]],
        };
        let path = temp("tri.obj");
        write_mesh_obj(&path, &mesh).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.lines().any(|l| l == "f 1//1 2//2 3//3"), "{text}");
        assert_eq!(text.lines().filter(|l| l.starts_with("v ")).count(), 3);
    }
}
