//! Turning an RGB image in `[0, 1]` into the ViT's input, as the reference does (spec §4):
//!
//! 1. the rendered 64×64 patch is nearest-upsampled to 384×384, ImageNet-normalised, then
//!    inside the extractor nearest-resized to 224×224 and normalised AGAIN (the "double
//!    normalisation", `x'' = ((x − m)/s − m)/s`);
//! 2. for the foreground choice, the whole rendered view goes in at its own size (no resize,
//!    same double normalisation), cropped by the convolution to whole patches.
//!
//! Nearest resizing maps output index `i` to input index `⌊i · in / out⌋`. The two resizes of
//! step 1 are composed exactly (`in → reference_upsample → input_size`); per-pixel
//! normalisation commutes with them. For 64-px patches the composition equals a direct
//! 64 → 224 resize. `double_normalize = false` gives the usual single normalisation.

use std::ops::Range;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sos_core::image::RgbImage;
use sos_core::plugin::FeatureMap;

/// ImageNet channel means (RGB).
pub const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
/// ImageNet channel standard deviations (RGB).
pub const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];
/// Side of the reference's intermediate nearest upsample.
pub const REFERENCE_UPSAMPLE: usize = 384;

/// Which images are resized to `input_size × input_size`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Resize {
    /// Images no larger than `input_size` on both sides (stage-2 patches) are resized; larger
    /// ones (whole views, for the foreground choice) keep their size — the reference's two
    /// uses of DINO.
    #[default]
    Patches,
    /// Every image is resized.
    Always,
    /// No image is resized (only images smaller than one patch are enlarged to one).
    Never,
}

impl Resize {
    /// The config spelling.
    pub fn name(self) -> &'static str {
        match self {
            Resize::Patches => "patches",
            Resize::Always => "always",
            Resize::Never => "never",
        }
    }
}

/// Preprocessing settings.
#[derive(Debug, Clone, PartialEq)]
pub struct Preprocess {
    /// Side that resized images get.
    pub input_size: usize,
    /// Which images are resized.
    pub resize: Resize,
    /// Intermediate nearest-upsample side when resizing (0: resize directly).
    pub reference_upsample: usize,
    /// Channel means.
    pub mean: [f32; 3],
    /// Channel standard deviations.
    pub std: [f32; 3],
    /// Normalise twice, as the reference does.
    pub double_normalize: bool,
    /// The model's patch side: unresized images are cropped to whole patches and images
    /// smaller than one patch are enlarged to one.
    pub patch: usize,
}

/// A preprocessed image, `[3, height, width]` channel-first.
#[derive(Debug, Clone, PartialEq)]
pub struct Tensor3 {
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
    /// Values.
    pub data: Vec<f32>,
}

/// Nearest source index of each output index (`⌊i · in / out⌋`, through `via` if nonzero).
fn nearest_map(input: usize, output: usize, via: usize) -> Vec<usize> {
    (0..output)
        .map(|i| match ((i * via).checked_div(output), via) {
            (Some(up), v) if v > 0 => up * input / v,
            _ => i * input / output,
        })
        .map(|s| s.min(input - 1))
        .collect()
}

impl Preprocess {
    /// The reference's settings for a model with this patch size: 224, resize patches via
    /// 384, ImageNet statistics, double normalisation.
    pub fn reference(patch: usize) -> Preprocess {
        Preprocess {
            input_size: 224,
            resize: Resize::Patches,
            reference_upsample: REFERENCE_UPSAMPLE,
            mean: IMAGENET_MEAN,
            std: IMAGENET_STD,
            double_normalize: true,
            patch,
        }
    }

    /// `(height, width, resized)` of the model input for a `width × height` image, where
    /// `resized` says whether the whole image is resized to `input_size × input_size`.
    pub fn target_size(&self, width: usize, height: usize) -> (usize, usize, bool) {
        let s = self.input_size;
        let resize = match self.resize {
            Resize::Always => true,
            Resize::Patches => width <= s && height <= s,
            Resize::Never => false,
        };
        if resize {
            return (s, s, true);
        }
        let p = self.patch.max(1);
        let crop = |v: usize| if v < p { p } else { v / p * p };
        (crop(height), crop(width), false)
    }

    /// The model input for one image. The image must have pixels (`width, height > 0`).
    pub fn apply(&self, image: &RgbImage) -> Tensor3 {
        let (w, h) = (image.width, image.height);
        let (out_h, out_w, resized) = self.target_size(w, h);
        let axis = |input: usize, output: usize| {
            if resized {
                nearest_map(input, output, self.reference_upsample)
            } else if input < output {
                nearest_map(input, output, 0) // smaller than one patch: enlarge
            } else {
                (0..output).collect() // crop to whole patches
            }
        };
        let (rows, cols) = (axis(h, out_h), axis(w, out_w));
        // Per-channel affine map: one or two normalisations folded into x·a + b.
        let mut affine = [(1.0f32, 0.0f32); 3];
        for (c, ab) in affine.iter_mut().enumerate() {
            let (m, s) = (self.mean[c], self.std[c]);
            *ab = (1.0 / s, -m / s);
            if self.double_normalize {
                *ab = (ab.0 / s, (ab.1 - m) / s);
            }
        }
        let mut data = vec![0.0f32; 3 * out_h * out_w];
        for (r, &sr) in rows.iter().enumerate() {
            for (c, &sc) in cols.iter().enumerate() {
                let px = image.pixel(sc, sr);
                for k in 0..3 {
                    data[(k * out_h + r) * out_w + c] = px[k] * affine[k].0 + affine[k].1;
                }
            }
        }
        Tensor3 { height: out_h, width: out_w, data }
    }
}

impl Preprocess {
    /// The model inputs of a set of images, in parallel; `None` for an image without pixels
    /// (or with a buffer of the wrong length), which the extractors answer with an empty map.
    pub fn apply_all(&self, images: &[RgbImage]) -> Vec<Option<Tensor3>> {
        let valid = |img: &RgbImage| img.width > 0 && img.height > 0 && img.data.len() == img.width * img.height * 3;
        images.par_iter().map(|img| valid(img).then(|| self.apply(img))).collect()
    }
}

/// Splits inputs into consecutive runs of equal-sized images, at most `max` long, each run one
/// batch of a forward pass; a `None` input is a run of its own.
pub fn equal_size_runs(inputs: &[Option<Tensor3>], max: usize) -> Vec<Range<usize>> {
    let size = |i: usize| inputs[i].as_ref().map(|t| (t.height, t.width));
    let mut runs = Vec::new();
    let mut i = 0;
    while i < inputs.len() {
        let mut j = i + 1;
        if size(i).is_some() {
            while j < inputs.len() && j - i < max.max(1) && size(j) == size(i) {
                j += 1;
            }
        }
        runs.push(i..j);
        i = j;
    }
    runs
}

/// The images of a run as one `[n, 3, height, width]` batch.
pub fn stack(inputs: &[Option<Tensor3>]) -> Vec<f32> {
    inputs.iter().flatten().flat_map(|t| t.data.iter().copied()).collect()
}

impl Preprocess {
    /// One feature map per image, in order: the images' model inputs ([`Preprocess::apply_all`]),
    /// then `forward(batch, n, height, width)` on each run of equal-sized inputs (at most `max`
    /// at a time), which returns that run's maps; an image the preprocessing rejects gets
    /// `empty()`.
    pub fn extract_in_runs(
        &self,
        images: &[RgbImage],
        max: usize,
        empty: impl Fn() -> FeatureMap,
        mut forward: impl FnMut(&[f32], usize, usize, usize) -> Vec<FeatureMap>,
    ) -> Vec<FeatureMap> {
        let inputs = self.apply_all(images);
        let mut out: Vec<Option<FeatureMap>> = vec![None; inputs.len()];
        for run in equal_size_runs(&inputs, max) {
            let Some(first) = &inputs[run.start] else {
                out[run.start] = Some(empty());
                continue;
            };
            let maps = forward(&stack(&inputs[run.clone()]), run.len(), first.height, first.width);
            for (k, map) in maps.into_iter().enumerate() {
                out[run.start + k] = Some(map);
            }
        }
        out.into_iter().map(|m| m.unwrap_or_else(&empty)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_group_equal_sizes_up_to_the_batch() {
        let t = |h: usize, w: usize| Some(Tensor3 { height: h, width: w, data: vec![0.0; 3 * h * w] });
        let inputs = [t(2, 2), t(2, 2), t(2, 2), None, t(2, 2), t(3, 2), t(3, 2)];
        assert_eq!(equal_size_runs(&inputs, 2), vec![0..2, 2..3, 3..4, 4..5, 5..7]);
        assert_eq!(equal_size_runs(&inputs, 0).len(), 7);
        assert_eq!(equal_size_runs(&[None, None], 8), vec![0..1, 1..2]);
        assert_eq!(stack(&inputs[..2]).len(), 24);
    }

    #[test]
    fn composed_nearest_equals_the_direct_resize_for_64_px_patches() {
        // Spec: 64 → 384 → 224 equals 64 → 224 with src = ⌊2·dst/7⌋.
        let via = nearest_map(64, 224, 384);
        let direct: Vec<usize> = (0..224).map(|i| 2 * i / 7).collect();
        assert_eq!(via, direct);
        assert_eq!(nearest_map(64, 224, 0), direct);
        // Not so for other sizes, where the intermediate step matters.
        assert_ne!(nearest_map(100, 224, 384), nearest_map(100, 224, 0));
        assert_eq!(nearest_map(3, 7, 0), vec![0, 0, 0, 1, 1, 2, 2]);
    }

    #[test]
    fn double_normalisation_and_sizes() {
        let mut img = RgbImage::new(64, 64);
        img.set_pixel(0, 0, [0.9, 0.2, 0.5]);
        let pre = Preprocess::reference(16);
        let t = pre.apply(&img);
        assert_eq!((t.height, t.width), (224, 224));
        let want = |x: f32, c: usize| ((x - IMAGENET_MEAN[c]) / IMAGENET_STD[c] - IMAGENET_MEAN[c]) / IMAGENET_STD[c];
        for (c, x) in [0.9f32, 0.2, 0.5].into_iter().enumerate() {
            // Input pixel (0, 0) covers output pixels 0..=3 (⌊2·3/7⌋ = 0, ⌊2·4/7⌋ = 1).
            assert!((t.data[c * 224 * 224 + 3] - want(x, c)).abs() < 1e-5);
            assert!((t.data[c * 224 * 224 + 4] - want(0.0, c)).abs() < 1e-5);
        }
        let single = Preprocess { double_normalize: false, ..pre.clone() }.apply(&img);
        assert!((single.data[0] - (0.9 - 0.485) / 0.229).abs() < 1e-5);
        // Whole views keep their size, cropped to whole patches; tiny images grow to a patch.
        assert_eq!(pre.target_size(1008, 756), (752, 1008, false));
        assert_eq!(pre.target_size(250, 100), (96, 240, false));
        let never = Preprocess { resize: Resize::Never, ..pre.clone() };
        assert_eq!(never.target_size(64, 64), (64, 64, false));
        assert_eq!(never.target_size(10, 40), (32, 16, false));
        let t = never.apply(&RgbImage::new(10, 40));
        assert_eq!((t.height, t.width, t.data.len()), (32, 16, 3 * 32 * 16));
        let always = Preprocess { resize: Resize::Always, ..pre };
        assert_eq!(always.target_size(1008, 756), (224, 224, true));
    }
}
