//! Reference fixtures are JSON files whose arrays are `{"shape": [...], "data": [...]}`; the
//! crates' tests read them here.

/// A row-major array from a fixture file.
#[derive(Debug, Clone, PartialEq)]
pub struct Array {
    /// Dimensions.
    pub shape: Vec<usize>,
    /// Values, row-major.
    pub data: Vec<f64>,
}

impl From<&serde_json::Value> for Array {
    fn from(v: &serde_json::Value) -> Self {
        let shape = v["shape"]
            .as_array()
            .expect("fixture array has a shape")
            .iter()
            .map(|d| d.as_u64().expect("shape entries are integers") as usize)
            .collect::<Vec<_>>();
        let data = v["data"]
            .as_array()
            .expect("fixture array has data")
            .iter()
            .map(|x| x.as_f64().expect("data entries are numbers"))
            .collect::<Vec<_>>();
        let numel: usize = shape.iter().product();
        assert_eq!(numel, data.len(), "fixture array of shape {shape:?} holds {} values", data.len());
        Array { shape, data }
    }
}

/// Parses a fixture file's text.
pub fn load_fixture(text: &str) -> serde_json::Value {
    serde_json::from_str(text).expect("fixture is valid JSON")
}

/// Unit round-off of `f32` arithmetic, `u = 2⁻²⁴`.
pub const F32_UNIT_ROUNDOFF: f64 = 1.0 / (1u64 << 24) as f64;

/// `γ_n = n·u / (1 − n·u)`: the largest relative error of a sum of `n` terms accumulated in
/// `f32`, relative to the sum of the terms' magnitudes (Higham, *Accuracy and Stability of
/// Numerical Algorithms*, §3.1), whatever the order of accumulation.
pub fn f32_gamma(n: usize) -> f64 {
    let nu = n as f64 * F32_UNIT_ROUNDOFF;
    nu / (1.0 - nu)
}

/// The largest difference two `f32` evaluations of the same gradient entry may show, each a
/// sum of `accumulation` terms in its own order: `2·γ_n·|want|` for terms that do not cancel,
/// plus a floor for entries that are small because their terms cancel, `2·√n·u·largest`
/// (round-off of terms as large as the largest entry `largest`, accumulating as a random walk).
pub fn f32_gradient_tolerance(want: f64, largest: f64, accumulation: usize) -> f64 {
    let n = accumulation.max(1);
    2.0 * f32_gamma(n) * want.abs() + 2.0 * (n as f64).sqrt() * F32_UNIT_ROUNDOFF * largest.abs()
}

/// Asserts every entry of `got` against `want` within [`f32_gradient_tolerance`] for sums of
/// `accumulation` terms; names `what` and the worst entry.
pub fn assert_f32_gradients(what: &str, got: &[f64], want: &[f64], accumulation: usize) {
    assert_eq!(got.len(), want.len(), "{what}: lengths differ");
    let largest = want.iter().fold(0.0f64, |m, w| m.max(w.abs()));
    let mut worst: Option<(usize, f64)> = None;
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        let ratio = (g - w).abs() / f32_gradient_tolerance(*w, largest, accumulation).max(f64::MIN_POSITIVE);
        if ratio.is_nan() || worst.is_none_or(|(_, r)| ratio > r) {
            worst = Some((i, ratio));
        }
    }
    if let Some((i, ratio)) = worst {
        assert!(
            ratio <= 1.0,
            "{what}: entry {i}: {} vs {} beyond the f32 round-off bound for {accumulation} terms ({ratio:.2}x it)",
            got[i],
            want[i]
        );
    }
}
