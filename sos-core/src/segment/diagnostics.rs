//! A picture of why a view's mask came out as it did: every k-means cluster in its own colour
//! (the one named foreground brightest), the pixels the support-plane rule dropped darkened,
//! the focus voters white and empty rays black. Written beside each held-out mask, it shows at
//! a glance whether a bad mask comes from the clustering, the foreground vote or the rendered
//! geometry (a support plane that was not found).

use crate::camera::Vec3;
use crate::image::RgbImage;

/// Colours of the clusters, in label order (repeating beyond eight clusters).
const PALETTE: [[f32; 3]; 8] = [
    [0.12, 0.47, 0.71],
    [1.0, 0.5, 0.05],
    [0.17, 0.63, 0.17],
    [0.84, 0.15, 0.16],
    [0.58, 0.4, 0.74],
    [0.55, 0.34, 0.29],
    [0.89, 0.47, 0.76],
    [0.74, 0.74, 0.13],
];

/// Brightness of the clusters that are not the foreground one.
const OTHER_CLUSTER_SHADE: f32 = 0.45;

/// Brightness left to pixels on a support plane.
const SUPPORT_SHADE: f32 = 0.4;

/// What one view's mask was decided from.
pub struct MaskEvidence<'a> {
    /// k-means cluster of each pixel, row-major.
    pub labels: &'a [u32],
    /// The cluster named foreground.
    pub foreground_cluster: usize,
    /// Whether each pixel lies on a support plane (`None` when the rule is off).
    pub support: Option<&'a [bool]>,
    /// Pixels nearest the focus, which voted for the foreground cluster.
    pub voters: &'a [usize],
    /// Rendered 3D point of each pixel, `None` for empty rays.
    pub points: &'a [Option<Vec3>],
}

/// Draws the evidence as a `width x height` image (see the module documentation).
pub fn evidence_image(evidence: &MaskEvidence, width: usize, height: usize) -> RgbImage {
    let mut out = RgbImage::new(width, height);
    for (i, px) in out.data.chunks_exact_mut(3).enumerate().take(evidence.labels.len()) {
        if !evidence.points.get(i).is_some_and(Option::is_some) {
            continue;
        }
        let label = evidence.labels[i] as usize;
        let mut shade = if label == evidence.foreground_cluster { 1.0 } else { OTHER_CLUSTER_SHADE };
        if evidence.support.is_some_and(|s| s.get(i).copied().unwrap_or(false)) {
            shade *= SUPPORT_SHADE;
        }
        let colour = PALETTE[label % PALETTE.len()];
        for k in 0..3 {
            px[k] = colour[k] * shade;
        }
    }
    for &i in evidence.voters {
        if let Some(px) = out.data.get_mut(i * 3..i * 3 + 3) {
            px.copy_from_slice(&[1.0; 3]);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_kind_of_pixel_is_drawn_apart() {
        // Four pixels: foreground cluster, other cluster, other cluster on a support plane,
        // an empty ray; pixel 0 also votes.
        let labels = [1, 0, 0, 1, 1];
        let support = [false, false, true, false, false];
        let points = [Some([0.0; 3]), Some([0.0; 3]), Some([0.0; 3]), None, Some([0.0; 3])];
        let evidence = MaskEvidence {
            labels: &labels,
            foreground_cluster: 1,
            support: Some(&support),
            voters: &[0],
            points: &points,
        };
        let img = evidence_image(&evidence, 5, 1);
        assert_eq!(img.pixel(0, 0), [1.0; 3], "a voter is white");
        assert_eq!(img.pixel(3, 0), [0.0; 3], "an empty ray is black");
        assert_eq!(img.pixel(4, 0), PALETTE[1], "the foreground cluster at full brightness");
        let other = img.pixel(1, 0);
        let dropped = img.pixel(2, 0);
        for k in 0..3 {
            assert!((other[k] - PALETTE[0][k] * OTHER_CLUSTER_SHADE).abs() < 1e-6);
            assert!((dropped[k] - other[k] * SUPPORT_SHADE).abs() < 1e-6);
        }
        // Without the support rule, nothing is darkened.
        let plain = MaskEvidence { support: None, ..evidence };
        assert_eq!(evidence_image(&plain, 5, 1).pixel(2, 0), other);
    }
}
