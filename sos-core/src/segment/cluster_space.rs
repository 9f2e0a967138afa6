//! Which space a view's logits are clustered in: the raw logits (as the reference does) or
//! their directions (unit length).
//!
//! The contrastive losses compare logits by direction only, so the head is trained to put the
//! object and its background apart in angle; the length of a pixel's logits is left to drift.
//! On most scenes the raw clusters follow the directions anyway (and the lengths help: a dim
//! base whose direction is uncertain has short logits, like the object's). Where the lengths
//! vary across the view more than the directions do, the raw clusters cut across what the
//! losses trained (the middle of a room against its corners, the ground near the cameras
//! against the ground far off). The test: the raw partition's share of the directions'
//! variance against the share that clustering the directions themselves explains.

use crate::config::MaskConfig;
use crate::kmeans::{kmeans, KMeansError, KMeansResult};
use crate::segment::infer::{cluster_logits, kmeans_config};

/// Below this ratio of explained direction variance (raw partition over direction partition),
/// the raw clusters cut across the directions and the directions are clustered instead: the
/// raw partition then explains less than half of what the trained signal separates. On the
/// benchmark heads the ratio is above 0.75 in almost every view and 0.12–0.43 where raw
/// clustering splits a view by length (`RESULTS.md`, "Clustering by direction").
pub const DIRECTION_CUT_RATIO: f64 = 0.5;

/// Pixels the test clusters by direction (an even subsample of the view's).
const TEST_POINTS: usize = 8192;

/// A view's clusters and the space they were found in.
pub struct ViewClusters {
    /// The k-means result used for the mask.
    pub result: KMeansResult,
    /// Whether the directions (unit-length logits) were clustered.
    pub by_direction: bool,
}

/// Each row of `values` (`[n, d]`) scaled to unit length (rows whose squares overflow are
/// scaled down first; all-zero rows stay zero).
pub fn unit_rows(values: &mut [f32], d: usize) {
    for row in values.chunks_exact_mut(d) {
        if !row.iter().map(|v| v * v).sum::<f32>().is_finite() {
            // The squares overflow (logits beyond ~1e19): scale the row down first, or it
            // would divide by an infinite norm to zero.
            let largest = row.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            row.iter_mut().for_each(|v| *v /= largest);
        }
        let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-10);
        row.iter_mut().for_each(|v| *v /= norm);
    }
}

/// Share of the variance of `points` (`[n, d]`) that the partition `labels` (into `0..k`)
/// explains: 1 − within-cluster / total sum of squares; 0 when the points do not vary.
pub fn explained_share(points: &[f32], d: usize, labels: &[u32], k: usize) -> f64 {
    let n = labels.len();
    if n == 0 || d == 0 {
        return 0.0;
    }
    let mut sums = vec![0.0f64; (k + 1) * d];
    let mut counts = vec![0usize; k + 1];
    let mut squares = 0.0f64;
    for (row, &l) in points.chunks_exact(d).zip(labels) {
        let l = l as usize;
        counts[l] += 1;
        counts[k] += 1;
        for (j, &v) in row.iter().enumerate() {
            let v = v as f64;
            sums[l * d + j] += v;
            sums[k * d + j] += v;
            squares += v * v;
        }
    }
    // Σ|x − mean|² = Σ|x|² − |Σx|²/count, per cluster and over all points.
    let spread = |c: usize| {
        if counts[c] == 0 {
            return 0.0;
        }
        sums[c * d..(c + 1) * d].iter().map(|s| s * s).sum::<f64>() / counts[c] as f64
    };
    let total = squares - spread(k);
    let within = squares - (0..k).map(spread).sum::<f64>();
    if total <= f64::EPSILON * squares.max(1.0) {
        return 0.0;
    }
    (1.0 - within / total).clamp(0.0, 1.0)
}

/// Clusters one view's logits (`[n, d]`) by `masks`: raw (or, with `masks.normalize`, by
/// direction) and, with `masks.direction_check` on raw logits, by direction instead when the
/// raw clusters explain less than [`DIRECTION_CUT_RATIO`] of what the direction clusters
/// explain of the directions' variance.
pub fn cluster_view(logits: &[f32], d: usize, masks: &MaskConfig, seed: u64) -> Result<ViewClusters, KMeansError> {
    let raw = cluster_logits(logits, d, masks, seed)?;
    if masks.normalize || masks.softmax || !masks.direction_check {
        return Ok(ViewClusters { result: raw, by_direction: masks.normalize });
    }
    // The test runs on an even subsample of the pixels: a share of variance needs far fewer
    // points than a mask, and the full clustering by direction is paid only where it is used.
    let n = raw.labels.len();
    let step = n.div_ceil(TEST_POINTS).max(1);
    let mut units: Vec<f32> = logits.chunks_exact(d).step_by(step).flatten().copied().collect();
    unit_rows(&mut units, d);
    let raw_labels: Vec<u32> = raw.labels.iter().step_by(step).copied().collect();
    let sampled = kmeans(&units, d, &kmeans_config(masks, seed))?;
    let raw_share = explained_share(&units, d, &raw_labels, raw.k);
    let direction_share = explained_share(&units, d, &sampled.labels, sampled.k);
    Ok(if raw_share < DIRECTION_CUT_RATIO * direction_share {
        let directional = MaskConfig { normalize: true, ..masks.clone() };
        ViewClusters { result: cluster_logits(logits, d, &directional, seed)?, by_direction: true }
    } else {
        ViewClusters { result: raw, by_direction: false }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two directions `degrees` apart (the object's and the background's), each at lengths
    /// from `short` to `long`.
    fn two_directions(degrees: f32, short: f32, long: f32, per_group: usize) -> (Vec<f32>, Vec<bool>) {
        let mut logits = Vec::new();
        let mut object = Vec::new();
        let a = degrees.to_radians();
        for (dir, is_object) in [([1.0f32, 0.0], true), ([a.cos(), a.sin()], false)] {
            for i in 0..per_group {
                let t = i as f32 / (per_group - 1) as f32;
                let len = short + (long - short) * t;
                logits.extend([dir[0] * len, dir[1] * len]);
                object.push(is_object);
            }
        }
        (logits, object)
    }

    fn follows(labels: &[u32], truth: &[bool]) -> bool {
        let first = labels[truth.iter().position(|&t| t).unwrap()];
        labels.iter().zip(truth).all(|(&l, &t)| (l == first) == t)
    }

    #[test]
    fn explained_share_is_one_for_separate_points_and_zero_for_a_cut_across() {
        let points = [0.0f32, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0];
        assert!((explained_share(&points, 2, &[0, 0, 1, 1], 2) - 1.0).abs() < 1e-9);
        assert!(explained_share(&points, 2, &[0, 1, 0, 1], 2).abs() < 1e-9);
        assert_eq!(explained_share(&[0.5; 8], 2, &[0, 1, 0, 1], 2), 0.0, "no variance");
    }

    #[test]
    fn lengths_that_vary_more_than_directions_switch_clustering_to_directions() {
        // Directions 30 degrees apart at lengths from 0.05 to 3: raw k-means splits short
        // from long across both directions.
        let (logits, object) = two_directions(30.0, 0.05, 3.0, 40);
        let masks = MaskConfig::default();
        let raw = cluster_logits(&logits, 2, &masks, 0).unwrap();
        assert!(!follows(&raw.labels, &object), "raw clusters follow length here");
        let view = cluster_view(&logits, 2, &masks, 0).unwrap();
        assert!(view.by_direction);
        assert!(follows(&view.result.labels, &object));
        // Switched off, the raw clusters stay.
        let off = cluster_view(&logits, 2, &MaskConfig { direction_check: false, ..masks }, 0).unwrap();
        assert!(!off.by_direction);
        assert_eq!(off.result.labels, raw.labels);
    }

    #[test]
    fn raw_clusters_that_follow_the_directions_are_kept() {
        // Lengths vary little: the raw clusters already follow the directions.
        let (logits, object) = two_directions(90.0, 0.8, 1.2, 40);
        let masks = MaskConfig::default();
        let view = cluster_view(&logits, 2, &masks, 0).unwrap();
        assert!(!view.by_direction);
        assert!(follows(&view.result.labels, &object));
        assert_eq!(view.result.labels, cluster_logits(&logits, 2, &masks, 0).unwrap().labels);
    }
}
