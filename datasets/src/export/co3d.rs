//! Writer of the CO3Dv2 layout (one category, one sequence).

use std::path::Path;

use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::Scene;

use super::file_stems;
use crate::co3d::{
    ndc_from_intrinsics, pytorch3d_from_pose, write_jgz, FrameAnnotation, ImageAnnotation, MaskAnnotation,
    SequenceAnnotation, ViewpointAnnotation,
};
use crate::pose;
use crate::views::Intrinsics;

/// Writes category folder `dir/<category>/` with `frame_annotations.jgz`,
/// `sequence_annotations.jgz` and `<sequence>/{images,masks}/<stem>.png`; cameras in PyTorch3D's
/// convention with `ndc_isotropic` intrinsics (or `ndc_norm_image_bounds` when `isotropic` is
/// false). Frame numbers are the view indices.
pub fn write_co3d(
    scene: &Scene,
    dir: &Path,
    category: &str,
    sequence: &str,
    isotropic: bool,
) -> Result<(), DatasetError> {
    let stems = file_stems(scene);
    let cat_dir = dir.join(category);
    let mut frames = Vec::with_capacity(scene.views.len());
    for (i, (v, stem)) in scene.views.iter().zip(&stems).enumerate() {
        let image_rel = format!("{category}/{sequence}/images/{stem}.png");
        v.image.save_png(&dir.join(&image_rel))?;
        let mask = match &v.mask {
            Some(m) => {
                let rel = format!("{category}/{sequence}/masks/{stem}.png");
                m.save_png(&dir.join(&rel))?;
                Some(MaskAnnotation { path: rel, mass: Some(m.data.iter().map(|&x| x as f64).sum()) })
            }
            None => None,
        };
        let k = Intrinsics::of(&v.camera);
        let (focal_length, principal_point) = ndc_from_intrinsics(&k, isotropic);
        let (r, t) = pytorch3d_from_pose(&pose::from_camera(&v.camera));
        frames.push(FrameAnnotation {
            sequence_name: sequence.to_string(),
            frame_number: i as i64,
            image: ImageAnnotation { path: image_rel, size: [k.height as u64, k.width as u64] },
            mask,
            viewpoint: Some(ViewpointAnnotation {
                r,
                t,
                focal_length,
                principal_point,
                intrinsics_format: if isotropic { "ndc_isotropic" } else { "ndc_norm_image_bounds" }.into(),
            }),
        });
    }
    write_jgz(&cat_dir.join("frame_annotations.jgz"), &frames)?;
    let seqs = [SequenceAnnotation {
        sequence_name: sequence.to_string(),
        category: category.to_string(),
        viewpoint_quality_score: Some(1.0),
    }];
    write_jgz(&cat_dir.join("sequence_annotations.jgz"), &seqs)
}
