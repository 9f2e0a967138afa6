//! A blank scene for tests of samplers and teachers: black images, cameras on the z axis.

use crate::camera::Camera;
use crate::image::RgbImage;
use crate::scene::{Scene, SceneExtent, View};

/// `views` black `width x height` views named `v0`, `v1`, ..., all used for training.
pub fn blank_scene(views: usize, width: u32, height: u32) -> Scene {
    let views = (0..views)
        .map(|i| View {
            name: format!("v{i}"),
            camera: Camera::look_at([0.0, 0.0, 3.0 + i as f32], [0.0; 3], [0.0, 1.0, 0.0], width, height, 100.0),
            image: RgbImage::new(width as usize, height as usize),
            mask: None,
            depth: None,
        })
        .collect::<Vec<_>>();
    Scene {
        name: "t".into(),
        train: (0..views.len()).collect(),
        views,
        test: vec![],
        extent: SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] },
        near: 0.0,
        render_path: vec![],
    }
}
