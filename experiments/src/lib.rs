//! What the studies share: their command line, and opening a finished run with its head.

use sos_core::segment::head::SegHead;
use sos_core::segment::store::load_with_head;
use sos_core::train::Session;

/// The command-line arguments; with fewer than `required`, prints `usage` and exits with
/// code 2.
pub fn args_or_usage(required: usize, usage: &str) -> Vec<String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < required {
        eprintln!("usage: {usage}");
        std::process::exit(2);
    }
    args
}

/// The run of `config` with the field and segmentation head of `checkpoint`.
pub fn open_with_head(config: &str, checkpoint: &str) -> (Session, SegHead) {
    let mut session = Session::open(config.as_ref()).expect("config opens");
    let (loaded, _) = load_with_head(&mut session, Some(checkpoint.as_ref())).expect("checkpoint loads");
    let head = loaded.expect("the checkpoint holds a segmentation head").head;
    (session, head)
}
