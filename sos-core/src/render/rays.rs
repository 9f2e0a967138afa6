//! Batches of camera rays: whole images, random pixels and strided patches.

use crate::camera::{Camera, Vec3};

/// Rays packed as parallel arrays.
#[derive(Debug, Clone, Default)]
pub struct RayBatch {
    /// Ray origins (world).
    pub origins: Vec<Vec3>,
    /// Unit ray directions (world).
    pub directions: Vec<Vec3>,
}

impl RayBatch {
    /// Number of rays.
    pub fn len(&self) -> usize {
        self.origins.len()
    }

    /// Whether the batch is empty.
    pub fn is_empty(&self) -> bool {
        self.origins.is_empty()
    }

    /// Appends the ray through the centre of pixel `(col, row)`.
    pub fn push_pixel(&mut self, camera: &Camera, col: u32, row: u32) {
        self.origins.push(camera.origin());
        self.directions.push(camera.direction(col as f32 + 0.5, row as f32 + 0.5));
    }

    /// Rays of every pixel of `camera`, row-major.
    pub fn full_image(camera: &Camera) -> RayBatch {
        let mut rays = RayBatch::default();
        for row in 0..camera.height {
            for col in 0..camera.width {
                rays.push_pixel(camera, col, row);
            }
        }
        rays
    }

    /// Rays `[start, end)` of this batch.
    pub fn slice(&self, start: usize, end: usize) -> RayBatch {
        RayBatch { origins: self.origins[start..end].to_vec(), directions: self.directions[start..end].to_vec() }
    }
}

/// A `size x size` grid of pixels with spacing `stride`, top-left at `(col0, row0)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct PatchGrid {
    /// Left column.
    pub col0: u32,
    /// Top row.
    pub row0: u32,
    /// Rays per side.
    pub size: u32,
    /// Pixel spacing between neighbouring rays.
    pub stride: u32,
}

impl PatchGrid {
    /// The stride to use for a `size`-ray patch in a `width x height` image: `wanted` if the
    /// patch fits, otherwise the largest stride that fits (at least 1). Returns `None` when not
    /// even a stride of 1 fits.
    pub fn fitting_stride(width: u32, height: u32, size: u32, wanted: u32) -> Option<u32> {
        let span = |s: u32| (size - 1) * s + 1;
        if span(1) > width.min(height) {
            return None;
        }
        let mut s = wanted.max(1);
        while s > 1 && (span(s) > width || span(s) > height) {
            s -= 1;
        }
        Some(s)
    }

    /// Pixel coordinates `(col, row)` of ray `(a, b)` (row `a`, column `b`).
    pub fn pixel(&self, a: u32, b: u32) -> (u32, u32) {
        (self.col0 + b * self.stride, self.row0 + a * self.stride)
    }
}
