//! The four DINO ViT architectures and where their official weights are published.

use serde::{Deserialize, Serialize};

/// Where the DINO authors list their pretrained weights.
pub const DINO_README: &str = "https://github.com/facebookresearch/dino#pretrained-models";

/// A DINO ViT architecture, or `auto` to take it from the checkpoint.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Arch {
    /// Whatever the checkpoint holds (width, patch and depth are read from its shapes; heads
    /// are `width / 64`, as in every DINO ViT, unless `heads` is set).
    #[default]
    Auto,
    /// ViT-S/16 (384 wide, 12 blocks, 6 heads, 16-px patches): the reference's teacher.
    Vits16,
    /// ViT-S/8.
    Vits8,
    /// ViT-B/16 (768 wide, 12 blocks, 12 heads).
    Vitb16,
    /// ViT-B/8.
    Vitb8,
}

/// The named architectures with `(embed dim, patch, depth, heads)`.
pub const NAMED: [(Arch, usize, usize, usize, usize); 4] = [
    (Arch::Vits16, 384, 16, 12, 6),
    (Arch::Vits8, 384, 8, 12, 6),
    (Arch::Vitb16, 768, 16, 12, 12),
    (Arch::Vitb8, 768, 8, 12, 12),
];

impl Arch {
    /// `(embed dim, patch, depth, heads)` of a named architecture; `None` for `auto`.
    pub fn dims(self) -> Option<(usize, usize, usize, usize)> {
        NAMED.iter().find(|n| n.0 == self).map(|n| (n.1, n.2, n.3, n.4))
    }

    /// The named architecture with these dimensions, if any.
    pub fn from_dims(dim: usize, patch: usize, depth: usize) -> Option<Arch> {
        NAMED.iter().find(|n| (n.1, n.2, n.3) == (dim, patch, depth)).map(|n| n.0)
    }

    /// The config spelling (`vits16`, …).
    pub fn name(self) -> &'static str {
        match self {
            Arch::Auto => "auto",
            Arch::Vits16 => "vits16",
            Arch::Vits8 => "vits8",
            Arch::Vitb16 => "vitb16",
            Arch::Vitb8 => "vitb8",
        }
    }

    /// File name of the official backbone weights (`auto`: ViT-S/16's, the reference's).
    pub fn official_file(self) -> &'static str {
        match self {
            Arch::Auto | Arch::Vits16 => "dino_deitsmall16_pretrain.pth",
            Arch::Vits8 => "dino_deitsmall8_pretrain.pth",
            Arch::Vitb16 => "dino_vitbase16_pretrain.pth",
            Arch::Vitb8 => "dino_vitbase8_pretrain.pth",
        }
    }

    /// Download address of the official backbone weights.
    pub fn official_url(self) -> String {
        let file = self.official_file();
        let stem = file.trim_end_matches(".pth");
        format!("https://dl.fbaipublicfiles.com/dino/{stem}/{file}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_dims_and_urls() {
        assert_eq!(Arch::from_dims(384, 16, 12), Some(Arch::Vits16));
        assert_eq!(Arch::from_dims(768, 8, 12), Some(Arch::Vitb8));
        assert_eq!(Arch::from_dims(64, 16, 2), None);
        assert_eq!(Arch::Vitb16.dims(), Some((768, 16, 12, 12)));
        assert_eq!(Arch::Auto.dims(), None);
        assert_eq!(
            Arch::Vits16.official_url(),
            "https://dl.fbaipublicfiles.com/dino/dino_deitsmall16_pretrain/dino_deitsmall16_pretrain.pth"
        );
        assert_eq!(Arch::Vitb8.official_file(), "dino_vitbase8_pretrain.pth");
        let parsed: Arch = serde_json::from_str("\"vits8\"").unwrap();
        assert_eq!(parsed, Arch::Vits8);
        assert_eq!(parsed.name(), "vits8");
    }
}
