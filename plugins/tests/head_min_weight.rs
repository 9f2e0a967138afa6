//! `masks.head_min_weight`: a rendered view's composited logits leave out the samples at or
//! below it; unset, the view uses the samples stage 2 trained the head on.

mod common;

use std::path::Path;

use common::two_stage_session;
use sos_core::config::{LogitSource, RunConfig};
use sos_core::segment::infer::render_logits;
// Links every plugin so the config kinds resolve.
use sos_plugins as _;

#[test]
fn head_min_weight_leaves_out_light_samples_and_defaults_to_the_training_threshold() {
    // The threshold leaves samples out of composited logits only.
    let (mut s, seg) = two_stage_session("head-min-weight", LogitSource::Composited);
    let camera = s.scene.views[s.scene.test[0]].camera.clone();
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();

    let unset = render_logits(&s, &seg.head, &camera);
    s.config.masks.head_min_weight = Some(s.config.segment.weight_threshold);
    let same = render_logits(&s, &seg.head, &camera);
    assert_eq!(bits(&unset.logits), bits(&same.logits), "unset must mean the training threshold");

    s.config.masks.head_min_weight = Some(0.2);
    let surface = render_logits(&s, &seg.head, &camera);
    assert!(surface.logits.iter().all(|v| v.is_finite()));
    assert_ne!(bits(&unset.logits), bits(&surface.logits), "a higher threshold must leave samples out");
    // Colour and depth do not depend on it.
    assert_eq!(unset.rgb.data, surface.rgb.data);
    assert_eq!(bits(&unset.depth), bits(&surface.depth));
}

#[test]
fn a_head_min_weight_outside_zero_to_one_is_refused_by_name() {
    for bad in ["1.0", "-0.1", "nan"] {
        let text = format!("name = \"x\"\n[scene]\nkind = \"synthetic\"\n[masks]\nhead_min_weight = {bad}\n");
        let err = RunConfig::parse(&text, Path::new("bad.toml")).unwrap_err().to_string();
        assert!(err.contains("masks.head_min_weight") && err.contains("bad.toml"), "{bad}: {err}");
    }
}
