//! Stage 2 with the density pass's state (NeRF's trunk kept for the colour pass) trains the
//! same head, bit for bit, as stage 2 evaluating the kept samples afresh; for `nerf` and for
//! `nerf++` with its background network.

mod common;

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use common::tiny_session;
use sos_core::camera::Vec3;
use sos_core::plugin::field::plain;
use sos_core::plugin::{FieldTape, FrozenPass, HierarchicalSampling, RadianceField};
use sos_core::segment::train::{train_segmentation, Segmenter};
use sos_core::train::photometric::train_photometric;
use sos_core::train::Session;
// Links every plugin (datasets, extractors, losses) so the config kinds resolve.
use sos_plugins as _;

/// A field that either hides its density state (so the renderer evaluates kept samples
/// afresh) or counts the samples coloured from it.
struct Probe {
    inner: Box<dyn RadianceField>,
    hide_state: bool,
    from_state: Arc<AtomicUsize>,
}

impl RadianceField for Probe {
    sos_core::pass_on_field_methods!(inner);

    fn forward(&self, p: &[Vec3], d: &[Vec3], density: &mut [f32], rgb: &mut [[f32; 3]], record: bool) -> FieldTape {
        self.inner.forward(p, d, density, rgb, record)
    }
    fn backward(&mut self, p: &[Vec3], d: &[Vec3], tape: FieldTape, gd: &[f32], gc: &[[f32; 3]]) {
        self.inner.backward(p, d, tape, gd, gc);
    }
    fn step(&mut self, lr_factor: f32) {
        self.inner.step(lr_factor);
    }
    fn hierarchical(&self) -> Option<&dyn HierarchicalSampling> {
        self.inner.hierarchical()
    }
    fn frozen_pass(&self) -> Option<&dyn FrozenPass> {
        Some(self)
    }
}

impl FrozenPass for Probe {
    fn forward_with_seg_input(
        &self,
        p: &[Vec3],
        d: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        seg: &mut [f32],
    ) {
        plain::forward_with_seg_input(self.inner.as_ref(), p, d, density, rgb, seg);
    }
    fn density_state_dim(&self) -> usize {
        if self.hide_state {
            0
        } else {
            plain::density_state_dim(self.inner.as_ref())
        }
    }
    fn density_with_state(&self, p: &[Vec3], density: &mut [f32], state: &mut [f32]) {
        plain::density_with_state(self.inner.as_ref(), p, density, state);
    }
    fn colour_from_state(
        &self,
        p: &[Vec3],
        d: &[Vec3],
        state: &[f32],
        rows: &[u32],
        rgb: &mut [[f32; 3]],
        seg: Option<&mut [f32]>,
    ) {
        self.from_state.fetch_add(rows.len(), Ordering::Relaxed);
        plain::colour_from_state(self.inner.as_ref(), p, d, state, rows, rgb, seg);
    }
}

fn session(field: &str, tag: &str) -> Session {
    let (rig, sampling) = match field {
        "nerf" => ("object-centric", "coarse_samples = 8\nfine_samples = 16"),
        _ => ("unbounded", "hierarchical = false"),
    };
    let keys = format!("depth = 2\nwidth = 32\nskip = 0\nview_width = 8\n{sampling}");
    tiny_session(field, rig, &keys, 6, &format!("density-state-{tag}"))
}

/// Stage 2 from the field state `trained` with the probe wrapped around the field: the
/// head's bytes and the samples coloured from the density pass's state.
fn stage2(field: &str, trained: &[u8], hide_state: bool) -> (Vec<u8>, usize) {
    let tag = if hide_state { "hidden" } else { "kept" };
    let mut s = session(field, tag);
    let mut donor = session(field, &format!("{tag}-donor"));
    std::fs::remove_dir_all(&donor.run_dir).ok();
    donor.field.load_state(trained).unwrap();
    let from_state = Arc::new(AtomicUsize::new(0));
    s.field = Box::new(Probe { inner: donor.field, hide_state, from_state: from_state.clone() });
    let mut seg = Segmenter::build(&s).unwrap();
    train_segmentation(&mut s, &mut seg).unwrap();
    std::fs::remove_dir_all(&s.run_dir).ok();
    (seg.head.to_bytes(), from_state.load(Ordering::Relaxed))
}

#[test]
fn stage_two_trains_the_same_head_with_the_density_state() {
    for field in ["nerf", "nerf++"] {
        let mut s = session(field, "stage1");
        train_photometric(&mut s).unwrap();
        let trained = s.field.save_state();
        std::fs::remove_dir_all(&s.run_dir).ok();
        let (kept, coloured) = stage2(field, &trained, false);
        let (hidden, none) = stage2(field, &trained, true);
        assert!(coloured > 0, "{field}: stage 2 took no colour from the density state");
        assert_eq!(none, 0);
        assert!(kept == hidden, "{field}: the head differs when the density state is used");
    }
}
