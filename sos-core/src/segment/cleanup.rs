//! Mask cleanup after clustering (`masks.keep = "connected"`): keep only the foreground
//! regions that contain the object.
//!
//! k-means labels pixels by their logits alone, so a patch of background whose logits happen
//! to resemble the object's (a noisy, poorly reconstructed far wall, say) joins the foreground
//! cluster although it lies elsewhere in the image. The `focus` rule already knows which pixels
//! show the object: the ones whose rendered 3D points lie nearest the focus point. This keeps
//! the 4-connected foreground regions that contain at least one of those pixels and returns
//! every other foreground region to the background.
//!
//! Such a patch often touches the object in the image (a blob of wall beside the silhouette, a
//! strand of floaters above it) while lying far behind it. With [`DepthContinuity`], two
//! neighbouring pixels belong to one region only where the rendered depth is continuous, so a
//! silhouette edge separates the object from whatever is seen behind it.

use std::collections::VecDeque;

/// Neighbouring pixels join one region only if their rendered depths differ by at most
/// `max_jump` times the nearer of the two.
#[derive(Debug, Clone, Copy)]
pub struct DepthContinuity<'a> {
    /// Rendered depth of every pixel, row-major.
    pub depth: &'a [f32],
    /// Largest relative depth step inside a region (e.g. 0.1).
    pub max_jump: f32,
}

impl DepthContinuity<'_> {
    fn joins(&self, i: usize, j: usize) -> bool {
        let (a, b) = (self.depth[i], self.depth[j]);
        (a - b).abs() <= self.max_jump * a.min(b)
    }
}

/// Keeps the 4-connected regions of `foreground` (row-major `width x height`) that contain at
/// least one pixel of `seeds`; seeds outside the foreground are ignored. With `depth`, regions
/// also stop where the depth jumps. With no seed in the foreground, the mask is returned
/// unchanged (there is nothing to anchor the cleanup on).
pub fn keep_seeded_regions(
    foreground: &[bool],
    width: usize,
    height: usize,
    seeds: &[usize],
    depth: Option<DepthContinuity>,
) -> Vec<bool> {
    assert_eq!(foreground.len(), width * height, "mask size");
    if let Some(d) = &depth {
        assert_eq!(d.depth.len(), foreground.len(), "depth size");
    }
    let mut kept = vec![false; foreground.len()];
    let mut queue: VecDeque<usize> = seeds.iter().copied().filter(|&s| s < foreground.len() && foreground[s]).collect();
    if queue.is_empty() {
        return foreground.to_vec();
    }
    for &s in &queue {
        kept[s] = true;
    }
    // Breadth-first flood fill from every seed at once.
    while let Some(i) = queue.pop_front() {
        let (r, c) = (i / width, i % width);
        let neighbours = [
            (r > 0).then(|| i - width),
            (r + 1 < height).then(|| i + width),
            (c > 0).then(|| i - 1),
            (c + 1 < width).then(|| i + 1),
        ];
        for j in neighbours.into_iter().flatten() {
            if foreground[j] && !kept[j] && depth.as_ref().is_none_or(|d| d.joins(i, j)) {
                kept[j] = true;
                queue.push_back(j);
            }
        }
    }
    kept
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mask(rows: &[&str]) -> (Vec<bool>, usize, usize) {
        let w = rows[0].len();
        (rows.iter().flat_map(|r| r.chars().map(|c| c == '#')).collect(), w, rows.len())
    }

    #[test]
    fn keeps_the_seeded_region_and_drops_the_others() {
        let (fg, w, h) = mask(&["##...#", "##...#", "......", "...##."]);
        let kept = keep_seeded_regions(&fg, w, h, &[w + 1], None);
        let (want, _, _) = mask(&["##....", "##....", "......", "......"]);
        assert_eq!(kept, want);
    }

    #[test]
    fn diagonal_neighbours_are_separate_regions() {
        let (fg, w, h) = mask(&["#.", ".#"]);
        assert_eq!(keep_seeded_regions(&fg, w, h, &[0], None), vec![true, false, false, false]);
    }

    #[test]
    fn seeds_in_several_regions_keep_each_of_them() {
        let (fg, w, h) = mask(&["#.#", "...", "#.."]);
        let kept = keep_seeded_regions(&fg, w, h, &[0, 2, 4], None);
        assert_eq!(kept, vec![true, false, true, false, false, false, false, false, false]);
    }

    #[test]
    fn a_depth_jump_separates_touching_regions() {
        // One foreground block: the left half near (depth 2), the right half far (depth 5),
        // plus a ramp row whose steps are small enough to stay connected.
        let (fg, w, h) = mask(&["####", "####", "####"]);
        let depth = [2.0, 2.0, 5.0, 5.0, 2.0, 2.0, 5.0, 5.0, 2.0, 2.1, 2.2, 2.3];
        let continuity = DepthContinuity { depth: &depth, max_jump: 0.1 };
        let kept = keep_seeded_regions(&fg, w, h, &[0], Some(continuity));
        let (want, _, _) = mask(&["##..", "##..", "####"]);
        assert_eq!(kept, want);
        // Without the depth test the whole block is one region.
        assert_eq!(keep_seeded_regions(&fg, w, h, &[0], None), fg);
    }

    #[test]
    fn without_a_seed_in_the_foreground_the_mask_is_unchanged() {
        let (fg, w, h) = mask(&["#..", "..#"]);
        assert_eq!(keep_seeded_regions(&fg, w, h, &[1, 99], None), fg);
        assert_eq!(keep_seeded_regions(&fg, w, h, &[], None), fg);
    }
}
