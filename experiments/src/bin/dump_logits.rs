//! Writes what mask inference sees for each held-out view, for studying inference rules
//! outside the pipeline: `<out>/<view>.bin` holds, for every pixel, the composited logits,
//! the rendered depth, the rendered 3D point (NaN for empty rays), the ground-truth mask
//! (−1 where there is none), the mask `sos` infers (1 foreground, 0 background) and the
//! ground-truth depth (NaN where there is none), as little-endian f32 rows of
//! `channels + 1 + 3 + 1 + 1 + 1` values; `<out>/meta.json` gives the
//! sizes, the focus point, the camera centre and the channel count.
//!
//! `cargo run --release --manifest-path experiments/Cargo.toml --bin dump_logits -- CONFIG CHECKPOINT OUT_DIR`

use std::io::Write;
use std::path::PathBuf;

use sos_core::segment::infer::{render_logits, FocusTarget, MaskInference};
use sos_experiments::{args_or_usage, open_with_head};
use sos_plugins as _;

fn main() {
    sos_benchmarks::setup();
    let args = args_or_usage(3, "dump_logits CONFIG CHECKPOINT OUT_DIR");
    let (session, head) = open_with_head(&args[0], &args[1]);
    let out = &args[2];
    let out = PathBuf::from(out);
    std::fs::create_dir_all(&out).expect("output folder");
    let focus = FocusTarget::of_scene(&session.scene);
    let inference = MaskInference::new(&session, &head, None).expect("inference");
    let mut views = Vec::new();
    for &i in &session.scene.test {
        let view = &session.scene.views[i];
        let r = render_logits(&session, &head, &view.camera);
        let (w, h) = (r.rgb.width, r.rgb.height);
        // A second render of the view: the mask keeps its depth and points but not its logits.
        let mask = inference.segment(&view.camera, &view.name).expect("mask");
        let gt = view.mask.as_ref().map(|m| m.resized_nearest(w, h));
        let gt_depth = view.depth.as_ref().map(|d| d.resized_nearest(w, h));
        let mut bytes = Vec::with_capacity(w * h * (r.channels + 7) * 4);
        for p in 0..w * h {
            let mut row: Vec<f32> = r.logits[p * r.channels..(p + 1) * r.channels].to_vec();
            row.push(r.depth[p]);
            row.extend(r.points[p].unwrap_or([f32::NAN; 3]));
            row.push(gt.as_ref().map_or(-1.0, |g| g.data[p]));
            row.push(if mask.foreground[p] { 1.0 } else { 0.0 });
            row.push(gt_depth.as_ref().map_or(f32::NAN, |d| d.data[p]));
            row.iter().for_each(|v| bytes.extend(v.to_le_bytes()));
        }
        std::fs::write(out.join(format!("{}.bin", view.name)), bytes).expect("write view");
        let fp = focus.point_for(&r.depth, w, h).unwrap_or(session.scene.focus_point());
        views.push(format!(
            "{{\"name\":\"{}\",\"width\":{w},\"height\":{h},\"focus\":{:?},\"origin\":{:?}}}",
            view.name,
            fp,
            view.camera.origin()
        ));
        eprintln!("{}", view.name);
    }
    let channels = head.outputs();
    let mut f = std::fs::File::create(out.join("meta.json")).expect("meta");
    writeln!(f, "{{\"channels\":{channels},\"views\":[{}]}}", views.join(",")).expect("meta");
}
