//! Adjusted Rand index, as sklearn's `adjusted_rand_score`.

use std::collections::HashMap;
use std::hash::Hash;

use super::MetricError;

/// Adjusted Rand index between two labelings of the same elements (sklearn's
/// `adjusted_rand_score`, including its special case: when the two labelings put every pair
/// of elements on the same side — identical partitions up to renaming, which covers a single
/// element, one cluster in both, or every element its own cluster in both — the result is
/// exactly `1.0`).
///
/// The result is invariant to renaming labels (so a foreground/background flip does not
/// change it). It lies in `[-0.5, 1]`; `0` is the expected value for random labelings.
/// Pair counts use exact 128-bit integer arithmetic, as Python does, so large images
/// (millions of pixels) do not overflow. Empty input gives `1.0` (as sklearn).
pub fn adjusted_rand_index<A, B>(truth: &[A], pred: &[B]) -> Result<f64, MetricError>
where
    A: Eq + Hash + Copy,
    B: Eq + Hash + Copy,
{
    if truth.len() != pred.len() {
        return Err(MetricError::SizeMismatch {
            what: "adjusted Rand index: true and predicted labels",
            left: truth.len(),
            right: pred.len(),
        });
    }
    let (t_ids, n_t) = dense_ids(truth);
    let (p_ids, n_p) = dense_ids(pred);

    // Contingency table: dense when small (the usual 2x2 case), sparse otherwise.
    let mut row = vec![0i128; n_t];
    let mut col = vec![0i128; n_p];
    let mut sum_sq: i128 = 0;
    if n_t.saturating_mul(n_p) <= 1 << 22 {
        let mut table = vec![0u64; n_t * n_p];
        for (&t, &p) in t_ids.iter().zip(&p_ids) {
            table[t as usize * n_p + p as usize] += 1;
        }
        for (i, &c) in table.iter().enumerate() {
            let c = c as i128;
            row[i / n_p] += c;
            col[i % n_p] += c;
            sum_sq += c * c;
        }
    } else {
        let mut table: HashMap<(u32, u32), u64> = HashMap::new();
        for (&t, &p) in t_ids.iter().zip(&p_ids) {
            *table.entry((t, p)).or_default() += 1;
        }
        for (&(t, p), &c) in &table {
            let c = c as i128;
            row[t as usize] += c;
            col[p as usize] += c;
            sum_sq += c * c;
        }
    }

    // sklearn's pair_confusion_matrix (ordered pairs, hence the factor 2 below).
    let n = truth.len() as i128;
    let tp = sum_sq - n;
    let fp = row.iter().map(|r| r * r).sum::<i128>() - sum_sq;
    let fn_ = col.iter().map(|c| c * c).sum::<i128>() - sum_sq;
    let tn = n * n - fp - fn_ - sum_sq;
    if fn_ == 0 && fp == 0 {
        return Ok(1.0);
    }
    let num = tp * tn - fn_ * fp;
    let den = (tp + fn_) * (fn_ + tn) + (tp + fp) * (fp + tn);
    Ok(2.0 * num as f64 / den as f64)
}

/// Maps labels to `0..count` in order of first appearance.
fn dense_ids<T: Eq + Hash + Copy>(labels: &[T]) -> (Vec<u32>, usize) {
    let mut map: HashMap<T, u32> = HashMap::new();
    let mut last: Option<(T, u32)> = None;
    let ids = labels
        .iter()
        .map(|&l| {
            // Label maps come in long runs; skip the hash lookup for repeats.
            if let Some((pl, pid)) = last {
                if pl == l {
                    return pid;
                }
            }
            let next = map.len() as u32;
            let id = *map.entry(l).or_insert(next);
            last = Some((l, id));
            id
        })
        .collect();
    (ids, map.len())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::fixture;

    #[test]
    fn reproduces_reference_fixture() {
        let fx = fixture::load();
        for (i, case) in fx.masks.iter().enumerate() {
            let ari = adjusted_rand_index(&case.gt.labels(), &case.pred.labels()).unwrap();
            assert!((ari - case.ari).abs() < 1e-12, "case {i}: {ari} vs {}", case.ari);
        }
    }

    #[test]
    fn matches_sklearn_documented_examples() {
        // Values from sklearn's adjusted_rand_score docstring.
        let ari = |a: &[i32], b: &[i32]| adjusted_rand_index(a, b).unwrap();
        assert_eq!(ari(&[0, 0, 1, 1], &[0, 0, 1, 1]), 1.0);
        assert_eq!(ari(&[0, 0, 1, 1], &[1, 1, 0, 0]), 1.0);
        assert!((ari(&[0, 0, 1, 2], &[0, 0, 1, 1]) - 0.571_428_571_428_571_4).abs() < 1e-12);
        assert!((ari(&[0, 0, 1, 1], &[0, 0, 1, 2]) - 0.571_428_571_428_571_4).abs() < 1e-12);
        assert_eq!(ari(&[0, 0, 0, 0], &[0, 1, 2, 3]), 0.0);
        assert!((ari(&[0, 0, 1, 1], &[0, 1, 0, 1]) - -0.5).abs() < 1e-12);
    }

    #[test]
    fn special_cases() {
        let empty: [u8; 0] = [];
        assert_eq!(adjusted_rand_index(&empty, &empty).unwrap(), 1.0);
        assert_eq!(adjusted_rand_index(&[7], &[3]).unwrap(), 1.0);
        assert_eq!(adjusted_rand_index(&[1, 1, 1], &[2, 2, 2]).unwrap(), 1.0);
        assert_eq!(adjusted_rand_index(&[1, 2, 3], &[6, 5, 4]).unwrap(), 1.0);
        let err = adjusted_rand_index(&[1, 2], &[1]).unwrap_err();
        assert!(matches!(err, MetricError::SizeMismatch { left: 2, right: 1, .. }));
    }

    #[test]
    fn large_input_does_not_overflow_and_uses_sparse_table() {
        // 1008x756 image, two halves, prediction off by a few rows: close to but below 1.
        let n = 1008 * 756;
        let truth: Vec<u8> = (0..n).map(|i| (i >= n / 2) as u8).collect();
        let pred: Vec<u8> = (0..n).map(|i| (i >= n / 2 + 3024) as u8).collect();
        let ari = adjusted_rand_index(&truth, &pred).unwrap();
        assert!(ari > 0.97 && ari < 1.0, "{ari}");
        // Many distinct labels on both sides (sparse contingency path).
        let a: Vec<u32> = (0..20000u32).map(|i| i / 4).collect();
        let b: Vec<u32> = (0..20000u32).map(|i| i / 2).collect();
        let ari = adjusted_rand_index(&a, &b).unwrap();
        assert!(ari > 0.0 && ari < 1.0, "{ari}");
    }
}
