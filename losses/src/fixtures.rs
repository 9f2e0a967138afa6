//! Loading of the reference fixtures (tests only).

use serde_json::Value;
use sos_core::testing::fixture::{load_fixture, Array};

/// One parsed fixture file.
pub(crate) struct Fixture(Value);

impl Fixture {
    pub(crate) fn appearance() -> Self {
        Fixture(load_fixture(include_str!("../../fixtures/losses/appearance.json")))
    }

    pub(crate) fn geometry() -> Self {
        Fixture(load_fixture(include_str!("../../fixtures/losses/geometry.json")))
    }

    /// A scalar.
    pub(crate) fn scalar(&self, key: &str) -> f64 {
        self.0[key].as_f64().unwrap_or_else(|| panic!("fixture key {key} is not a number"))
    }

    /// An array: (shape, data as f64).
    pub(crate) fn array(&self, key: &str) -> (Vec<usize>, Vec<f64>) {
        let Array { shape, data } = Array::from(&self.0[key]);
        (shape, data)
    }

    /// An array as f32 values.
    pub(crate) fn array_f32(&self, key: &str) -> (Vec<usize>, Vec<f32>) {
        let (s, d) = self.array(key);
        (s, d.into_iter().map(|x| x as f32).collect())
    }

    /// The mined negatives.
    pub(crate) fn neg(&self) -> Vec<usize> {
        self.array("neg").1.into_iter().map(|x| x as usize).collect()
    }

    /// The CLS vectors, one per patch.
    pub(crate) fn cls(&self) -> Vec<Vec<f32>> {
        let (shape, data) = self.array_f32("cls");
        data.chunks(shape[1]).map(<[f32]>::to_vec).collect()
    }
}

/// Asserts `a ≈ b` elementwise: `|a−b| ≤ rtol·max(|b|, floor)`, where `floor` is `rtol`'s
/// reference magnitude for entries near zero (a fraction of the largest |b|).
pub(crate) fn assert_close(what: &str, a: &[f64], b: &[f64], rtol: f64, floor_frac: f64) {
    assert_eq!(a.len(), b.len(), "{what}: lengths differ");
    let scale = b.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let floor = scale * floor_frac;
    let mut worst = (0usize, -1.0f64);
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        let err = (x - y).abs() / y.abs().max(floor).max(f64::MIN_POSITIVE);
        // NaN counts as the worst error.
        if err.is_nan() || err > worst.1 {
            worst = (i, err);
        }
    }
    if a.is_empty() {
        return;
    }
    let (i, err) = worst;
    assert!(err <= rtol && !err.is_nan(), "{what}: entry {i}: {} vs {} (rel err {err:e}, tol {rtol:e})", a[i], b[i]);
}
