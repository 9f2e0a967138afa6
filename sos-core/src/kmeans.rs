//! Seeded k-means with k-means++ initialisation and restarts.
//!
//! Follows scikit-learn's `KMeans` (the version the reference used): greedy k-means++ seeding
//! with `2 + ⌊ln k⌋` local trials, Lloyd iterations that stop when the labels no longer change
//! or when the total squared centre shift is at most `tol × mean per-dimension variance`,
//! relocation of empty clusters to the points farthest from their centres, and `n_init`
//! restarts of which the lowest inertia wins. The assignment step runs on rayon in fixed-size
//! chunks whose partial sums are reduced in order, so results depend only on the seed, never
//! on the thread count.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Points per parallel task; fixed so that floating-point reductions are reproducible.
const CHUNK: usize = 8192;

/// Largest coordinate clustered as it is (2^50); see [`kmeans`].
const HUGE: f32 = 1_125_899_906_842_624.0;

/// Settings of [`kmeans`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct KMeansConfig {
    /// Number of clusters (the reference uses 2).
    pub k: usize,
    /// Number of restarts with different seedings; the lowest inertia wins (sklearn < 1.4: 10).
    pub n_init: usize,
    /// Maximum Lloyd iterations per restart.
    pub max_iter: usize,
    /// Convergence tolerance relative to the data's mean per-dimension variance.
    pub tol: f64,
    /// Seed of the random seeding (`random_state`).
    pub seed: u64,
}

impl Default for KMeansConfig {
    fn default() -> Self {
        KMeansConfig { k: 2, n_init: 10, max_iter: 300, tol: 1e-4, seed: 0 }
    }
}

/// The best clustering found.
#[derive(Debug, Clone, PartialEq)]
pub struct KMeansResult {
    /// Cluster of each point, in `0..k`.
    pub labels: Vec<u32>,
    /// Centres, `[k, dim]` row-major.
    pub centroids: Vec<f32>,
    /// Number of clusters actually formed. Equals the requested `k` unless the data has fewer
    /// than `k` distinct points, in which case it is the number of distinct points (each
    /// distinct point then becomes its own cluster).
    pub k: usize,
    /// Dimension of the points.
    pub dim: usize,
    /// Sum of squared distances of the points to their centres.
    pub inertia: f64,
    /// Lloyd iterations of the winning restart.
    pub n_iter: usize,
}

impl KMeansResult {
    /// Centre of cluster `c`.
    pub fn centroid(&self, c: usize) -> &[f32] {
        &self.centroids[c * self.dim..(c + 1) * self.dim]
    }

    /// Number of points in each cluster.
    pub fn cluster_sizes(&self) -> Vec<usize> {
        let mut sizes = vec![0; self.k];
        for &l in &self.labels {
            sizes[l as usize] += 1;
        }
        sizes
    }
}

/// Invalid input to [`kmeans`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum KMeansError {
    /// The data length is not a multiple of `dim`, or `dim` is zero.
    #[error("k-means: data of length {len} is not a whole number of {dim}-dimensional points")]
    Shape {
        /// Length of the data slice.
        len: usize,
        /// Point dimension given.
        dim: usize,
    },
    /// There are no points to cluster.
    #[error("k-means: no points to cluster")]
    Empty,
    /// A setting is out of range.
    #[error("k-means: `{key}` {reason}")]
    Invalid {
        /// The setting.
        key: &'static str,
        /// What is allowed.
        reason: &'static str,
    },
    /// A coordinate is NaN or infinite.
    #[error("k-means: point {point} has a non-finite coordinate")]
    NonFinite {
        /// Index of the first offending point.
        point: usize,
    },
}

/// Clusters `n` points of dimension `dim`, stored row-major in `data` (`[n, dim]`).
///
/// Deterministic for a given `config.seed`. When the data has fewer than `config.k` distinct
/// points the result has fewer clusters (see [`KMeansResult::k`]) rather than an error.
pub fn kmeans(data: &[f32], dim: usize, config: &KMeansConfig) -> Result<KMeansResult, KMeansError> {
    if dim == 0 || !data.chunks_exact(dim).remainder().is_empty() {
        return Err(KMeansError::Shape { len: data.len(), dim });
    }
    if data.is_empty() {
        return Err(KMeansError::Empty);
    }
    let invalid = |key, reason| Err(KMeansError::Invalid { key, reason });
    if config.k == 0 {
        return invalid("k", "must be at least 1");
    }
    if config.n_init == 0 {
        return invalid("n_init", "must be at least 1");
    }
    if config.max_iter == 0 {
        return invalid("max_iter", "must be at least 1");
    }
    if !(config.tol >= 0.0 && config.tol.is_finite()) {
        return invalid("tol", "must be a finite number >= 0");
    }
    if let Some(i) = data.iter().position(|v| !v.is_finite()) {
        return Err(KMeansError::NonFinite { point: i / dim });
    }
    // Squared distances are f32: beyond ~1e18 they overflow, and every point then ties with
    // every centre. Such data is clustered scaled down by a power of two (exact), then the
    // centres and inertia are scaled back.
    let largest = data.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    if largest > HUGE {
        let scale = 2f32.powi(40 - largest.log2().ceil() as i32);
        let scaled: Vec<f32> = data.iter().map(|v| v * scale).collect();
        let mut r = kmeans(&scaled, dim, config)?;
        r.centroids.iter_mut().for_each(|c| *c /= scale);
        r.inertia /= f64::from(scale) * f64::from(scale);
        return Ok(r);
    }

    let points = Points { data, dim };
    let tol = config.tol * points.mean_variance();
    // One seed per restart, drawn from the master seed (as sklearn draws from random_state).
    let mut master = ChaCha8Rng::seed_from_u64(config.seed);
    let mut best: Option<KMeansResult> = None;
    for _ in 0..config.n_init {
        let mut rng = ChaCha8Rng::seed_from_u64(master.gen());
        let centers = kmeans_plus_plus(&points, config.k, &mut rng);
        let run = lloyd(&points, centers, config.max_iter, tol);
        if !matches!(&best, Some(b) if b.inertia <= run.inertia) {
            best = Some(run);
        }
    }
    Ok(best.expect("n_init >= 1"))
}

/// Row-major points.
#[derive(Clone, Copy)]
struct Points<'a> {
    data: &'a [f32],
    dim: usize,
}

impl<'a> Points<'a> {
    fn len(&self) -> usize {
        self.data.len() / self.dim
    }

    fn point(&self, i: usize) -> &'a [f32] {
        &self.data[i * self.dim..(i + 1) * self.dim]
    }

    /// Mean over dimensions of the per-dimension variance (sklearn's `np.mean(np.var(X, 0))`).
    fn mean_variance(&self) -> f64 {
        let (n, dim) = (self.len(), self.dim);
        let sums = self.chunked_sum(dim, |p, acc| {
            for (a, &v) in acc.iter_mut().zip(p) {
                *a += v as f64;
            }
        });
        let mean: Vec<f64> = sums.iter().map(|s| s / n as f64).collect();
        let sq = self.chunked_sum(dim, |p, acc| {
            for ((a, &v), m) in acc.iter_mut().zip(p).zip(&mean) {
                let d = v as f64 - m;
                *a += d * d;
            }
        });
        sq.iter().sum::<f64>() / (n * dim) as f64
    }

    /// Sums a per-point contribution into `width` accumulators, in parallel chunks reduced
    /// in order.
    fn chunked_sum(&self, width: usize, f: impl Fn(&[f32], &mut [f64]) + Sync) -> Vec<f64> {
        let partials: Vec<Vec<f64>> = self
            .data
            .par_chunks(CHUNK * self.dim)
            .map(|chunk| {
                let mut acc = vec![0.0; width];
                for p in chunk.chunks_exact(self.dim) {
                    f(p, &mut acc);
                }
                acc
            })
            .collect();
        let mut total = vec![0.0; width];
        for p in partials {
            for (t, v) in total.iter_mut().zip(p) {
                *t += v;
            }
        }
        total
    }
}

#[inline]
fn sq_dist(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// Index and squared distance of the centre nearest to `p` (ties: lowest index).
#[inline]
fn nearest(p: &[f32], centers: &[f32], dim: usize) -> (usize, f32) {
    let mut best = (0, f32::INFINITY);
    for (c, center) in centers.chunks_exact(dim).enumerate() {
        let d = sq_dist(p, center);
        if d < best.1 {
            best = (c, d);
        }
    }
    best
}

/// Greedy k-means++ seeding (sklearn's `_kmeans_plusplus`). Stops early, returning fewer
/// centres, when every point already coincides with a chosen centre.
fn kmeans_plus_plus(points: &Points, k: usize, rng: &mut ChaCha8Rng) -> Vec<f32> {
    let (n, dim) = (points.len(), points.dim);
    let trials = 2 + (k as f64).ln() as usize;
    let first = rng.gen_range(0..n);
    let mut centers = points.point(first).to_vec();
    let mut closest: Vec<f64> = vec![0.0; n];
    closest.par_chunks_mut(CHUNK).enumerate().for_each(|(ci, out)| {
        for (j, o) in out.iter_mut().enumerate() {
            *o = sq_dist(points.point(ci * CHUNK + j), points.point(first)) as f64;
        }
    });
    let mut chunk_pots = chunk_sums(&closest);
    for _ in 1..k {
        let pot: f64 = chunk_pots.iter().sum();
        if pot <= 0.0 {
            break; // fewer distinct points than k
        }
        // Candidates drawn with probability proportional to the squared distance; keep the
        // one that lowers the potential most.
        let mut best: Option<(usize, f64)> = None;
        for _ in 0..trials {
            let r = rng.gen::<f64>() * pot;
            let cand = sample_index(&closest, &chunk_pots, r);
            let c = points.point(cand);
            let cand_pot: f64 = closest
                .par_chunks(CHUNK)
                .enumerate()
                .map(|(ci, d)| {
                    d.iter()
                        .enumerate()
                        .map(|(j, &dj)| dj.min(sq_dist(points.point(ci * CHUNK + j), c) as f64))
                        .sum::<f64>()
                })
                .collect::<Vec<f64>>()
                .iter()
                .sum();
            if !matches!(best, Some((_, p)) if p <= cand_pot) {
                best = Some((cand, cand_pot));
            }
        }
        let (chosen, _) = best.expect("at least two trials");
        let c = points.point(chosen);
        closest.par_chunks_mut(CHUNK).enumerate().for_each(|(ci, d)| {
            for (j, dj) in d.iter_mut().enumerate() {
                *dj = dj.min(sq_dist(points.point(ci * CHUNK + j), c) as f64);
            }
        });
        chunk_pots = chunk_sums(&closest);
        centers.extend_from_slice(c);
    }
    debug_assert_eq!(centers.len() % dim, 0);
    centers
}

fn chunk_sums(values: &[f64]) -> Vec<f64> {
    values.par_chunks(CHUNK).map(|c| c.iter().sum()).collect()
}

/// First index whose running sum of `weights` exceeds `r` (so its weight is positive);
/// falls back to the last positive weight when rounding leaves `r` just out of reach.
fn sample_index(weights: &[f64], chunk_sums: &[f64], r: f64) -> usize {
    let mut acc = 0.0;
    for (ci, &s) in chunk_sums.iter().enumerate() {
        if acc + s > r {
            let start = ci * CHUNK;
            let chunk = &weights[start..(start + CHUNK).min(weights.len())];
            let mut a = acc;
            for (j, &w) in chunk.iter().enumerate() {
                a += w;
                if a > r && w > 0.0 {
                    return start + j;
                }
            }
            break;
        }
        acc += s;
    }
    weights.iter().rposition(|&w| w > 0.0).expect("positive total weight")
}

/// Per-chunk statistics of an assignment pass.
struct Partial {
    sums: Vec<f64>,
    counts: Vec<u64>,
    inertia: f64,
    changed: usize,
}

/// Assigns every point to its nearest centre, updating `labels` in place, and returns the
/// per-cluster coordinate sums and counts, the inertia and the number of changed labels.
fn assign(points: &Points, centers: &[f32], labels: &mut [u32]) -> Partial {
    let (dim, k) = (points.dim, centers.len() / points.dim);
    let partials: Vec<Partial> = points
        .data
        .par_chunks(CHUNK * dim)
        .zip(labels.par_chunks_mut(CHUNK))
        .map(|(chunk, labels)| {
            let mut part = Partial { sums: vec![0.0; k * dim], counts: vec![0; k], inertia: 0.0, changed: 0 };
            for (p, label) in chunk.chunks_exact(dim).zip(labels.iter_mut()) {
                let (c, d) = nearest(p, centers, dim);
                if *label != c as u32 {
                    part.changed += 1;
                    *label = c as u32;
                }
                part.counts[c] += 1;
                part.inertia += d as f64;
                for (s, &v) in part.sums[c * dim..(c + 1) * dim].iter_mut().zip(p) {
                    *s += v as f64;
                }
            }
            part
        })
        .collect();
    let mut total = Partial { sums: vec![0.0; k * dim], counts: vec![0; k], inertia: 0.0, changed: 0 };
    for p in partials {
        total.sums.iter_mut().zip(&p.sums).for_each(|(t, v)| *t += v);
        total.counts.iter_mut().zip(&p.counts).for_each(|(t, v)| *t += v);
        total.inertia += p.inertia;
        total.changed += p.changed;
    }
    total
}

/// Lloyd iterations from the given centres (sklearn's `_kmeans_single_lloyd`).
fn lloyd(points: &Points, mut centers: Vec<f32>, max_iter: usize, tol: f64) -> KMeansResult {
    let (n, dim) = (points.len(), points.dim);
    let k = centers.len() / dim;
    // u32::MAX is never a valid label, so the first pass counts every label as changed.
    let mut labels = vec![u32::MAX; n];
    let mut n_iter = 0;
    for it in 0..max_iter {
        n_iter = it + 1;
        let mut stats = assign(points, &centers, &mut labels);
        if stats.changed == 0 {
            break; // strict convergence: the centres are already the means of these labels
        }
        relocate_empty_clusters(points, &centers, &labels, &mut stats);
        let mut shift = 0.0f64;
        for c in 0..k {
            if stats.counts[c] == 0 {
                continue; // relocation failed (all points coincide with centres): keep it
            }
            for j in 0..dim {
                let new = (stats.sums[c * dim + j] / stats.counts[c] as f64) as f32;
                let d = (new - centers[c * dim + j]) as f64;
                shift += d * d;
                centers[c * dim + j] = new;
            }
        }
        if shift <= tol {
            break;
        }
    }
    // Final E-step so that the labels and inertia match the returned centres.
    let stats = assign(points, &centers, &mut labels);
    KMeansResult { labels, centroids: centers, k, dim, inertia: stats.inertia, n_iter }
}

/// Gives each empty cluster one of the points farthest from their current centre (sklearn's
/// `_relocate_empty_clusters_dense`), by editing the sums and counts of the assignment.
fn relocate_empty_clusters(points: &Points, centers: &[f32], labels: &[u32], stats: &mut Partial) {
    let dim = points.dim;
    let empty: Vec<usize> = (0..stats.counts.len()).filter(|&c| stats.counts[c] == 0).collect();
    if empty.is_empty() {
        return;
    }
    let mut far: Vec<(f32, usize)> = (0..points.len())
        .into_par_iter()
        .map(|i| {
            let c = labels[i] as usize;
            (sq_dist(points.point(i), &centers[c * dim..(c + 1) * dim]), i)
        })
        .collect();
    // Farthest first; index breaks ties so the choice is reproducible.
    far.par_sort_unstable_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    for (&new, &(d, i)) in empty.iter().zip(&far) {
        if d <= 0.0 {
            break;
        }
        let old = labels[i] as usize;
        let p = points.point(i);
        for (j, &v) in p.iter().enumerate() {
            stats.sums[old * dim + j] -= v as f64;
            stats.sums[new * dim + j] = v as f64;
        }
        stats.counts[old] -= 1;
        stats.counts[new] = 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    /// `per` points around each centre, with uniform noise of half-width `spread`.
    fn blobs(centres: &[[f32; 2]], per: usize, spread: f32, seed: u64) -> (Vec<f32>, Vec<u32>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut data = Vec::new();
        let mut truth = Vec::new();
        for i in 0..per * centres.len() {
            let c = i % centres.len();
            data.push(centres[c][0] + rng.gen_range(-spread..spread));
            data.push(centres[c][1] + rng.gen_range(-spread..spread));
            truth.push(c as u32);
        }
        (data, truth)
    }

    #[test]
    fn recovers_well_separated_blobs() {
        let centres = [[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0], [5.0, 20.0]];
        let (data, truth) = blobs(&centres, 2000, 1.0, 1);
        let cfg = KMeansConfig { k: 5, ..Default::default() };
        let r = kmeans(&data, 2, &cfg).unwrap();
        assert_eq!(r.k, 5);
        assert_eq!(r.cluster_sizes(), vec![2000; 5]);
        // Same partition up to renaming.
        let ari = crate::metrics::adjusted_rand_index(&truth, &r.labels).unwrap();
        assert_eq!(ari, 1.0);
        for c in &centres {
            let near = (0..5).any(|j| sq_dist(r.centroid(j), c) < 0.01);
            assert!(near, "no centroid near {c:?}: {:?}", r.centroids);
        }
        // Inertia equals the sum of squared distances to the returned centroids.
        let direct: f64 =
            data.chunks_exact(2).zip(&r.labels).map(|(p, &l)| sq_dist(p, r.centroid(l as usize)) as f64).sum();
        assert!((direct - r.inertia).abs() < 1e-6 * direct, "{direct} vs {}", r.inertia);
        // Uniform noise of half-width 1 in 2D: expected squared distance 2/3 per point.
        assert!((r.inertia / 10_000.0 - 2.0 / 3.0).abs() < 0.03, "{}", r.inertia);
    }

    #[test]
    fn higher_dimensional_data_and_restarts_pick_lowest_inertia() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let dim = 16;
        let k = 8;
        let means: Vec<Vec<f32>> = (0..k).map(|_| (0..dim).map(|_| rng.gen_range(-20.0..20.0)).collect()).collect();
        let mut data = Vec::new();
        for i in 0..4000 {
            data.extend(means[i % k].iter().map(|m| m + rng.gen_range(-1.0f32..1.0)));
        }
        let one = kmeans(&data, dim, &KMeansConfig { k, n_init: 1, ..Default::default() });
        let ten = kmeans(&data, dim, &KMeansConfig { k, ..Default::default() }).unwrap();
        assert!(ten.inertia <= one.unwrap().inertia);
        assert_eq!(ten.cluster_sizes(), vec![500; 8]);
    }

    #[test]
    fn deterministic_given_seed() {
        let (data, _) = blobs(&[[0.0, 0.0], [3.0, 0.0], [1.5, 2.0]], 20_000, 2.0, 3);
        let cfg = KMeansConfig { k: 3, seed: 42, ..Default::default() };
        let a = kmeans(&data, 2, &cfg).unwrap();
        let b = kmeans(&data, 2, &cfg).unwrap();
        assert_eq!(a, b);
        // Same result on a single thread (chunked reductions do not depend on the threads).
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        let c = pool.install(|| kmeans(&data, 2, &cfg).unwrap());
        assert_eq!(a, c);
    }

    #[test]
    fn fewer_distinct_points_than_k_gives_fewer_clusters() {
        // Three distinct points, repeated.
        let data: Vec<f32> =
            [[0.0f32, 0.0], [1.0, 1.0], [5.0, 5.0]].iter().cycle().take(30).flatten().copied().collect();
        let r = kmeans(&data, 2, &KMeansConfig { k: 5, ..Default::default() }).unwrap();
        assert_eq!(r.k, 3);
        assert_eq!(r.centroids.len(), 6);
        assert_eq!(r.inertia, 0.0);
        assert_eq!(r.cluster_sizes(), vec![10; 3]);
        // k larger than the number of points, and a constant data set.
        let r = kmeans(&[1.0, 2.0], 1, &KMeansConfig { k: 4, ..Default::default() }).unwrap();
        assert_eq!((r.k, r.inertia), (2, 0.0));
        let r = kmeans(&[0.5; 40], 4, &KMeansConfig::default()).unwrap();
        assert_eq!((r.k, r.labels.as_slice()), (1, &[0u32; 10][..]));
    }

    #[test]
    fn invalid_input_is_an_error() {
        let cfg = KMeansConfig::default();
        assert!(matches!(kmeans(&[1.0, 2.0, 3.0], 2, &cfg), Err(KMeansError::Shape { .. })));
        assert!(matches!(kmeans(&[1.0], 0, &cfg), Err(KMeansError::Shape { .. })));
        assert_eq!(kmeans(&[], 2, &cfg), Err(KMeansError::Empty));
        assert_eq!(kmeans(&[0.0, 1.0, f32::NAN, 0.0], 2, &cfg), Err(KMeansError::NonFinite { point: 1 }));
        for bad in [
            KMeansConfig { k: 0, ..cfg.clone() },
            KMeansConfig { n_init: 0, ..cfg.clone() },
            KMeansConfig { max_iter: 0, ..cfg.clone() },
            KMeansConfig { tol: -1.0, ..cfg.clone() },
            KMeansConfig { tol: f64::NAN, ..cfg.clone() },
        ] {
            assert!(matches!(kmeans(&[0.0, 1.0], 1, &bad), Err(KMeansError::Invalid { .. })));
        }
        let toml_err = toml::from_str::<KMeansConfig>("k = 2\nn_inits = 3").unwrap_err();
        assert!(toml_err.to_string().contains("n_inits"), "{toml_err}");
    }

    #[test]
    fn empty_cluster_is_relocated() {
        // Centres seeded far from the data: cluster 1 starts empty and must be relocated.
        let (data, truth) = blobs(&[[0.0, 0.0], [8.0, 8.0]], 500, 0.5, 5);
        let points = Points { data: &data, dim: 2 };
        let r = lloyd(&points, vec![4.0, 4.0, 100.0, 100.0], 300, 0.0);
        assert_eq!(r.cluster_sizes(), vec![500, 500]);
        assert_eq!(crate::metrics::adjusted_rand_index(&truth, &r.labels).unwrap(), 1.0);
    }

    /// Timing on the reference's problem size (1008x756 views, 2-d logits, k = 2, n_init 10);
    /// prints the time so `cargo test -- --nocapture` shows it; fails only if absurdly slow.
    #[test]
    fn separates_overlapping_blobs_at_full_view_size() {
        let n = 1008 * 756;
        let (data, truth) = blobs(&[[-1.0, 1.0], [1.5, -0.5]], n / 2, 1.2, 9);
        let r = kmeans(&data, 2, &KMeansConfig::default()).unwrap();
        let ari = crate::metrics::adjusted_rand_index(&truth, &r.labels).unwrap();
        assert!(ari > 0.5, "{ari}");
    }
}
