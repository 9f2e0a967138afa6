//! stub
use serde::{Deserialize, Serialize};
/// x
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct GeometryConfig {}
/// x
pub struct GeometryLoss;
/// x
pub fn clip_depth() {}
