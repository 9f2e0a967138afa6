//! Loading of the reference fixtures (tests only).

use serde_json::Value;

/// One parsed fixture file.
pub(crate) struct Fixture(Value);

impl Fixture {
    pub(crate) fn appearance() -> Self {
        Fixture(
            serde_json::from_str(include_str!("../../fixtures/losses/appearance.json"))
                .expect("appearance fixture parses"),
        )
    }

    pub(crate) fn geometry() -> Self {
        Fixture(
            serde_json::from_str(include_str!("../../fixtures/losses/geometry.json")).expect("geometry fixture parses"),
        )
    }

    /// A scalar.
    pub(crate) fn scalar(&self, key: &str) -> f64 {
        self.0[key].as_f64().unwrap_or_else(|| panic!("fixture key {key} is not a number"))
    }

    /// An array: (shape, data as f64).
    pub(crate) fn array(&self, key: &str) -> (Vec<usize>, Vec<f64>) {
        let v = &self.0[key];
        let shape = v["shape"]
            .as_array()
            .unwrap_or_else(|| panic!("fixture key {key} has no shape"))
            .iter()
            .map(|x| x.as_u64().expect("shape entry") as usize)
            .collect::<Vec<_>>();
        let data = v["data"]
            .as_array()
            .unwrap_or_else(|| panic!("fixture key {key} has no data"))
            .iter()
            .map(|x| x.as_f64().expect("data entry"))
            .collect::<Vec<_>>();
        assert_eq!(shape.iter().product::<usize>(), data.len(), "fixture key {key}");
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
