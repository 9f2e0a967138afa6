//! Floating-point RGB images and binary masks, with PNG/JPEG input and PNG output.

use std::path::Path;

use crate::error::IoError;

/// An RGB image with values in `[0, 1]`, row-major `[height, width, 3]`.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbImage {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Interleaved RGB values.
    pub data: Vec<f32>,
}

impl RgbImage {
    /// A black image.
    pub fn new(width: usize, height: usize) -> Self {
        RgbImage { width, height, data: vec![0.0; width * height * 3] }
    }

    /// Colour at `(col, row)`.
    pub fn pixel(&self, col: usize, row: usize) -> [f32; 3] {
        let i = (row * self.width + col) * 3;
        [self.data[i], self.data[i + 1], self.data[i + 2]]
    }

    /// Sets the colour at `(col, row)`.
    pub fn set_pixel(&mut self, col: usize, row: usize, rgb: [f32; 3]) {
        let i = (row * self.width + col) * 3;
        self.data[i..i + 3].copy_from_slice(&rgb);
    }

    /// Reads a PNG or JPEG file (8 or 16 bit; alpha is dropped).
    pub fn load(path: &Path) -> Result<Self, IoError> {
        let img = open_image(path, "image", "; re-export it as PNG or JPEG")?;
        let rgb = img.to_rgb32f();
        let (w, h) = rgb.dimensions();
        if w == 0 || h == 0 {
            return Err(IoError::file(path, "image has zero size"));
        }
        Ok(RgbImage { width: w as usize, height: h as usize, data: rgb.into_raw() })
    }

    /// Writes an 8-bit PNG, creating the parent folder; written to a temporary file first so an
    /// interrupted run never leaves a truncated PNG.
    pub fn save_png(&self, path: &Path) -> Result<(), IoError> {
        let bytes: Vec<u8> = self.data.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8).collect();
        let buf = image::RgbImage::from_raw(self.width as u32, self.height as u32, bytes)
            .expect("buffer length matches dimensions");
        save_atomically(path, |tmp| buf.save_with_format(tmp, image::ImageFormat::Png))
    }

    /// Area-averaged resize (box filter when shrinking, bilinear when enlarging).
    pub fn resized(&self, width: usize, height: usize) -> RgbImage {
        let mut out = RgbImage::new(width, height);
        resize_channels(&self.data, self.width, self.height, 3, &mut out.data, width, height);
        out
    }
}

/// The most pixels one image file may hold: 100 megapixels, 1.2 GB as the 32-bit RGB a view
/// keeps (several images decode at once). Larger photographs belong downscaled on disk; a
/// header declaring more (a decompression bomb, or a corrupt size) is refused before any
/// pixel is decoded.
pub const MAX_IMAGE_PIXELS: u64 = 100_000_000;

/// Decodes an image file after checking its declared size against [`MAX_IMAGE_PIXELS`];
/// `what` names it in errors ("image", "mask"), `hint` is appended to decoding errors.
pub fn open_image(path: &Path, what: &str, hint: &str) -> Result<image::DynamicImage, IoError> {
    let undecodable = |e: &dyn std::fmt::Display| IoError::file(path, format!("cannot decode {what} ({e}){hint}"));
    let reader = image::ImageReader::open(path)
        .map_err(|e| IoError::file(path, format!("cannot read {what}: {e}")))?
        .with_guessed_format()
        .map_err(|e| undecodable(&e))?;
    let (w, h) = reader.into_dimensions().map_err(|e| undecodable(&e))?;
    if u64::from(w) * u64::from(h) > MAX_IMAGE_PIXELS {
        return Err(IoError::file(
            path,
            format!("{what} is {w}x{h}, over {} megapixels; downscale it on disk first", MAX_IMAGE_PIXELS / 1_000_000),
        ));
    }
    image::open(path).map_err(|e| undecodable(&e))
}

/// A single-channel image (mask or scalar map), row-major `[height, width]`.
#[derive(Debug, Clone, PartialEq)]
pub struct GrayImage {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Values, usually in `[0, 1]`.
    pub data: Vec<f32>,
}

impl GrayImage {
    /// Reads any image as luminance in `[0, 1]`.
    pub fn load(path: &Path) -> Result<Self, IoError> {
        let img = open_image(path, "mask", "")?;
        let g = img.to_luma32f();
        let (w, h) = g.dimensions();
        Ok(GrayImage { width: w as usize, height: h as usize, data: g.into_raw() })
    }

    /// Writes an 8-bit grey PNG (values clamped to `[0, 1]`), atomically.
    pub fn save_png(&self, path: &Path) -> Result<(), IoError> {
        let bytes: Vec<u8> = self.data.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8).collect();
        let buf = image::GrayImage::from_raw(self.width as u32, self.height as u32, bytes)
            .expect("buffer length matches dimensions");
        save_atomically(path, |tmp| buf.save_with_format(tmp, image::ImageFormat::Png))
    }

    /// Nearest-neighbour resize (masks must stay binary).
    pub fn resized_nearest(&self, width: usize, height: usize) -> GrayImage {
        let mut data = vec![0.0; width * height];
        for r in 0..height {
            let sr = (r * self.height / height).min(self.height - 1);
            for c in 0..width {
                let sc = (c * self.width / width).min(self.width - 1);
                data[r * width + c] = self.data[sr * self.width + sc];
            }
        }
        GrayImage { width, height, data }
    }
}

fn save_atomically(path: &Path, write: impl FnOnce(&Path) -> image::ImageResult<()>) -> Result<(), IoError> {
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).map_err(|e| IoError::file(parent, e))?;
    }
    let tmp = path.with_extension("png.tmp");
    write(&tmp).map_err(|e| IoError::file(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| IoError::file(path, e))
}

/// Resizes interleaved `channels`-channel data. Shrinking averages the covered source area
/// (anti-aliased, like ImageMagick's box filter); enlarging interpolates bilinearly.
pub fn resize_channels(
    src: &[f32],
    src_w: usize,
    src_h: usize,
    channels: usize,
    dst: &mut [f32],
    dst_w: usize,
    dst_h: usize,
) {
    assert_eq!(src.len(), src_w * src_h * channels, "source buffer size");
    assert_eq!(dst.len(), dst_w * dst_h * channels, "destination buffer size");
    let sx = src_w as f32 / dst_w as f32;
    let sy = src_h as f32 / dst_h as f32;
    for r in 0..dst_h {
        for c in 0..dst_w {
            let out = &mut dst[(r * dst_w + c) * channels..][..channels];
            out.fill(0.0);
            if sx >= 1.0 && sy >= 1.0 {
                // Box filter over the source footprint [x0, x1) x [y0, y1).
                let (x0, x1) = (c as f32 * sx, (c + 1) as f32 * sx);
                let (y0, y1) = (r as f32 * sy, (r + 1) as f32 * sy);
                let mut total = 0.0;
                let mut yy = y0.floor() as usize;
                while (yy as f32) < y1 && yy < src_h {
                    let wy = (y1.min(yy as f32 + 1.0) - y0.max(yy as f32)).max(0.0);
                    let mut xx = x0.floor() as usize;
                    while (xx as f32) < x1 && xx < src_w {
                        let wx = (x1.min(xx as f32 + 1.0) - x0.max(xx as f32)).max(0.0);
                        let w = wx * wy;
                        let s = &src[(yy * src_w + xx) * channels..][..channels];
                        for k in 0..channels {
                            out[k] += w * s[k];
                        }
                        total += w;
                        xx += 1;
                    }
                    yy += 1;
                }
                for v in out.iter_mut() {
                    *v /= total.max(1e-12);
                }
            } else {
                let fx = ((c as f32 + 0.5) * sx - 0.5).clamp(0.0, (src_w - 1) as f32);
                let fy = ((r as f32 + 0.5) * sy - 0.5).clamp(0.0, (src_h - 1) as f32);
                let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
                let (x1, y1) = ((x0 + 1).min(src_w - 1), (y0 + 1).min(src_h - 1));
                let (tx, ty) = (fx - x0 as f32, fy - y0 as f32);
                for k in 0..channels {
                    let at = |x: usize, y: usize| src[(y * src_w + x) * channels + k];
                    out[k] = (1.0 - ty) * ((1.0 - tx) * at(x0, y0) + tx * at(x1, y0))
                        + ty * ((1.0 - tx) * at(x0, y1) + tx * at(x1, y1));
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_resize_preserves_mean_and_png_round_trips() {
        let mut img = RgbImage::new(8, 6);
        for (i, v) in img.data.iter_mut().enumerate() {
            *v = (i % 7) as f32 / 7.0;
        }
        let small = img.resized(4, 3);
        let mean = |d: &[f32]| d.iter().sum::<f32>() / d.len() as f32;
        assert!((mean(&small.data) - mean(&img.data)).abs() < 1e-5);

        let dir = std::env::temp_dir().join(format!("sos-img-{}", std::process::id()));
        let path = dir.join("a.png");
        img.save_png(&path).unwrap();
        let back = RgbImage::load(&path).unwrap();
        assert_eq!((back.width, back.height), (8, 6));
        for (a, b) in back.data.iter().zip(&img.data) {
            assert!((a - b).abs() <= 0.5 / 255.0 + 1e-6);
        }
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn corrupt_image_is_an_error_naming_the_file() {
        let dir = std::env::temp_dir().join(format!("sos-bad-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("bad.png");
        std::fs::write(&path, b"not a png").unwrap();
        let err = RgbImage::load(&path).unwrap_err().to_string();
        assert!(err.contains("bad.png"), "{err}");
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn an_image_declaring_too_many_pixels_is_refused_before_decoding() {
        let dir = std::env::temp_dir().join(format!("sos-huge-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("huge.jpg");
        image::RgbImage::new(8, 8).save(&path).unwrap();
        assert_eq!((RgbImage::load(&path).unwrap().width, GrayImage::load(&path).unwrap().height), (8, 8));
        // The frame header (SOF0: marker, length, precision, height, width) now declares
        // 20000x20000 pixels, 4.8 GB as 32-bit RGB.
        let mut bytes = std::fs::read(&path).unwrap();
        let mut sof = 2; // after the start-of-image marker, walk the segments
        while bytes[sof + 1] != 0xC0 {
            sof += 2 + usize::from(u16::from_be_bytes([bytes[sof + 2], bytes[sof + 3]]));
        }
        bytes[sof + 5..sof + 9].copy_from_slice(&[0x4E, 0x20, 0x4E, 0x20]);
        std::fs::write(&path, &bytes).unwrap();
        for err in [RgbImage::load(&path).unwrap_err().to_string(), GrayImage::load(&path).unwrap_err().to_string()] {
            assert!(err.contains("huge.jpg") && err.contains("20000x20000") && err.contains("downscale"), "{err}");
        }
        std::fs::remove_dir_all(dir).ok();
    }
}
