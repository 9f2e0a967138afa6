//! Colour refinement of a view's mask along its outline: every pixel within a band of the
//! mask's edge goes to the side whose colours explain its rendered colour better.
//!
//! The head's logits come from a teacher that sees cells several pixels wide, and the field's
//! segmentation input is smooth, so a mask's outline wanders into whatever touches the object
//! (a leaf behind a flower, a shadow on the ground) and drops stripes of a texture. Two colour
//! histograms, one of the mask's interior and one of the background's (both away from the
//! outline), decide each pixel near the outline by their log-likelihood ratio, averaged over the
//! pixel's 3x3 neighbourhood, as GrabCut's colour models do, without its graph cut: only the
//! band moves, so a colour shared by object and background cannot spread across the image.

use crate::image::RgbImage;

/// Levels per colour channel of the histograms (16³ bins): coarse enough for a few thousand
/// pixels to fill the colours they hold, fine enough to tell a leaf from a petal.
pub const COLOUR_LEVELS: usize = 16;

/// Pixels nearer the outline than this (4-connected steps) inform neither histogram: the
/// outline's own pixels are the ones in doubt.
pub const CORE_MARGIN: u32 = 2;

/// Fewest interior pixels either side needs for its histogram to be trusted; with fewer the
/// mask is left as it is.
pub const MIN_CORE_PIXELS: usize = 20;

/// Moves the pixels within `band` steps (4-connected) of the mask's outline to the side whose
/// colour histogram gives their colours the higher likelihood; a pixel joins the mask only
/// when the log-likelihood ratio, averaged over its 3x3 neighbourhood, exceeds `margin` (0: the
/// likelier side wins). `rgb` is the view's rendered colour, `mask` its row-major foreground.
/// Returns the refined mask.
pub fn refine_by_colour(rgb: &RgbImage, mask: &[bool], band: u32, margin: f32) -> Vec<bool> {
    let (w, h) = (rgb.width, rgb.height);
    if band == 0 || mask.len() != w * h || rgb.data.len() != w * h * 3 {
        return mask.to_vec();
    }
    let to_background = city_block_distance(mask, w, h, false);
    let to_foreground = city_block_distance(mask, w, h, true);
    // A pixel's steps to the other side of the outline.
    let across: Vec<u32> =
        mask.iter().enumerate().map(|(i, &f)| if f { to_background[i] } else { to_foreground[i] }).collect();
    let codes: Vec<usize> = rgb.data.chunks_exact(3).map(colour_code).collect();
    let bins = COLOUR_LEVELS.pow(3);
    let (mut inside, mut outside) = (vec![0u32; bins], vec![0u32; bins]);
    let (mut n_inside, mut n_outside) = (0usize, 0usize);
    for i in 0..mask.len() {
        if across[i] <= CORE_MARGIN {
            continue;
        }
        if mask[i] {
            inside[codes[i]] += 1;
            n_inside += 1;
        } else {
            outside[codes[i]] += 1;
            n_outside += 1;
        }
    }
    if n_inside < MIN_CORE_PIXELS || n_outside < MIN_CORE_PIXELS {
        return mask.to_vec();
    }
    // Each bin counts one pixel more than it holds (Laplace), so an unseen colour has a small,
    // finite likelihood on both sides.
    let (total_in, total_out) = ((n_inside + bins) as f32, (n_outside + bins) as f32);
    let ratio =
        |code: usize| ((inside[code] as f32 + 1.0) / total_in).ln() - ((outside[code] as f32 + 1.0) / total_out).ln();
    // Each pixel weighs its 3x3 neighbourhood's colour evidence: a lone pixel of a colour the two
    // sides share does not flip on its own, so thin parts and colour clashes stay in one piece.
    let evidence: Vec<f32> = codes.iter().map(|&c| ratio(c)).collect();
    let smoothed = box_mean_3x3(&evidence, w, h);
    mask.iter().enumerate().map(|(i, &f)| if across[i] <= band { smoothed[i] > margin } else { f }).collect()
}

/// The mean of each pixel's 3x3 neighbourhood (the pixels inside the image).
fn box_mean_3x3(values: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut out = vec![0.0; values.len()];
    for y in 0..h {
        for x in 0..w {
            let (mut sum, mut n) = (0.0, 0.0);
            for yy in y.saturating_sub(1)..(y + 2).min(h) {
                for xx in x.saturating_sub(1)..(x + 2).min(w) {
                    sum += values[yy * w + xx];
                    n += 1.0;
                }
            }
            out[y * w + x] = sum / n;
        }
    }
    out
}

/// The band width in pixels for a view: `fraction` of its diagonal, at least one pixel when
/// the fraction is positive.
pub fn band_pixels(fraction: f32, width: usize, height: usize) -> u32 {
    if fraction <= 0.0 {
        return 0;
    }
    let diagonal = ((width * width + height * height) as f32).sqrt();
    (fraction * diagonal).round().max(1.0) as u32
}

/// The histogram bin of a colour in [0, 1]³ (values outside are clamped).
fn colour_code(c: &[f32]) -> usize {
    let level = |v: f32| ((v * COLOUR_LEVELS as f32) as isize).clamp(0, COLOUR_LEVELS as isize - 1) as usize;
    (level(c[0]) * COLOUR_LEVELS + level(c[1])) * COLOUR_LEVELS + level(c[2])
}

/// 4-connected steps from each pixel to the nearest pixel whose mask value is `target`
/// (0 on those pixels; `u32::MAX` when the image holds none): two raster passes, exact for
/// the city-block metric.
fn city_block_distance(mask: &[bool], w: usize, h: usize, target: bool) -> Vec<u32> {
    let far = u32::MAX / 2;
    let mut d: Vec<u32> = mask.iter().map(|&m| if m == target { 0 } else { far }).collect();
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if x > 0 {
                d[i] = d[i].min(d[i - 1] + 1);
            }
            if y > 0 {
                d[i] = d[i].min(d[i - w] + 1);
            }
        }
    }
    for y in (0..h).rev() {
        for x in (0..w).rev() {
            let i = y * w + x;
            if x + 1 < w {
                d[i] = d[i].min(d[i + 1] + 1);
            }
            if y + 1 < h {
                d[i] = d[i].min(d[i + w] + 1);
            }
        }
    }
    if d.iter().all(|&v| v >= far) {
        return vec![u32::MAX; d.len()];
    }
    d
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `w`×`h` image painted by `colour(x, y)`.
    fn image(w: usize, h: usize, colour: impl Fn(usize, usize) -> [f32; 3]) -> RgbImage {
        let mut im = RgbImage::new(w, h);
        for y in 0..h {
            for x in 0..w {
                im.data[(y * w + x) * 3..][..3].copy_from_slice(&colour(x, y));
            }
        }
        im
    }

    const ORANGE: [f32; 3] = [0.95, 0.45, 0.2];
    const GREEN: [f32; 3] = [0.2, 0.6, 0.25];

    #[test]
    fn a_mask_that_spills_onto_another_colour_is_pulled_back_to_its_object() {
        // An orange square (x, y in 20..40) on green; the mask spills 4 px right and down.
        let (w, h) = (64, 64);
        let object = |x: usize, y: usize| (20..40).contains(&x) && (20..40).contains(&y);
        let rgb = image(w, h, |x, y| if object(x, y) { ORANGE } else { GREEN });
        let spilled: Vec<bool> =
            (0..w * h).map(|i| (20..44).contains(&(i % w)) && (20..44).contains(&(i / w))).collect();
        let refined = refine_by_colour(&rgb, &spilled, 6, 0.0);
        let exact: Vec<bool> = (0..w * h).map(|i| object(i % w, i / w)).collect();
        assert_eq!(refined, exact);
    }

    #[test]
    fn stripes_left_out_of_a_mask_join_it_when_their_colour_is_the_objects() {
        // A striped object (orange and dark red rows) on green; the mask misses some rows of
        // each colour, as a head does that lumps one stripe colour with the background.
        let (w, h) = (64, 64);
        let red = [0.5, 0.1, 0.1];
        let object = |x: usize, y: usize| (16..48).contains(&x) && (16..48).contains(&y);
        let rgb = image(w, h, |x, y| match (object(x, y), (y / 2) % 2) {
            (true, 0) => ORANGE,
            (true, _) => red,
            _ => GREEN,
        });
        let holed: Vec<bool> = (0..w * h).map(|i| object(i % w, i / w) && !(30..33).contains(&(i / w))).collect();
        let refined = refine_by_colour(&rgb, &holed, 3, 0.0);
        for y in 30..33 {
            for x in 17..47 {
                assert!(refined[y * w + x], "pixel ({x}, {y}) of a left-out stripe stays out");
            }
        }
        // Nothing of the green around the object joins.
        let green_joined = (0..w * h).filter(|&i| refined[i] && !object(i % w, i / w)).count();
        assert_eq!(green_joined, 0);
    }

    #[test]
    fn pixels_beyond_the_band_keep_their_side() {
        // The whole left half is masked but only its outermost columns are orange: the green
        // pixels more than `band` from the outline stay in the mask.
        let (w, h) = (40, 20);
        let rgb = image(w, h, |x, _| if (16..20).contains(&x) { ORANGE } else { GREEN });
        let mask: Vec<bool> = (0..w * h).map(|i| i % w < 20).collect();
        let refined = refine_by_colour(&rgb, &mask, 2, 0.0);
        for y in 0..h {
            assert!(refined[y * w], "a pixel far from the outline moved");
        }
    }

    #[test]
    fn masks_without_two_sides_are_left_alone() {
        let rgb = image(16, 16, |x, _| if x < 8 { ORANGE } else { GREEN });
        for mask in [vec![false; 256], vec![true; 256]] {
            assert_eq!(refine_by_colour(&rgb, &mask, 4, 0.0), mask);
        }
        // A band of zero turns the refinement off.
        let half: Vec<bool> = (0..256).map(|i| i % 16 < 4).collect();
        assert_eq!(refine_by_colour(&rgb, &half, 0, 0.0), half);
    }

    #[test]
    fn the_band_follows_the_view_size() {
        assert_eq!(band_pixels(0.025, 504, 378), 16);
        assert_eq!(band_pixels(0.025, 160, 120), 5);
        assert_eq!(band_pixels(0.0001, 16, 12), 1);
        assert_eq!(band_pixels(0.0, 504, 378), 0);
    }

    #[test]
    fn one_pixel_of_a_shared_colour_does_not_flip_alone() {
        // An orange square on green with a single green pixel inside the object, next to its
        // outline: its neighbours' evidence keeps it in the mask.
        let (w, h) = (48, 48);
        let object = |x: usize, y: usize| (12..36).contains(&x) && (12..36).contains(&y);
        let rgb = image(w, h, |x, y| if object(x, y) && (x, y) != (14, 20) { ORANGE } else { GREEN });
        let exact: Vec<bool> = (0..w * h).map(|i| object(i % w, i / w)).collect();
        let refined = refine_by_colour(&rgb, &exact, 4, 0.5);
        assert!(refined[20 * w + 14], "the lone green pixel left the mask");
    }

    #[test]
    fn box_means_cover_the_pixels_inside_the_image() {
        let values = [1.0, 2.0, 3.0, 4.0];
        // Every 3x3 window of a 2x2 image holds all four pixels.
        assert_eq!(box_mean_3x3(&values, 2, 2), vec![2.5; 4]);
        let row = box_mean_3x3(&[0.0, 3.0, 6.0], 3, 1);
        assert_eq!(row, vec![1.5, 3.0, 4.5]);
    }

    #[test]
    fn distances_are_city_block_steps() {
        // One foreground pixel in the middle of a 5x5 image.
        let mask: Vec<bool> = (0..25).map(|i| i == 12).collect();
        let d = city_block_distance(&mask, 5, 5, true);
        assert_eq!(d[12], 0);
        assert_eq!(d[0], 4);
        assert_eq!(d[7], 1);
        assert!(city_block_distance(&[false; 4], 2, 2, true).iter().all(|&v| v == u32::MAX));
    }
}
