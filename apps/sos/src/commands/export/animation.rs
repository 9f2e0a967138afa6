//! The camera path's animated GIF: frames are quantised to a palette each (NeuQuant, as
//! `image` does) and appended as they are rendered, so no more than one frame is held.

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use sos_core::image::RgbImage;

/// Time each frame is shown, in hundredths of a second (the GIF unit): about 15 frames a second.
pub const FRAME_DELAY_CS: u16 = 7;

/// NeuQuant sampling speed (1 = best palette, 30 = fastest); 10 is the `gif` crate's default.
const QUANTISER_SPEED: i32 = 10;

/// An animated GIF being written; [`GifWriter::finish`] moves it into place.
pub struct GifWriter {
    encoder: gif::Encoder<BufWriter<File>>,
    tmp: PathBuf,
    path: PathBuf,
    width: u16,
    height: u16,
    frames: usize,
}

impl GifWriter {
    /// Starts a looping GIF of `width` x `height` frames at `path` (written to a temporary file
    /// until finished).
    pub fn create(path: &Path, width: usize, height: usize) -> anyhow::Result<GifWriter> {
        let (Ok(w), Ok(h)) = (u16::try_from(width), u16::try_from(height)) else {
            bail!(
                "{}: a GIF holds at most 65535x65535 pixels, the camera path renders {width}x{height}",
                path.display()
            );
        };
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
        }
        let mut tmp = path.as_os_str().to_owned();
        tmp.push(".tmp");
        let tmp = PathBuf::from(tmp);
        let file = File::create(&tmp).with_context(|| format!("writing {}", tmp.display()))?;
        let mut encoder =
            gif::Encoder::new(BufWriter::new(file), w, h, &[]).with_context(|| format!("writing {}", tmp.display()))?;
        encoder.set_repeat(gif::Repeat::Infinite).with_context(|| format!("writing {}", tmp.display()))?;
        Ok(GifWriter { encoder, tmp, path: path.to_path_buf(), width: w, height: h, frames: 0 })
    }

    /// Appends a frame of the size the GIF was created with.
    pub fn push(&mut self, frame: &RgbImage) -> anyhow::Result<()> {
        if (frame.width, frame.height) != (self.width as usize, self.height as usize) {
            bail!(
                "{}: frame {} is {}x{}, the GIF's first frame {}x{}",
                self.path.display(),
                self.frames,
                frame.width,
                frame.height,
                self.width,
                self.height
            );
        }
        let bytes: Vec<u8> = frame.data.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8).collect();
        let mut gif_frame = gif::Frame::from_rgb_speed(self.width, self.height, &bytes, QUANTISER_SPEED);
        gif_frame.delay = FRAME_DELAY_CS;
        self.encoder.write_frame(&gif_frame).with_context(|| format!("writing {}", self.tmp.display()))?;
        self.frames += 1;
        Ok(())
    }

    /// Writes the trailer and moves the file into place; returns the number of frames.
    pub fn finish(self) -> anyhow::Result<usize> {
        let mut out = self.encoder.into_inner().with_context(|| format!("writing {}", self.tmp.display()))?;
        std::io::Write::flush(&mut out).with_context(|| format!("writing {}", self.tmp.display()))?;
        drop(out);
        std::fs::rename(&self.tmp, &self.path).with_context(|| format!("writing {}", self.path.display()))?;
        Ok(self.frames)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_decode_back_in_order() {
        let path = std::env::temp_dir().join(format!("sos-export-gif-{}.gif", std::process::id()));
        let mut gif = GifWriter::create(&path, 6, 4).unwrap();
        for shade in [0.0, 0.5, 1.0] {
            let mut img = RgbImage::new(6, 4);
            img.data.iter_mut().for_each(|v| *v = shade);
            gif.push(&img).unwrap();
        }
        assert!(gif.push(&RgbImage::new(5, 4)).is_err());
        assert_eq!(gif.finish().unwrap(), 3);
        let mut options = gif::DecodeOptions::new();
        options.set_color_output(gif::ColorOutput::RGBA);
        let mut decoder = options.read_info(File::open(&path).unwrap()).unwrap();
        let mut greys = Vec::new();
        while let Some(frame) = decoder.read_next_frame().unwrap() {
            assert_eq!((frame.width, frame.height, frame.delay), (6, 4, FRAME_DELAY_CS));
            greys.push(frame.buffer[0]);
        }
        assert_eq!(greys.len(), 3);
        assert!(greys[0] < 10 && (120..136).contains(&greys[1]) && greys[2] > 245, "{greys:?}");
        std::fs::remove_file(&path).ok();
    }
}
