//! Property-based fuzzing (proptest) of every parser and loader, seeded from the generator's
//! output in each layout: files are truncated, bytes flipped or inserted, numbers replaced by
//! NaN, infinities or huge values, lines deleted or duplicated, files emptied or replaced by
//! noise. The property: the result is `Ok` or a typed error, never a panic (proptest catches
//! panics and shrinks them to a minimal mutation).
//!
//! Case counts: `SOS_FUZZ_CASES` (default 1000) per parser test and an eighth of it per
//! loader test; each test prints how many cases it tried. `datasets/FUZZING.md` records runs.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use proptest::prelude::*;
use proptest::test_runner::{Config, TestRunner};
use sos_datasets::layouts::Format;
use sos_datasets::synthetic::{generate, Rig, SyntheticConfig};
use sos_datasets::{blendedmvs, co3d, colmap, colmap_points, npy, tanks_temples};

fn cases() -> u32 {
    std::env::var("SOS_FUZZ_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(1000)
}

fn runner(cases: u32) -> TestRunner {
    TestRunner::new(Config { cases, failure_persistence: None, ..Config::default() })
}

/// The generator's small object-centric scene written in every layout to a folder of the test
/// `name` (removed by the test).
fn seed_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("sos-fuzz-seed-{}-{name}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    let scene = |rig| {
        generate(&SyntheticConfig { rig, width: 24, height: 16, views: 6, hold_out_every: 3, ..Default::default() })
    };
    let (orbit, forward) = (scene(Rig::ObjectCentric), scene(Rig::ForwardFacing));
    for f in Format::ALL {
        // COLMAP reads its points only for captures that look one way.
        let s = if matches!(f, Format::ColmapBin | Format::ColmapTxt) { &forward } else { &orbit };
        f.write(s, &dir.join(f.name())).unwrap();
    }
    dir
}

/// Every file below `dir`, sorted.
fn files_below(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// Replacement numbers: non-finite, out of range, degenerate, malformed.
const NUMBERS: [&str; 14] = [
    "nan",
    "NaN",
    "inf",
    "-inf",
    "1e400",
    "-1e400",
    "0",
    "-0",
    "1e-320",
    "-1",
    "99999999999999999999",
    "3.5e38",
    "",
    "1..2",
];

/// Eight-byte values written over binary files.
const WORDS: [u64; 6] = [
    0x7ff8_0000_0000_0000, // NaN
    0x7ff0_0000_0000_0000, // inf
    u64::MAX,
    0,
    1 << 40,
    0x7fef_ffff_ffff_ffff, // f64::MAX
];

#[derive(Debug, Clone)]
enum Mutation {
    Truncate(f64),
    Flip(Vec<(f64, u8)>),
    Insert(f64, Vec<u8>),
    Number(f64, usize),
    Word(f64, usize),
    DeleteLine(f64),
    DuplicateLine(f64),
    Empty,
    Noise(Vec<u8>),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        1 => (0.0..1.0f64).prop_map(Mutation::Truncate),
        1 => proptest::collection::vec((0.0..1.0f64, 1u8..=255), 1..6).prop_map(Mutation::Flip),
        1 => (0.0..1.0f64, proptest::collection::vec(any::<u8>(), 1..12))
            .prop_map(|(p, b)| Mutation::Insert(p, b)),
        3 => (0.0..1.0f64, 0..NUMBERS.len()).prop_map(|(p, k)| Mutation::Number(p, k)),
        1 => (0.0..1.0f64, 0..WORDS.len()).prop_map(|(p, k)| Mutation::Word(p, k)),
        1 => (0.0..1.0f64).prop_map(Mutation::DeleteLine),
        1 => (0.0..1.0f64).prop_map(Mutation::DuplicateLine),
        1 => Just(Mutation::Empty),
        1 => proptest::collection::vec(any::<u8>(), 0..48).prop_map(Mutation::Noise),
    ]
}

fn at(p: f64, len: usize) -> usize {
    ((p * len as f64) as usize).min(len.saturating_sub(1))
}

/// Byte ranges of the numbers in `bytes` (runs of `0-9 . e E + -` holding a digit).
fn number_spans(bytes: &[u8]) -> Vec<(usize, usize)> {
    let is_num = |b: u8| b.is_ascii_digit() || b"+-.eE".contains(&b);
    let mut spans = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        if is_num(bytes[i]) {
            let start = i;
            while i < bytes.len() && is_num(bytes[i]) {
                i += 1;
            }
            if bytes[start..i].iter().any(u8::is_ascii_digit) {
                spans.push((start, i));
            }
        } else {
            i += 1;
        }
    }
    spans
}

fn line_spans(bytes: &[u8]) -> Vec<(usize, usize)> {
    let mut spans = Vec::new();
    let mut start = 0;
    for (i, &b) in bytes.iter().enumerate() {
        if b == b'\n' {
            spans.push((start, i + 1));
            start = i + 1;
        }
    }
    if start < bytes.len() {
        spans.push((start, bytes.len()));
    }
    spans
}

fn apply(bytes: &[u8], m: &Mutation) -> Vec<u8> {
    let mut b = bytes.to_vec();
    match m {
        Mutation::Truncate(p) => b.truncate(at(*p, b.len())),
        Mutation::Flip(flips) => {
            for &(p, x) in flips {
                if !b.is_empty() {
                    let i = at(p, b.len());
                    b[i] ^= x;
                }
            }
        }
        Mutation::Insert(p, ins) => {
            let i = at(*p, b.len() + 1);
            b.splice(i..i, ins.iter().copied());
        }
        Mutation::Number(p, k) => {
            let spans = number_spans(&b);
            if !spans.is_empty() {
                let (s, e) = spans[at(*p, spans.len())];
                b.splice(s..e, NUMBERS[*k].bytes());
            }
        }
        Mutation::Word(p, k) => {
            if b.len() >= 8 {
                let i = at(*p, (b.len() - 8) / 8 + 1) * 8;
                b[i..i + 8].copy_from_slice(&WORDS[*k].to_le_bytes());
            }
        }
        Mutation::DeleteLine(p) => {
            let lines = line_spans(&b);
            if !lines.is_empty() {
                let (s, e) = lines[at(*p, lines.len())];
                b.drain(s..e);
            }
        }
        Mutation::DuplicateLine(p) => {
            let lines = line_spans(&b);
            if !lines.is_empty() {
                let (s, e) = lines[at(*p, lines.len())];
                let line = b[s..e].to_vec();
                b.splice(e..e, line);
            }
        }
        Mutation::Empty => b.clear(),
        Mutation::Noise(n) => b = n.clone(),
    }
    b
}

fn gunzip(bytes: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    flate2::read::GzDecoder::new(bytes).read_to_end(&mut out).unwrap();
    out
}

fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    enc.write_all(bytes).unwrap();
    enc.finish().unwrap()
}

/// Runs the parser that reads files named like `path` on `bytes`; `None` when no parser
/// reads such files.
fn parse(path: &Path, bytes: &[u8]) -> Option<bool> {
    let name = path.file_name()?.to_str()?;
    let text = || String::from_utf8_lossy(bytes).into_owned();
    let parent = path.parent()?.file_name()?.to_str()?;
    Some(match name {
        "poses_bounds.npy" => npy::parse_npy(bytes).is_ok(),
        "cameras.bin" => colmap::parse_cameras_bin(path, bytes).is_ok(),
        "images.bin" => colmap::parse_images_bin(path, bytes).is_ok(),
        "cameras.txt" => colmap::parse_cameras_txt(path, &text()).is_ok(),
        "images.txt" => colmap::parse_images_txt(path, &text()).is_ok(),
        "points3D.bin" => colmap_points::parse_points_bin(path, bytes).is_ok(),
        "points3D.txt" => colmap_points::parse_points_txt(path, &text()).is_ok(),
        "intrinsics.txt" => blendedmvs::parse_nsvf_intrinsics(path, &text()).is_ok(),
        "bbox.txt" => blendedmvs::parse_bbox(path, &text()).is_ok(),
        "frame_annotations.jgz" => co3d::parse_jgz::<Vec<co3d::FrameAnnotation>>(path, bytes).is_ok(),
        "sequence_annotations.jgz" => co3d::parse_jgz::<Vec<co3d::SequenceAnnotation>>(path, bytes).is_ok(),
        n if n.ends_with("_cam.txt") => blendedmvs::parse_cam_txt(path, &text()).is_ok(),
        n if n.ends_with(".txt") && parent == "pose" => tanks_temples::parse_c2w_opencv(path, &text()).is_ok(),
        n if n.ends_with(".txt") && parent == "intrinsics" => tanks_temples::parse_k(path, &text()).is_ok(),
        _ => return None,
    })
}

/// One seed file per parser: (path, bytes, whether it is gzip to be mutated inside).
fn parser_seeds(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut seeds: Vec<(PathBuf, Vec<u8>)> = Vec::new();
    for f in files_below(dir) {
        let bytes = std::fs::read(&f).unwrap();
        if parse(&f, &bytes).is_some() {
            // The seeds themselves parse.
            assert_eq!(parse(&f, &bytes), Some(true), "{}", f.display());
            // One file per parser kind and layout is enough.
            let key = |p: &Path| {
                let n = p.file_name().unwrap().to_str().unwrap();
                let kind = if n.ends_with("_cam.txt") { "_cam.txt" } else { n };
                let kind = if p.parent().unwrap().ends_with("pose") { "pose" } else { kind };
                let kind = if p.parent().unwrap().ends_with("intrinsics") { "k" } else { kind };
                kind.to_string()
            };
            if !seeds.iter().any(|(s, _)| key(s) == key(&f)) {
                seeds.push((f, bytes));
            }
        }
    }
    seeds
}

#[test]
fn parsers_never_panic_on_mutated_seeds() {
    let dir = seed_dir("parsers");
    let seeds = parser_seeds(&dir);
    assert!(seeds.len() >= 12, "{} seed files", seeds.len());
    let tried = AtomicUsize::new(0);
    let accepted = AtomicUsize::new(0);
    let n = cases();
    // Each case mutates every seed (jgz files both as bytes and inside the gzip stream).
    runner(n)
        .run(&proptest::collection::vec(mutation(), 2), |ms| {
            for (path, bytes) in &seeds {
                let mutated = apply(bytes, &ms[0]);
                let mut ok = parse(path, &mutated).unwrap();
                if path.extension().is_some_and(|e| e == "jgz") {
                    let inner = apply(&gunzip(bytes), &ms[1]);
                    ok &= parse(path, &gzip(&inner)).unwrap();
                }
                tried.fetch_add(1, Ordering::Relaxed);
                accepted.fetch_add(ok as usize, Ordering::Relaxed);
            }
            Ok(())
        })
        .unwrap();
    std::fs::remove_dir_all(&dir).ok();
    println!(
        "fuzz parsers: {} cases ({} mutated files over {} seeds), {} still parsed",
        n,
        tried.load(Ordering::Relaxed),
        seeds.len(),
        accepted.load(Ordering::Relaxed)
    );
}

fn copy_dir(from: &Path, to: &Path) {
    for f in files_below(from) {
        let dest = to.join(f.strip_prefix(from).unwrap());
        std::fs::create_dir_all(dest.parent().unwrap()).unwrap();
        std::fs::copy(&f, dest).unwrap();
    }
}

/// Mutates one file (or removes it) of a layout and opens it; every layout in turn.
#[test]
fn loaders_never_panic_on_mutated_layouts() {
    let n = (cases() / 8).max(16);
    let work = std::env::temp_dir().join(format!("sos-fuzz-work-{}", std::process::id()));
    let mut summary = Vec::new();
    let seeds = seed_dir("loaders");
    for f in Format::ALL {
        let seed = seeds.join(f.name());
        f.open_raw(&seed, None).unwrap();
        let files = files_below(&seed);
        let (tried, failed) = (AtomicUsize::new(0), AtomicUsize::new(0));
        runner(n)
            .run(&(0..files.len(), mutation(), any::<bool>()), |(k, m, remove)| {
                let dir = work.join(f.name());
                std::fs::remove_dir_all(&dir).ok();
                copy_dir(&seed, &dir);
                let target = dir.join(files[k].strip_prefix(&seed).unwrap());
                if remove && matches!(m, Mutation::Empty) {
                    std::fs::remove_file(&target).unwrap();
                } else {
                    let bytes = std::fs::read(&target).unwrap();
                    std::fs::write(&target, apply(&bytes, &m)).unwrap();
                }
                let result = f.open_raw(&dir, None);
                tried.fetch_add(1, Ordering::Relaxed);
                if let Err(e) = result {
                    failed.fetch_add(1, Ordering::Relaxed);
                    // Typed errors name a file or folder of the layout.
                    let msg = e.to_string();
                    prop_assert!(msg.contains(&*dir.to_string_lossy()), "{msg}");
                }
                Ok(())
            })
            .unwrap();
        summary.push(format!(
            "{}: {} cases, {} errors",
            f.name(),
            tried.load(Ordering::Relaxed),
            failed.load(Ordering::Relaxed)
        ));
    }
    std::fs::remove_dir_all(&work).ok();
    std::fs::remove_dir_all(&seeds).ok();
    println!("fuzz loaders: {}", summary.join("; "));
}
