//! Stage-2 checkpointing: the trained head is saved as a `head` section next to the field in
//! the run's checkpoint (with a small `head-meta` section recording the stage-2 steps), and
//! loaded back for mask inference without retraining.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::RunError;
use crate::segment::head::SegHead;
use crate::train::session::Session;

/// Checkpoint section holding [`SegHead::to_bytes`].
pub const HEAD_SECTION: &str = "head";
/// Checkpoint section holding [`HeadMeta`] as JSON.
pub const HEAD_META_SECTION: &str = "head-meta";

/// What to do about a saved head that cannot be used.
const TRAIN_A_NEW_HEAD: &str = "run `sos segment` (without --masks-only) to train a new one";

/// What is recorded about a saved head besides its parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct HeadMeta {
    /// Stage-2 steps the head was trained for.
    pub steps: usize,
}

/// Writes the run's checkpoint with the field and the trained head.
pub fn save_with_head(session: &Session, head: &SegHead, meta: HeadMeta) -> Result<(), RunError> {
    let bytes = head.to_bytes();
    let meta_bytes = serde_json::to_vec(&meta).expect("head meta serialises");
    session.save_checkpoint_with(&[(HEAD_SECTION, &bytes), (HEAD_META_SECTION, &meta_bytes)])
}

/// A head restored from a checkpoint.
#[derive(Debug, Clone)]
pub struct LoadedHead {
    /// The head.
    pub head: SegHead,
    /// Its record (`steps = 0` if the checkpoint has none).
    pub meta: HeadMeta,
}

/// Restores the field from `path` (the run's own checkpoint when `None`) and returns the head
/// saved with it, if any. A head that does not fit the field or the `[head]` config is an
/// error naming the checkpoint.
pub fn load_with_head(session: &mut Session, path: Option<&Path>) -> Result<(Option<LoadedHead>, PathBuf), RunError> {
    let (ckpt, path) = session.load_checkpoint_sections(path)?;
    let Some(bytes) = ckpt.section(HEAD_SECTION) else {
        return Ok((None, path));
    };
    let fail = |message: String| RunError::Checkpoint { path: path.clone(), message };
    let head = SegHead::from_bytes(bytes).map_err(|e| fail(format!("{e}; {TRAIN_A_NEW_HEAD}")))?;
    let non_finite =
        head.mlp.layers.iter().flat_map(|l| l.weight.value.iter().chain(&l.bias.value)).any(|v| !v.is_finite());
    if non_finite {
        return Err(fail(format!("its `{HEAD_SECTION}` section holds a non-finite parameter; {TRAIN_A_NEW_HEAD}")));
    }
    let want_in = session.field.seg_input_dim();
    let want_out = session.config.head.outputs;
    if head.mlp.in_dim() != want_in || head.outputs() != want_out {
        return Err(fail(format!(
            "its segmentation head maps {} inputs to {} logits but the config asks for {} to {}; \
             {TRAIN_A_NEW_HEAD}",
            head.mlp.in_dim(),
            head.outputs(),
            want_in,
            want_out
        )));
    }
    let meta = match ckpt.section(HEAD_META_SECTION) {
        Some(b) => serde_json::from_slice(b).map_err(|e| fail(format!("bad head-meta section: {e}")))?,
        None => HeadMeta { steps: 0 },
    };
    Ok((Some(LoadedHead { head, meta }), path))
}
