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
//!
//! The object may also be a group of things side by side, of which the voters touch only one.
//! On an orbit rig the object stands well inside the cameras' path and everything else beyond
//! it, so [`keep_nearby_parts`] returns the unseeded regions that come close to the focus and
//! stand in front of their surroundings (their outline steps back in depth along most of its
//! length, as a thing standing on the ground does and a patch of the ground does not).

use std::collections::VecDeque;

use crate::camera::{dot, sub, Vec3};

/// Regions smaller than this many pixels are speckle, never a part of the object.
pub const MIN_PART_PIXELS: usize = 10;

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

    /// Whether pixel `j` lies farther than pixel `i` by more than the largest step.
    fn steps_back(&self, i: usize, j: usize) -> bool {
        self.depth[j] > self.depth[i] * (1.0 + self.max_jump)
    }
}

/// The 4-neighbours of pixel `i` in a row-major `width x height` image.
fn neighbours(i: usize, width: usize, height: usize) -> impl Iterator<Item = usize> {
    let (r, c) = (i / width, i % width);
    [
        (r > 0).then(|| i - width),
        (r + 1 < height).then(|| i + width),
        (c > 0).then(|| i - 1),
        (c + 1 < width).then(|| i + 1),
    ]
    .into_iter()
    .flatten()
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
        for j in neighbours(i, width, height) {
            if foreground[j] && !kept[j] && depth.as_ref().is_none_or(|d| d.joins(i, j)) {
                kept[j] = true;
                queue.push_back(j);
            }
        }
    }
    kept
}

/// Where the other parts of the object may be: within `radius` of the focus `centre`.
#[derive(Debug, Clone, Copy)]
pub struct NearbyParts<'a> {
    /// Rendered 3D point of every pixel, `None` for empty rays.
    pub points: &'a [Option<Vec3>],
    /// The focus point.
    pub centre: Vec3,
    /// Largest distance from the focus at which a region still counts as near.
    pub radius: f32,
    /// Share of a region's outline at which the depth must step back.
    pub min_standing_outline: f32,
}

/// Adds to `kept` (the seeded regions) every other depth-continuous region of `foreground`
/// of at least [`MIN_PART_PIXELS`] pixels that has a point within the radius of the focus and
/// stands in front of its surroundings: at no less than `min_standing_outline` of the
/// region's outline (pixel edges to pixels outside it) the neighbour lies farther by more
/// than the continuity's largest step. Empty rays lie farthest of all.
pub fn keep_nearby_parts(
    foreground: &[bool],
    kept: Vec<bool>,
    width: usize,
    height: usize,
    parts: &NearbyParts,
    depth: DepthContinuity,
) -> Vec<bool> {
    add_regions(foreground, kept, width, height, parts, depth, |region, _, region_of| {
        let (mut outline, mut behind) = (0usize, 0usize);
        for &i in region {
            for j in neighbours(i, width, height).filter(|&j| region_of[j] != region[0]) {
                outline += 1;
                behind += usize::from(depth.steps_back(i, j));
            }
        }
        outline > 0 && behind as f64 >= f64::from(parts.min_standing_outline) * outline as f64
    })
}

/// Adds to `kept` (the mask so far) every depth-continuous region of `others` of at least
/// [`MIN_PART_PIXELS`] pixels that touches the mask and has a point within the radius of the
/// focus: the parts that hold the object up. `others` are the pixels of the other clusters
/// that lie clearly off the view's support planes, so a dark base that clustered with the
/// ground it stands on is a region of its own there, while the ground and the shadows on it
/// are not candidates at all. A base rises from the ground without stepping back from it, so
/// unlike [`keep_nearby_parts`] no standing test applies. A part is no larger than the mask it
/// holds up: where the rendered ground is foggy, patches of it float clear of the fitted plane
/// all around the object, and such a patch joined to the mask would outgrow it.
pub fn keep_attached_parts(
    others: &[bool],
    kept: Vec<bool>,
    width: usize,
    height: usize,
    parts: &NearbyParts,
    depth: DepthContinuity,
) -> Vec<bool> {
    let mask_pixels = kept.iter().filter(|&&k| k).count();
    add_regions(others, kept, width, height, parts, depth, |region, mask, _| {
        region.len() <= mask_pixels && region.iter().any(|&i| neighbours(i, width, height).any(|j| mask[j]))
    })
}

/// Walks the depth-continuous regions of `candidates` outside `kept` and adds to `kept` each
/// region of at least [`MIN_PART_PIXELS`] pixels with a point near the focus that `accept`
/// takes. `accept` sees the region (its first pixel names it in the region map), the mask
/// before any addition, and the region map (`usize::MAX` outside every region).
fn add_regions(
    candidates: &[bool],
    mut kept: Vec<bool>,
    width: usize,
    height: usize,
    parts: &NearbyParts,
    depth: DepthContinuity,
    accept: impl Fn(&[usize], &[bool], &[usize]) -> bool,
) -> Vec<bool> {
    assert_eq!(candidates.len(), width * height, "mask size");
    assert_eq!(kept.len(), candidates.len(), "kept size");
    assert_eq!(parts.points.len(), candidates.len(), "points size");
    let radius2 = parts.radius * parts.radius;
    let near = |i: usize| {
        parts.points[i].is_some_and(|p| {
            let d = sub(p, parts.centre);
            dot(d, d) <= radius2
        })
    };
    let mask = kept.clone();
    let mut visited = kept.clone();
    let mut region_of = vec![usize::MAX; candidates.len()];
    for start in 0..candidates.len() {
        if !candidates[start] || visited[start] {
            continue;
        }
        visited[start] = true;
        region_of[start] = start;
        let mut region = vec![start];
        let mut next = 0;
        while next < region.len() {
            let i = region[next];
            next += 1;
            for j in neighbours(i, width, height) {
                if candidates[j] && !visited[j] && depth.joins(i, j) {
                    visited[j] = true;
                    region_of[j] = start;
                    region.push(j);
                }
            }
        }
        if region.len() >= MIN_PART_PIXELS && region.iter().any(|&i| near(i)) && accept(&region, &mask, &region_of) {
            for &i in &region {
                kept[i] = true;
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

    /// A 10x8 view: a 4x4 foreground block at depth 2 (columns 1-4, rows 1-4) in front of a
    /// far wall (rows 0-2, depth 5) and the ground (rows 3-7, depth 3), and a 4x3 foreground
    /// patch of that ground (columns 6-9, rows 5-7); pixel `i`'s point lies `column` units from
    /// the focus.
    fn scene() -> (Vec<bool>, Vec<f32>, Vec<Option<Vec3>>, usize, usize) {
        let (fg, w, h) = mask(&[
            "..........",
            ".####.....",
            ".####.....",
            ".####.....",
            ".####.....",
            "......####",
            "......####",
            "......####",
        ]);
        let depth: Vec<f32> = (0..w * h)
            .map(|i| match (i / w, i % w) {
                (1..=4, 1..=4) => 2.0,
                (0..=2, _) => 5.0,
                _ => 3.0,
            })
            .collect();
        let points = (0..w * h).map(|i| Some([(i % w) as f32, 0.0, 0.0])).collect();
        (fg, depth, points, w, h)
    }

    fn nearby(points: &[Option<Vec3>], radius: f32) -> NearbyParts<'_> {
        NearbyParts { points, centre: [0.0; 3], radius, min_standing_outline: 0.45 }
    }

    #[test]
    fn a_standing_part_near_the_focus_is_kept_and_a_ground_patch_is_not() {
        let (fg, depth, points, w, h) = scene();
        let continuity = DepthContinuity { depth: &depth, max_jump: 0.1 };
        let none = vec![false; w * h];
        let block: Vec<bool> = (0..w * h).map(|i| fg[i] && i % w <= 4).collect();
        assert_eq!(keep_nearby_parts(&fg, none.clone(), w, h, &nearby(&points, 20.0), continuity), block);
        // Beyond the radius (the block's nearest point is 1 unit away) it is not kept.
        assert_eq!(keep_nearby_parts(&fg, none.clone(), w, h, &nearby(&points, 0.5), continuity), none);
        // Regions already kept stay kept.
        assert_eq!(keep_nearby_parts(&fg, fg.clone(), w, h, &nearby(&points, 0.5), continuity), fg);
    }

    #[test]
    fn a_part_touching_the_mask_joins_it_and_parts_apart_far_or_tiny_do_not() {
        // The mask (o), a 12-pixel base under it (b), a 12-pixel region apart (a), and a
        // 3-pixel speck touching the mask (s); everything at one depth.
        let rows = [
            "............",
            ".oooo...aaa.",
            ".oooo...aaa.",
            ".oooos..aaa.",
            ".bbb.s..aaa.",
            ".bbb.s......",
            ".bbb........",
            ".bbb........",
        ];
        let (w, h) = (rows[0].len(), rows.len());
        let cell = |ch: char| rows.iter().flat_map(|r| r.chars()).map(|c| c == ch).collect::<Vec<bool>>();
        let (mask, base) = (cell('o'), cell('b'));
        let others: Vec<bool> = rows.iter().flat_map(|r| r.chars()).map(|c| "bas".contains(c)).collect();
        let depth = vec![2.0; w * h];
        let continuity = DepthContinuity { depth: &depth, max_jump: 0.05 };
        let points: Vec<Option<Vec3>> = (0..w * h).map(|i| Some([(i % w) as f32, 0.0, 0.0])).collect();
        let with_base: Vec<bool> = mask.iter().zip(&base).map(|(&m, &b)| m || b).collect();
        assert_eq!(keep_attached_parts(&others, mask.clone(), w, h, &nearby(&points, 20.0), continuity), with_base);
        // A region larger than the mask is ground floating off its plane, not a part.
        let small_mask: Vec<bool> = (0..w * h).map(|i| mask[i] && i / w == 3).collect();
        let kept = keep_attached_parts(&others, small_mask.clone(), w, h, &nearby(&points, 20.0), continuity);
        assert_eq!(kept, small_mask, "a 12-pixel base under a 4-pixel mask");
        // Beyond the radius (the base's nearest point is 1 unit from the focus) it stays out.
        assert_eq!(keep_attached_parts(&others, mask.clone(), w, h, &nearby(&points, 0.5), continuity), mask);
        // A depth step across the base splits it: the 6 pixels touching the mask are a speck.
        let mut stepped = depth.clone();
        for i in (6 * w..8 * w).filter(|&i| base[i]) {
            stepped[i] = 4.0;
        }
        let continuity = DepthContinuity { depth: &stepped, max_jump: 0.05 };
        assert_eq!(keep_attached_parts(&others, mask.clone(), w, h, &nearby(&points, 20.0), continuity), mask);
    }

    #[test]
    fn specks_are_not_parts() {
        let (fg, w, h) = mask(&["....", ".##.", "...."]);
        let depth = [5.0, 5.0, 5.0, 5.0, 5.0, 2.0, 2.0, 5.0, 5.0, 5.0, 5.0, 5.0];
        let points = vec![Some([0.0; 3]); w * h];
        let continuity = DepthContinuity { depth: &depth, max_jump: 0.1 };
        let kept = keep_nearby_parts(&fg, vec![false; w * h], w, h, &nearby(&points, 1.0), continuity);
        assert!(kept.iter().all(|&k| !k), "a 2-pixel region standing in front is still a speck");
    }
}
