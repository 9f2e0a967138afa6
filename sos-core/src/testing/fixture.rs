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
