//! The image-border prior of the mask rules (`masks.border_splits`): an object seen by a
//! capture rarely runs along most of the frame's edge, while the ground, the walls and the sky
//! always do (the boundary prior of salient-object detection, e.g. Zhu et al. 2014, "Saliency
//! optimization from robust background detection").
//!
//! When the object takes only a small part of the view, the two k-means clusters may split the
//! background (wall against floor) instead of separating the object, and the object is then
//! part of whichever background cluster holds it. The mask then covers much of the image
//! border. Splitting that cluster once more, on its own pixels' logits, separates the object
//! from the background it was lumped with; the mask rules then choose among the two halves.

use crate::config::MaskConfig;
use crate::segment::infer::cluster_logits;

/// Fewest pixels a cluster must hold to be split again.
pub const MIN_SPLIT_PIXELS: usize = 16;

/// Share of the outermost ring of pixels of a `width x height` image that `mask` covers
/// (0 for an empty image).
pub fn border_share(mask: &[bool], width: usize, height: usize) -> f64 {
    assert_eq!(mask.len(), width * height, "mask size");
    if width == 0 || height == 0 {
        return 0.0;
    }
    let mut ring = 0usize;
    let mut covered = 0usize;
    for r in 0..height {
        for c in 0..width {
            if r == 0 || c == 0 || r + 1 == height || c + 1 == width {
                ring += 1;
                covered += usize::from(mask[r * width + c]);
            }
        }
    }
    covered as f64 / ring as f64
}

/// Labels with `cluster` split in two by k-means (two clusters, the settings of `masks`
/// otherwise) over its own pixels' `logits` (`[pixels, d]`): its pixels keep their label or
/// take the new label `k`. `None` when the cluster is too small or its logits do not split.
pub fn split_cluster(
    labels: &[u32],
    k: usize,
    cluster: usize,
    logits: &[f32],
    d: usize,
    masks: &MaskConfig,
    seed: u64,
) -> Option<Vec<u32>> {
    let members: Vec<usize> = (0..labels.len()).filter(|&i| labels[i] as usize == cluster).collect();
    if members.len() < MIN_SPLIT_PIXELS {
        return None;
    }
    let values: Vec<f32> = members.iter().flat_map(|&i| logits[i * d..(i + 1) * d].iter().copied()).collect();
    let halves = MaskConfig { clusters: 2, ..masks.clone() };
    let km = cluster_logits(&values, d, &halves, seed).ok()?;
    if km.k < 2 {
        return None;
    }
    let mut out = labels.to_vec();
    for (&i, &half) in members.iter().zip(&km.labels) {
        if half == 1 {
            out[i] = k as u32;
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn border_share_counts_the_outer_ring_once() {
        // 4x3 image: the ring holds 10 pixels, the centre 2.
        let mut mask = vec![false; 12];
        assert_eq!(border_share(&mask, 4, 3), 0.0);
        mask[5] = true; // centre
        mask[6] = true; // centre
        assert_eq!(border_share(&mask, 4, 3), 0.0);
        mask[0] = true; // a corner counts once
        assert!((border_share(&mask, 4, 3) - 0.1).abs() < 1e-12);
        let full = vec![true; 12];
        assert_eq!(border_share(&full, 4, 3), 1.0);
        assert_eq!(border_share(&[], 0, 0), 0.0);
    }

    #[test]
    fn a_cluster_of_two_kinds_of_logits_splits_along_them() {
        // Cluster 1 holds logits near (1, 0) and near (0, 1); cluster 0 is left alone.
        let mut labels = Vec::new();
        let mut logits = Vec::new();
        for i in 0..40 {
            labels.push(1);
            let jitter = (i % 5) as f32 * 0.01;
            let row = if i < 20 { [1.0 + jitter, 0.0] } else { [0.0, 1.0 + jitter] };
            logits.extend_from_slice(&row);
        }
        labels.extend([0; 10]);
        for _ in 0..10 {
            logits.extend_from_slice(&[5.0, 5.0]);
        }
        let split = split_cluster(&labels, 2, 1, &logits, 2, &MaskConfig::default(), 0).expect("splits");
        assert!(split[40..].iter().all(|&l| l == 0), "the other cluster is untouched");
        let first = split[0];
        assert!(first == 1 || first == 2);
        assert!(split[..20].iter().all(|&l| l == first));
        assert!(split[20..40].iter().all(|&l| l != first && (l == 1 || l == 2)));
    }

    #[test]
    fn small_or_uniform_clusters_do_not_split() {
        let labels = vec![1u32; 8];
        let logits = vec![0.5f32; 16];
        assert!(split_cluster(&labels, 2, 1, &logits, 2, &MaskConfig::default(), 0).is_none(), "too small");
        let labels = vec![1u32; 40];
        let logits = vec![0.5f32; 80];
        assert!(split_cluster(&labels, 2, 1, &logits, 2, &MaskConfig::default(), 0).is_none(), "one value");
    }
}
