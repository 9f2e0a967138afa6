//! Mask cleanup after clustering (`masks.keep = "connected"`): keep only the foreground
//! regions that contain the object.
//!
//! k-means labels pixels by their logits alone, so a patch of background whose logits happen
//! to resemble the object's (a noisy, poorly reconstructed far wall, say) joins the foreground
//! cluster although it lies elsewhere in the image. The `focus` rule already knows which pixels
//! show the object: the ones whose rendered 3D points lie nearest the focus point. This keeps
//! the 4-connected foreground regions that contain at least one of those pixels and returns
//! every other foreground region to the background.

use std::collections::VecDeque;

/// Keeps the 4-connected regions of `foreground` (row-major `width x height`) that contain at
/// least one pixel of `seeds`; seeds outside the foreground are ignored. With no seed in the
/// foreground, the mask is returned unchanged (there is nothing to anchor the cleanup on).
pub fn keep_seeded_regions(foreground: &[bool], width: usize, height: usize, seeds: &[usize]) -> Vec<bool> {
    assert_eq!(foreground.len(), width * height, "mask size");
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
            if foreground[j] && !kept[j] {
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
        let kept = keep_seeded_regions(&fg, w, h, &[w + 1]);
        let (want, _, _) = mask(&["##....", "##....", "......", "......"]);
        assert_eq!(kept, want);
    }

    #[test]
    fn diagonal_neighbours_are_separate_regions() {
        let (fg, w, h) = mask(&["#.", ".#"]);
        assert_eq!(keep_seeded_regions(&fg, w, h, &[0]), vec![true, false, false, false]);
    }

    #[test]
    fn seeds_in_several_regions_keep_each_of_them() {
        let (fg, w, h) = mask(&["#.#", "...", "#.."]);
        let kept = keep_seeded_regions(&fg, w, h, &[0, 2, 4]);
        assert_eq!(kept, vec![true, false, true, false, false, false, false, false, false]);
    }

    #[test]
    fn without_a_seed_in_the_foreground_the_mask_is_unchanged() {
        let (fg, w, h) = mask(&["#..", "..#"]);
        assert_eq!(keep_seeded_regions(&fg, w, h, &[1, 99]), fg);
        assert_eq!(keep_seeded_regions(&fg, w, h, &[]), fg);
    }
}
