//! Non-finite losses and gradients: injected NaNs must skip the step (parameters untouched),
//! training must continue once they stop, and a run of bad steps must stop with a clear error.

mod common;

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use common::tiny_session;
use sos_core::camera::Vec3;
use sos_core::error::{RunError, StateError};
use sos_core::plugin::field::plain;
use sos_core::plugin::{CoarseToFine, FieldTape, RadianceField};
use sos_core::segment::train::{train_segmentation, Segmenter};
use sos_core::train::photometric::train_photometric;
use sos_core::train::Session;
// Links every plugin (datasets, extractors, losses) so the config kinds resolve.
use sos_plugins as _;

/// Where the NaN goes.
#[derive(Clone, Copy, PartialEq)]
enum Inject {
    /// NaN colours out of the forward pass (a non-finite loss).
    Colour,
    /// NaN density gradients into the wrapped field's backward (finite loss, bad gradients).
    Gradient,
}

/// Wraps a field and poisons the first `bad_steps` steps (counted by `begin_step`/forward).
struct Poisoned {
    inner: Box<dyn RadianceField>,
    inject: Inject,
    /// Steps still to poison.
    left: AtomicUsize,
    /// Steps the wrapped field actually applied.
    applied: Arc<AtomicUsize>,
}

impl Poisoned {
    fn active(&self) -> bool {
        self.left.load(Ordering::Relaxed) > 0
    }
}

impl RadianceField for Poisoned {
    sos_core::pass_on_field_methods!(inner);

    fn forward(&self, p: &[Vec3], dirs: &[Vec3], d: &mut [f32], c: &mut [[f32; 3]], record: bool) -> FieldTape {
        let tape = self.inner.forward(p, dirs, d, c, record);
        if self.active() {
            match self.inject {
                Inject::Colour => c.iter_mut().step_by(7).for_each(|c| c[1] = f32::NAN),
                Inject::Gradient => {}
            }
        }
        tape
    }
    fn backward(&mut self, p: &[Vec3], dirs: &[Vec3], tape: FieldTape, gd: &[f32], gc: &[[f32; 3]]) {
        if self.inject == Inject::Gradient && self.active() {
            let mut bad = gd.to_vec();
            bad.iter_mut().step_by(5).for_each(|g| *g = f32::NAN);
            self.inner.backward(p, dirs, tape, &bad, gc);
        } else {
            self.inner.backward(p, dirs, tape, gd, gc);
        }
    }
    fn step(&mut self, lr_factor: f32) {
        self.applied.fetch_add(1, Ordering::Relaxed);
        self.inner.step(lr_factor);
    }
    // Every field is wrapped as growing: its step hook counts the poisoned steps.
    fn coarse_to_fine(&self) -> Option<&dyn CoarseToFine> {
        Some(self)
    }
    fn coarse_to_fine_mut(&mut self) -> Option<&mut dyn CoarseToFine> {
        Some(self)
    }
}

impl CoarseToFine for Poisoned {
    fn begin_step(&mut self, step: usize, total: usize) -> bool {
        // One poisoned training step per call while any are left (stage 1).
        if step > 0 {
            let _ = self.left.fetch_update(Ordering::Relaxed, Ordering::Relaxed, |v| v.checked_sub(1));
        }
        plain::begin_step(self.inner.as_mut(), step, total)
    }
    fn detail_fraction(&self) -> f32 {
        plain::detail_fraction(self.inner.as_ref())
    }
}

fn session(steps: usize, field: &str) -> Session {
    let keys = if field == "nerf" {
        "depth = 2\nwidth = 16\nskip = 0\nview_width = 8\ncoarse_samples = 8\nfine_samples = 8"
    } else {
        "resolution = [16, 16, 16]\ninitial_resolution = [16, 16, 16]\nupsample_at = []"
    };
    tiny_session(field, "object-centric", keys, steps, &format!("non-finite-{steps}"))
}

fn poison(session: &mut Session, inject: Inject, bad_steps: usize) -> Arc<AtomicUsize> {
    let applied = Arc::new(AtomicUsize::new(0));
    let inner = std::mem::replace(&mut session.field, Box::new(Dummy));
    session.field = Box::new(Poisoned { inner, inject, left: AtomicUsize::new(bad_steps), applied: applied.clone() });
    applied
}

#[test]
fn bad_steps_are_skipped_and_training_continues() {
    for (field, inject) in
        [("voxel-grid", Inject::Colour), ("voxel-grid", Inject::Gradient), ("nerf", Inject::Gradient)]
    {
        let mut s = session(10, field);
        let before = s.field.save_state();
        // Steps 0..=3 are poisoned (begin_step of step k > 0 consumes one), then 6 clean ones.
        let applied = poison(&mut s, inject, 4);
        let stats = train_photometric(&mut s).expect("a few bad steps do not stop the run");
        let n = applied.load(Ordering::Relaxed);
        assert_eq!(n, 6, "{field}: only the clean steps may update the field (applied {n})");
        assert!(stats.mse.is_finite());
        assert_ne!(s.field.save_state(), before, "the clean steps trained");
        std::fs::remove_dir_all(&s.run_dir).ok();
    }
}

#[test]
fn a_run_of_bad_steps_stops_with_a_clear_message() {
    let mut s = session(40, "voxel-grid");
    let before = s.field.save_state();
    let applied = poison(&mut s, Inject::Gradient, usize::MAX);
    match train_photometric(&mut s) {
        Err(RunError::Diverged(message)) => {
            assert!(message.contains("20 stage-1 steps in a row"), "{message}");
            assert!(message.contains("learning rate"), "the message suggests a fix: {message}");
        }
        other => panic!("expected divergence, got {:?}", other.map(|s| s.mse)),
    }
    assert_eq!(applied.load(Ordering::Relaxed), 0);
    assert_eq!(s.field.save_state(), before, "no bad gradient reached the parameters");
}

#[test]
fn stage_two_skips_non_finite_steps_then_stops() {
    let mut s = session(2, "voxel-grid");
    train_photometric(&mut s).unwrap();
    // NaN colours reach the teacher through the rendered patches: a non-finite loss.
    poison(&mut s, Inject::Colour, usize::MAX);
    let mut seg = Segmenter::build(&s).unwrap();
    let head_before = seg.head.to_bytes();
    s.config.segment.steps = 25;
    // Keep every sample, so the poisoned colours are composited (0 · NaN = NaN).
    s.config.segment.weight_threshold = 0.0;
    match train_segmentation(&mut s, &mut seg) {
        Err(RunError::Diverged(message)) => assert!(message.contains("non-finite"), "{message}"),
        other => panic!("expected divergence, got {:?}", other.map(|s| s.total)),
    }
    assert_eq!(seg.head.to_bytes(), head_before, "no step reached the head");
    std::fs::remove_dir_all(&s.run_dir).ok();
}

/// Placeholder while the real field is moved into the wrapper.
struct Dummy;

impl RadianceField for Dummy {
    fn density(&self, _: &[Vec3], _: &mut [f32]) {}
    fn forward(&self, _: &[Vec3], _: &[Vec3], _: &mut [f32], _: &mut [[f32; 3]], _: bool) -> FieldTape {
        None
    }
    fn backward(&mut self, _: &[Vec3], _: &[Vec3], _: FieldTape, _: &[f32], _: &[[f32; 3]]) {}
    fn step(&mut self, _: f32) {}
    fn gradients_finite(&self) -> bool {
        true
    }
    fn discard_gradients(&mut self) {}
    fn seg_input_dim(&self) -> usize {
        0
    }
    fn seg_input(&self, _: &[Vec3], _: &mut [f32]) {}
    fn save_state(&self) -> Vec<u8> {
        Vec::new()
    }
    fn load_state(&mut self, _: &[u8]) -> Result<(), StateError> {
        Ok(())
    }
    fn num_parameters(&self) -> usize {
        0
    }
    fn parameters(&self) -> Vec<f32> {
        Vec::new()
    }
    fn set_parameters(&mut self, _: &[f32]) -> Result<(), sos_core::error::StateError> {
        Ok(())
    }
    fn gradients(&self) -> Vec<f32> {
        Vec::new()
    }
}
