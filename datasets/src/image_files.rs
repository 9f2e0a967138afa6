//! Finding and reading the image and mask files of a capture folder.

use std::path::{Path, PathBuf};

use sos_core::image::GrayImage;
use sos_core::plugin::dataset::DatasetError;

use crate::text::invalid;

/// File extensions accepted as images, in order of preference when several files share a stem.
pub const IMAGE_EXTENSIONS: [&str; 6] = ["png", "PNG", "jpg", "JPG", "jpeg", "JPEG"];

/// Mask values above this are foreground.
pub const MASK_THRESHOLD: f32 = 0.5;

/// The image files of `dir`, sorted by file name (as LLFF's loader sorts them).
pub fn list_images(dir: &Path) -> Result<Vec<PathBuf>, DatasetError> {
    let entries = std::fs::read_dir(dir).map_err(|e| DatasetError::Invalid {
        path: dir.to_path_buf(),
        message: format!("cannot list the folder: {e}"),
    })?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.is_file() && p.extension().and_then(|e| e.to_str()).is_some_and(|e| IMAGE_EXTENSIONS.contains(&e))
        })
        .collect();
    files.sort_by(|a, b| a.file_name().cmp(&b.file_name()));
    Ok(files)
}

/// `dir/stem.<ext>` for the first accepted extension that exists.
pub fn find_with_stem(dir: &Path, stem: &str) -> Option<PathBuf> {
    IMAGE_EXTENSIONS.iter().map(|ext| dir.join(format!("{stem}.{ext}"))).find(|p| p.is_file())
}

/// `dir/<name>` with an image extension: the name itself when it already names a file, else
/// the name with each accepted extension appended.
pub fn find_image(dir: &Path, name: &str) -> Option<PathBuf> {
    let direct = dir.join(name);
    if direct.is_file() {
        return Some(direct);
    }
    IMAGE_EXTENSIONS.iter().map(|ext| dir.join(format!("{name}.{ext}"))).find(|p| p.is_file())
}

/// Checks that every `.txt` file among `entries` (a listing of per-image camera or pose files)
/// has an image with its stem in `images`, so that no camera is silently dropped.
pub fn check_images_for(entries: std::fs::ReadDir, images: &Path) -> Result<(), DatasetError> {
    for e in entries.flatten() {
        let p = e.path();
        if p.extension().is_some_and(|x| x == "txt") && find_with_stem(images, stem(&p)).is_none() {
            return Err(invalid(
                &p,
                format!("no image with this stem in {}; remove the file or add the image", images.display()),
            ));
        }
    }
    Ok(())
}

/// File stem as text (empty when the name is not UTF-8).
pub fn stem(path: &Path) -> &str {
    path.file_stem().and_then(|s| s.to_str()).unwrap_or("")
}

/// Reads a mask (grey, or luminance of colour), binarised at [`MASK_THRESHOLD`]; it must be
/// `width` x `height`.
pub fn load_mask(path: &Path, width: usize, height: usize) -> Result<GrayImage, DatasetError> {
    binarised(GrayImage::load(path)?, path, width, height, "resize the mask to")
}

/// [`load_mask`] for a mask that may also be a whole multiple of `width` x `height` (masks
/// made at a capture's full resolution for images loaded downscaled), reduced by nearest
/// neighbour as `sos compare` reduces a reference mask.
pub fn load_mask_reduced(path: &Path, width: usize, height: usize) -> Result<GrayImage, DatasetError> {
    let mask = GrayImage::load(path)?;
    let k = mask.width / width.max(1);
    let multiple = k >= 1 && (mask.width, mask.height) == (k * width, k * height);
    let mask = if multiple { mask.resized_nearest(width, height) } else { mask };
    binarised(mask, path, width, height, "give the mask a whole multiple of that size or resize it to")
}

/// `mask` binarised, if it is `width` x `height`; else an error whose advice starts `fix`.
fn binarised(
    mut mask: GrayImage,
    path: &Path,
    width: usize,
    height: usize,
    fix: &str,
) -> Result<GrayImage, DatasetError> {
    if (mask.width, mask.height) != (width, height) {
        return Err(DatasetError::Invalid {
            path: path.to_path_buf(),
            message: format!(
                "mask is {}x{} but its image is {width}x{height}; {fix} \
                 {width}x{height} (nearest-neighbour)",
                mask.width, mask.height
            ),
        });
    }
    for v in &mut mask.data {
        *v = if *v > MASK_THRESHOLD { 1.0 } else { 0.0 };
    }
    Ok(mask)
}
