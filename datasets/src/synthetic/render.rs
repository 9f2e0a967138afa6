//! Renders one view of the synthetic world: 2x2 supersampled colour, an exact mask from the
//! pixel-centre ray and the range of content depths along a reference axis.

use rayon::prelude::*;
use sos_core::camera::{dot, sub, Camera, Vec3};
use sos_core::image::{GrayImage, RgbImage};

use super::world::Trace;

/// Sub-pixel offsets of the 2x2 supersampling pattern.
const SUBSAMPLES: [[f32; 2]; 4] = [[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]];

/// A rendered view.
#[derive(Debug, Clone)]
pub struct Rendered {
    /// Colour, the mean of 2x2 sub-pixel samples.
    pub image: RgbImage,
    /// 1 where the pixel-centre ray hits the foreground object.
    pub mask: GrayImage,
    /// Min and max depth of the pixel-centre hits along `depth_axis` from `depth_origin`.
    pub depth_range: [f32; 2],
}

/// Renders `cam` (world frame). Depths are measured as `dot(hit − depth_origin, depth_axis)`.
pub fn render_view<W: Trace + Sync>(world: &W, cam: &Camera, depth_origin: Vec3, depth_axis: Vec3) -> Rendered {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut image = RgbImage::new(w, h);
    let mut mask = GrayImage { width: w, height: h, data: vec![0.0; w * h] };
    let origin = cam.origin();
    let depth_range = image
        .data
        .par_chunks_mut(w * 3)
        .zip(mask.data.par_chunks_mut(w))
        .enumerate()
        .map(|(row, (rgb_row, mask_row))| {
            let mut range = [f32::INFINITY, f32::NEG_INFINITY];
            for col in 0..w {
                let subs = SUBSAMPLES.map(|[sx, sy]| cam.direction(col as f32 + sx, row as f32 + sy));
                rgb_row[col * 3..col * 3 + 3].copy_from_slice(&world.pixel(origin, subs));
                let (foreground, point) = world.probe(origin, cam.direction(col as f32 + 0.5, row as f32 + 0.5));
                mask_row[col] = if foreground { 1.0 } else { 0.0 };
                let depth = dot(sub(point, depth_origin), depth_axis);
                range = [range[0].min(depth), range[1].max(depth)];
            }
            range
        })
        .reduce(|| [f32::INFINITY, f32::NEG_INFINITY], |a, b| [a[0].min(b[0]), a[1].max(b[1])]);
    Rendered { image, mask, depth_range }
}
