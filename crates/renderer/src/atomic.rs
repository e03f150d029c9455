//! Atomic file writes: a finished file appears whole under its name, or not at all.
//!
//! Each write gets a temporary file of its own beside the destination (same folder, so the rename
//! is atomic): `.{name}.tmp-{pid}-{n}` with `n` from a process-wide counter and `name` cut to its
//! first 64 bytes (so any legal destination name, up to 255 bytes, has a legal temporary name, as
//! in lp3d's Python writer `lp3d/atomic.py`), created exclusively
//! (`create_new`, retried on a clash with a stale file), so threads and processes saving one path
//! at once never share a temporary file. It is created with mode 0666 less the umask, like any
//! new file (the permissions lp3d's Python writers give too), synced, then renamed; on every
//! failure it is removed and an existing destination is untouched.

use std::fs::{File, OpenOptions};
use std::io;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use crate::error::{Error, Result};

/// Sequence number of the next temporary name in this process.
static SEQUENCE: AtomicU64 = AtomicU64::new(0);
/// Names tried before giving up (a clash means a stale temporary file, or a reused pid).
const ATTEMPTS: u32 = 100;
/// Bytes of the destination's name kept in a temporary name (NAME_MAX is 255).
const NAME_BYTES: usize = 64;

/// The longest start of `name` of at most `limit` bytes that ends on a whole character.
fn name_prefix(name: &str, limit: usize) -> &str {
    let end = name.char_indices().map(|(i, c)| i + c.len_utf8()).take_while(|&end| end <= limit).last();
    &name[..end.unwrap_or(0)]
}

fn io_error(path: &Path, e: io::Error) -> Error {
    Error::io(path, e)
}

/// A complete, synced temporary file waiting to be renamed onto its destination. Dropped without
/// [`Staged::publish`] (an error, a panic), it deletes the temporary file.
#[derive(Debug)]
pub struct Staged {
    tmp: PathBuf,
    dest: PathBuf,
    published: bool,
}

impl Staged {
    /// The destination this file will be renamed onto.
    pub fn dest(&self) -> &Path {
        &self.dest
    }

    /// Renames the temporary file onto its destination (the temporary file is removed on failure).
    pub fn publish(mut self) -> Result<()> {
        std::fs::rename(&self.tmp, &self.dest).map_err(|e| io_error(&self.dest, e))?;
        self.published = true;
        Ok(())
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        if !self.published {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// Creates a new temporary file beside `path`, unique to this call, and its name.
fn create_temp(path: &Path) -> Result<(File, PathBuf)> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path
        .file_name()
        .ok_or_else(|| Error::io_kind(path, io::ErrorKind::InvalidInput, "not a file path"))?;
    let name = name.to_string_lossy();
    let name = name_prefix(&name, NAME_BYTES);
    for _ in 0..ATTEMPTS {
        let n = SEQUENCE.fetch_add(1, Ordering::Relaxed);
        let tmp = dir.join(format!(".{name}.tmp-{}-{n}", std::process::id()));
        // `create_new` is O_CREAT | O_EXCL: never opens (and truncates) another writer's file.
        match OpenOptions::new().write(true).create_new(true).open(&tmp) {
            Ok(file) => return Ok((file, tmp)),
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(io_error(path, e)),
        }
    }
    Err(Error::io_kind(
        path,
        io::ErrorKind::AlreadyExists,
        format!("no free temporary name beside it after {ATTEMPTS} tries"),
    ))
}

/// Runs `write` on a new temporary sibling of `path` and syncs it, ready for [`Staged::publish`].
pub fn stage(path: &Path, write: impl FnOnce(&mut File) -> io::Result<()>) -> Result<Staged> {
    let (mut file, tmp) = create_temp(path)?;
    // From here on the guard removes the temporary file on every failure.
    let staged = Staged { tmp, dest: path.into(), published: false };
    write(&mut file).and_then(|()| file.sync_all()).map_err(|e| io_error(path, e))?;
    Ok(staged)
}

/// Publishes staged files together, in order. If a rename fails, the destinations already renamed
/// by this call are removed again (an incomplete set is worse than none) and the remaining
/// temporary files are deleted.
pub fn publish_all(files: Vec<Staged>) -> Result<()> {
    let mut done: Vec<PathBuf> = Vec::new();
    for staged in files {
        let dest = staged.dest.clone();
        if let Err(e) = staged.publish() {
            for published in &done {
                let _ = std::fs::remove_file(published);
            }
            return Err(e); // the rest of `files` is dropped here: their temporary files go too
        }
        done.push(dest);
    }
    Ok(())
}

/// Runs `write` on a new temporary sibling of `path`, syncs it, then renames it into place.
pub fn write_atomically(path: &Path, write: impl FnOnce(&mut File) -> io::Result<()>) -> Result<()> {
    stage(path, write)?.publish()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("lp3d-atomic-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn entries(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn concurrent_writers_each_publish_a_whole_file() {
        let dir = temp_dir("threads");
        let path = dir.join("t.bin");
        std::thread::scope(|s| {
            for t in 0..4u8 {
                let path = &path;
                s.spawn(move || {
                    for _ in 0..50 {
                        // Written in pieces, so a shared temporary file would interleave writers.
                        write_atomically(path, |f| {
                            for _ in 0..64 {
                                f.write_all(&[t; 1024])?;
                            }
                            Ok(())
                        })
                        .unwrap();
                        let bytes = std::fs::read(path).unwrap();
                        assert_eq!(bytes.len(), 64 * 1024);
                        assert!(bytes.iter().all(|&b| b == bytes[0]), "a mix of writers");
                    }
                });
            }
        });
        assert_eq!(entries(&dir), ["t.bin"]);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn failures_leave_nothing_behind() {
        let dir = temp_dir("fail");
        let path = dir.join("t.bin");
        std::fs::write(&path, b"old").unwrap();
        let err = write_atomically(&path, |_| Err(io::Error::other("disk full (simulated)"))).unwrap_err();
        assert!(err.to_string().contains("disk full"), "{err}");
        assert_eq!(std::fs::read(&path).unwrap(), b"old");
        // A rename that fails (the destination is a non-empty folder) removes its temporary file.
        let folder = dir.join("sub");
        std::fs::create_dir_all(folder.join("x")).unwrap();
        assert!(write_atomically(&folder, |f| f.write_all(b"new")).is_err());
        assert_eq!(entries(&dir), ["sub", "t.bin"]);
        // A set whose second rename fails removes the first destination again.
        let first = stage(&dir.join("a.png"), |f| f.write_all(b"a")).unwrap();
        let second = stage(&folder, |f| f.write_all(b"b")).unwrap();
        assert!(publish_all(vec![first, second]).is_err());
        assert_eq!(entries(&dir), ["sub", "t.bin"]);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_destination_name_of_any_legal_length_can_be_written() {
        let dir = temp_dir("long");
        // 255 bytes, the file-system limit: "é" is 2 bytes, so the cut must fall between characters.
        let name = format!("{}{}.npz", "é".repeat(100), "a".repeat(51));
        assert_eq!(name.len(), 255);
        let path = dir.join(&name);
        write_atomically(&path, |f| f.write_all(b"long")).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"long");
        assert_eq!(entries(&dir), [name]);
        assert_eq!(name_prefix("aé", 2), "a");
        assert_eq!(name_prefix("aé", 3), "aé");
        assert_eq!(name_prefix("é", 1), "");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_stale_temporary_name_is_skipped() {
        let dir = temp_dir("stale");
        let path = dir.join("t.bin");
        let next = SEQUENCE.load(Ordering::Relaxed);
        // Squat on the next few names this process would pick (a stale file from a dead process).
        for n in next..next + 8 {
            std::fs::write(dir.join(format!(".t.bin.tmp-{}-{n}", std::process::id())), b"stale").unwrap();
        }
        write_atomically(&path, |f| f.write_all(b"fresh")).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"fresh");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
