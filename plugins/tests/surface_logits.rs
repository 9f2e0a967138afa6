//! `logits = "surface"`: a view's logits are the head at each pixel's rendered point times the
//! ray's opacity (zero for empty rays), with colour, depth and points those of the composited
//! render; stage 2 can train the head the same way, and views then follow it.

mod common;

use std::path::Path;

use common::{tiny_session, two_stage_session};
use sos_core::config::{LogitSource, RunConfig};
use sos_core::render::rays::RayBatch;
use sos_core::render::renderer::render_inference;
use sos_core::segment::head_pass;
use sos_core::segment::infer::render_logits;
use sos_core::segment::train::{train_segmentation, Segmenter};
use sos_core::train::photometric::train_photometric;
// Links every plugin so the config kinds resolve.
use sos_plugins as _;

#[test]
fn surface_logits_are_the_head_at_each_pixels_point_times_its_opacity() {
    let (mut s, seg) = two_stage_session("surface-logits", LogitSource::Composited);
    let camera = s.scene.views[s.scene.test[0]].camera.clone();
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();

    let composited = render_logits(&s, &seg.head, &camera);
    s.config.masks.logits = Some(LogitSource::Surface);
    let surface = render_logits(&s, &seg.head, &camera);
    assert_eq!(composited.rgb.data, surface.rgb.data);
    assert_eq!(bits(&composited.depth), bits(&surface.depth));
    assert_eq!(composited.points, surface.points);
    assert!(bits(&composited.logits) != bits(&surface.logits), "the surface logits must be evaluated anew");

    let rays = RayBatch::full_image(&camera);
    let ctx = s.render_context();
    let (colours, _) =
        render_inference(s.field.as_ref(), ctx, &rays, s.render_options(false), s.config.render.chunk, None);
    let d = surface.channels;
    let mut hits = 0;
    for (i, point) in surface.points.iter().enumerate() {
        let got = &surface.logits[i * d..(i + 1) * d];
        match point {
            Some(p) => {
                hits += 1;
                let head = head_pass::sample_logits(s.field.as_ref(), &seg.head, &[*p]);
                let expected: Vec<f32> = head.iter().map(|v| colours[i].acc * v).collect();
                // One point alone goes through the head's GEMMs in another blocking than a whole
                // view's points: its sums (of at most 128 products) may round differently.
                for (g, e) in got.iter().zip(&expected) {
                    assert!((g - e).abs() <= 1e-5 * (1.0 + e.abs()), "pixel {i}: {got:?} against {expected:?}");
                }
            }
            None => assert!(got.iter().all(|&v| v == 0.0), "empty pixel {i} has logits {got:?}"),
        }
    }
    assert!(hits > 0, "the view must show the scene");
}

#[test]
fn the_logit_source_is_read_from_the_config_and_an_unknown_one_is_refused_by_name() {
    let text = |value: &str| format!("name = \"x\"\n[scene]\nkind = \"synthetic\"\n[masks]\nlogits = \"{value}\"\n");
    let config = RunConfig::parse(&text("surface"), Path::new("ok.toml")).unwrap();
    assert_eq!(config.masks.logits, Some(LogitSource::Surface));
    let default = RunConfig::parse("name = \"x\"\n[scene]\nkind = \"synthetic\"\n", Path::new("ok.toml")).unwrap();
    assert_eq!((default.masks.logits, default.segment.logits), (None, LogitSource::Surface));
    let err = RunConfig::parse(&text("middle"), Path::new("bad.toml")).unwrap_err().to_string();
    assert!(err.contains("logits") && err.contains("bad.toml"), "{err}");
}

#[test]
fn stage_two_on_surface_points_trains_another_head_and_views_follow_it() {
    let mut s = tiny_session("voxel-grid", "object-centric", "", 40, "surface-training");
    train_photometric(&mut s).unwrap();
    s.config.segment.logits = LogitSource::Composited;
    let mut composited = Segmenter::build(&s).unwrap();
    let composited_stats = train_segmentation(&mut s, &mut composited).unwrap();
    s.config.segment.logits = LogitSource::Surface;
    let mut surface = Segmenter::build(&s).unwrap();
    let surface_stats = train_segmentation(&mut s, &mut surface).unwrap();
    assert!(composited_stats.total.is_finite() && surface_stats.total.is_finite());
    let camera = s.scene.views[s.scene.test[0]].camera.clone();
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    let unset = render_logits(&s, &surface.head, &camera);
    s.config.masks.logits = Some(LogitSource::Composited);
    let other = render_logits(&s, &composited.head, &camera);
    assert!(bits(&unset.logits) != bits(&other.logits), "the surface-trained head must differ");
    // An unset `masks.logits` renders views as stage 2 trained.
    s.config.masks.logits = Some(LogitSource::Surface);
    assert_eq!(bits(&unset.logits), bits(&render_logits(&s, &surface.head, &camera).logits));
}

#[test]
fn surface_training_with_a_trained_field_is_refused_by_name() {
    let text =
        "name = \"x\"\n[scene]\nkind = \"synthetic\"\n[segment]\nlogits = \"surface\"\nphotometric_weight = 0.1\n";
    let err = RunConfig::parse(text, Path::new("bad.toml")).unwrap_err().to_string();
    assert!(err.contains("segment.logits") && err.contains("bad.toml"), "{err}");
}
