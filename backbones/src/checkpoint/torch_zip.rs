//! PyTorch's zip checkpoint (`torch.save` since 1.6): a zip whose `<prefix>/data.pkl` pickles
//! the saved object, with each tensor storage in its own entry `<prefix>/data/<key>`.

use std::collections::BTreeMap;

use super::torch_pickle::{read_state_dict, StorageRef};
use super::{pickle, zip, TensorEntry};

/// Tensor name → where its values are, for a PyTorch zip checkpoint.
pub fn read_entries(bytes: &[u8]) -> Result<BTreeMap<String, TensorEntry>, String> {
    let files = zip::read_entries(bytes)?;
    let pkl_name = files
        .keys()
        .filter(|n| n.ends_with("data.pkl"))
        .min_by_key(|n| n.len())
        .ok_or("zip file without a `data.pkl` entry: not a PyTorch checkpoint")?
        .clone();
    let prefix = &pkl_name[..pkl_name.len() - "data.pkl".len()];
    if let Some(order) = files.get(&format!("{prefix}byteorder")) {
        if &bytes[order.clone()] != b"little" {
            return Err("the checkpoint was saved on a big-endian machine; save it again on a little-endian one".into());
        }
    }
    let root = pickle::load(&bytes[files[&pkl_name].clone()]).map_err(|e| format!("{pkl_name}: {e}"))?;
    read_state_dict(&root, &|s: &StorageRef| {
        files
            .get(&format!("{prefix}data/{}", s.key))
            .cloned()
            .ok_or_else(|| format!("storage `data/{}` is missing from the zip (truncated file?)", s.key))
    })
}
