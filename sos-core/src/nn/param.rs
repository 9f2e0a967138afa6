//! A trainable tensor: values plus accumulated gradient.

use serde::{Deserialize, Serialize};

/// A flat trainable parameter and its gradient, of equal length.
///
/// Serialisation stores `value` only; on deserialisation `grad` is rebuilt as zeros.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(from = "ParamRepr")]
pub struct Param {
    /// Current values.
    pub value: Vec<f32>,
    /// Gradient of the loss w.r.t. `value`, accumulated by backward passes until
    /// [`Param::zero_grad`] (or an optimiser step) clears it.
    #[serde(skip_serializing)]
    pub grad: Vec<f32>,
}

/// What is actually stored for a [`Param`].
#[derive(Deserialize)]
struct ParamRepr {
    value: Vec<f32>,
}

impl From<ParamRepr> for Param {
    fn from(r: ParamRepr) -> Self {
        Param::new(r.value)
    }
}

impl Param {
    /// Wraps `value` with a zero gradient of the same length.
    pub fn new(value: Vec<f32>) -> Self {
        let grad = vec![0.0; value.len()];
        Self { value, grad }
    }

    /// Number of scalars.
    pub fn len(&self) -> usize {
        self.value.len()
    }

    /// Whether the parameter holds no scalars.
    pub fn is_empty(&self) -> bool {
        self.value.is_empty()
    }

    /// Sets the gradient to zero (resizing it to `value`'s length if it drifted).
    pub fn zero_grad(&mut self) {
        self.grad.clear();
        self.grad.resize(self.value.len(), 0.0);
    }
}

/// The values of `params`, one after another.
pub fn flat_values<'a>(params: impl IntoIterator<Item = &'a Param>) -> Vec<f32> {
    params.into_iter().flat_map(|p| p.value.iter().copied()).collect()
}

/// The gradients of `params`, laid out as [`flat_values`].
pub fn flat_grads<'a>(params: impl IntoIterator<Item = &'a Param>) -> Vec<f32> {
    params.into_iter().flat_map(|p| p.grad.iter().copied()).collect()
}

/// Overwrites `params` from values laid out as [`flat_values`]; on a length mismatch nothing is
/// written and the expected length is returned.
pub fn assign_flat(params: &mut [&mut Param], values: &[f32]) -> Result<(), usize> {
    let want: usize = params.iter().map(|p| p.len()).sum();
    if values.len() != want {
        return Err(want);
    }
    let mut rest = values;
    for p in params.iter_mut() {
        let (head, tail) = rest.split_at(p.len());
        p.value.copy_from_slice(head);
        rest = tail;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn serde_keeps_value_and_rebuilds_grad() {
        let mut p = Param::new(vec![1.0, -2.5, 3.0]);
        p.grad = vec![9.0, 9.0, 9.0];
        let json = serde_json::to_string(&p).unwrap();
        assert!(!json.contains("grad"), "grad must not be stored: {json}");
        let q: Param = serde_json::from_str(&json).unwrap();
        assert_eq!(q.value, p.value);
        assert_eq!(q.grad, vec![0.0; 3]);
    }

    #[test]
    fn zero_grad_clears() {
        let mut p = Param::new(vec![1.0; 4]);
        p.grad.iter_mut().for_each(|g| *g = 3.0);
        p.zero_grad();
        assert_eq!(p.grad, vec![0.0; 4]);
    }
}
