//! A run is reproducible: the same config and seed give the same field and head, bit for bit,
//! whatever the number of threads. Stage 2 is chaotic (a last-bit difference in one step's
//! gradient grows into a visibly different mask), so parallel sums must not depend on how the
//! work was scheduled.

mod common;

use common::tiny_session;
use sos_core::segment::train::{train_segmentation, Segmenter};
use sos_core::train::photometric::train_photometric;
use sos_core::train::Session;
// Links every plugin (datasets, extractors, losses) so the config kinds resolve.
use sos_plugins as _;

fn session(field: &str, threads: usize) -> Session {
    let keys = if field == "nerf" {
        "depth = 2\nwidth = 32\nskip = 0\nview_width = 8\ncoarse_samples = 8\nfine_samples = 16"
    } else {
        "resolution = [16, 16, 16]\ninitial_resolution = [16, 16, 16]\nupsample_at = []"
    };
    tiny_session(field, "object-centric", keys, 4, &format!("reproducible-{threads}"))
}

/// Both stages in a pool of `threads`: the field's state and the head's bytes.
fn run(field: &str, threads: usize) -> (Vec<u8>, Vec<u8>) {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
    pool.install(|| {
        let mut s = session(field, threads);
        train_photometric(&mut s).unwrap();
        let mut seg = Segmenter::build(&s).unwrap();
        train_segmentation(&mut s, &mut seg).unwrap();
        std::fs::remove_dir_all(&s.run_dir).ok();
        (s.field.save_state(), seg.head.to_bytes())
    })
}

#[test]
fn same_bits_on_any_thread_count() {
    for field in ["voxel-grid", "nerf"] {
        let one = run(field, 1);
        for threads in [2, 3] {
            let other = run(field, threads);
            assert!(other.0 == one.0, "{field}: the field after stage 1 differs with {threads} threads");
            assert!(other.1 == one.1, "{field}: the head after stage 2 differs with {threads} threads");
        }
    }
}
