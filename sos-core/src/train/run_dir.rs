//! A run's folder, claimed before any work starts: created (or found) and checked writable, so
//! a bad `output_dir` fails at once rather than at the first checkpoint minutes later; locked
//! by a `run.lock` file naming this process, so a second run on the same folder is refused
//! instead of both overwriting each other's checkpoint; and cleared of a temporary checkpoint
//! a killed run left behind. The lock is released when the claim is dropped; a lock whose
//! process is gone (a run killed by SIGKILL) is taken over.

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::error::RunError;
use crate::train::checkpoint::TEMPORARY_EXTENSION;

/// Name of the lock file inside a run folder.
pub const LOCK_FILE: &str = "run.lock";

/// A claimed run folder; dropping it releases the lock.
#[derive(Debug)]
pub struct RunDirClaim {
    lock: PathBuf,
}

impl RunDirClaim {
    /// Claims `dir` for this process (see the module documentation). `config_key` names the
    /// setting that chose the folder, for messages.
    pub fn claim(dir: &Path, config_key: &str) -> Result<RunDirClaim, RunError> {
        let fail = |message: String| RunError::RunDir { path: dir.to_path_buf(), message };
        if dir.exists() && !dir.is_dir() {
            return Err(fail(format!("it is a file, not a folder; change `{config_key}`")));
        }
        std::fs::create_dir_all(dir)
            .map_err(|e| fail(format!("cannot be created ({e}); change `{config_key}` or its permissions")))?;
        let lock = dir.join(LOCK_FILE);
        for _ in 0..2 {
            match std::fs::OpenOptions::new().write(true).create_new(true).open(&lock) {
                Ok(mut f) => {
                    f.write_all(std::process::id().to_string().as_bytes()).and_then(|()| f.sync_all()).map_err(
                        |e| fail(format!("is not writable ({e}); change `{config_key}` or its permissions")),
                    )?;
                    remove_leftovers(dir);
                    return Ok(RunDirClaim { lock });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    let owner = std::fs::read_to_string(&lock).ok().and_then(|s| s.trim().parse::<u32>().ok());
                    match owner {
                        Some(pid) if process_alive(pid) && pid != std::process::id() => {
                            return Err(fail(format!(
                                "another run (process {pid}) is using it; wait for it to finish, stop it, or give \
                                 this run another `name`"
                            )))
                        }
                        // The process that locked it is gone: a killed run. Take the folder over.
                        _ => {
                            std::fs::remove_file(&lock).map_err(|e| fail(format!("its stale {LOCK_FILE}: {e}")))?;
                        }
                    }
                }
                Err(e) => {
                    return Err(fail(format!("is not writable ({e}); change `{config_key}` or its permissions")));
                }
            }
        }
        Err(fail(format!("its {LOCK_FILE} keeps reappearing: another run is starting on it")))
    }

    /// The lock file held.
    pub fn lock_path(&self) -> &Path {
        &self.lock
    }
}

impl Drop for RunDirClaim {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.lock);
    }
}

/// Whether process `pid` still runs. Where the system offers no process table (`/proc`), every
/// lock counts as held: the message tells the user which file to delete.
fn process_alive(pid: u32) -> bool {
    let proc = Path::new("/proc");
    !proc.is_dir() || proc.join(pid.to_string()).exists()
}

/// Removes the temporary files an interrupted checkpoint write leaves (`*.tmp`).
fn remove_leftovers(dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for entry in entries.flatten() {
        let path = entry.path();
        if path.is_file() && path.extension().is_some_and(|e| e == TEMPORARY_EXTENSION) {
            let _ = std::fs::remove_file(&path);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("sos-run-dir-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn claims_creates_locks_and_releases() {
        let dir = temp("claim").join("nested/run");
        let claim = RunDirClaim::claim(&dir, "output_dir").unwrap();
        let pid: u32 = std::fs::read_to_string(claim.lock_path()).unwrap().parse().unwrap();
        assert_eq!(pid, std::process::id());
        drop(claim);
        assert!(!dir.join(LOCK_FILE).exists());
        std::fs::remove_dir_all(temp("claim")).ok();
    }

    #[test]
    fn a_live_owner_is_refused_by_pid_and_a_dead_one_is_taken_over() {
        let dir = temp("owner");
        std::fs::create_dir_all(&dir).unwrap();
        // PID 1 always runs (where there is a /proc at all).
        std::fs::write(dir.join(LOCK_FILE), "1").unwrap();
        let err = RunDirClaim::claim(&dir, "output_dir").unwrap_err().to_string();
        assert!(err.contains("process 1") && err.contains(&dir.display().to_string()), "{err}");
        // A PID above the kernel's limit cannot run: a stale lock.
        if Path::new("/proc").is_dir() {
            std::fs::write(dir.join(LOCK_FILE), "4294967295").unwrap();
            std::fs::write(dir.join("checkpoint.tmp"), "half").unwrap();
            let claim = RunDirClaim::claim(&dir, "output_dir").unwrap();
            assert!(!dir.join("checkpoint.tmp").exists(), "the killed run's temporary checkpoint is removed");
            drop(claim);
        }
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn a_file_in_the_way_is_named() {
        let base = temp("file");
        std::fs::create_dir_all(&base).unwrap();
        let file = base.join("run");
        std::fs::write(&file, "x").unwrap();
        let err = RunDirClaim::claim(&file, "output_dir").unwrap_err().to_string();
        assert!(err.contains("is a file") && err.contains("output_dir"), "{err}");
        std::fs::remove_dir_all(base).ok();
    }
}
