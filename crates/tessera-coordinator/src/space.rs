//! Free space in the data directory (docs/store.md, "When the disk is full"): whether it
//! is full, probed by writing. A probe writes, syncs and removes a file of
//! [`PROBE_BYTES`]; it is how a coordinator that started on a full disk, or whose writes
//! failed for want of space, learns that space was freed before it opens its store again.
//! Writing is the test because it is what the store needs: a free-block count would not
//! see a quota, a full inode table or a filesystem that reserves blocks for root.

use std::io::Write;
use std::path::{Path, PathBuf};

/// Bytes a probe writes: room for the store's open (its write probe, the WAL's first
/// frames and its shared-memory file) with some to spare.
pub const PROBE_BYTES: usize = 1 << 20;

/// Name of the probe file in the data directory (removed after each probe).
pub const PROBE_FILE: &str = "tessera.space-probe";

/// Whether `err` says the disk (or a disk quota) is full.
pub fn is_no_space(err: &std::io::Error) -> bool {
    // ENOSPC and EDQUOT on Linux, the two `StorageFull` stands for.
    err.kind() == std::io::ErrorKind::StorageFull
        || matches!(err.raw_os_error(), Some(28) | Some(122))
}

/// Writes, syncs and removes a [`PROBE_BYTES`] file in `dir` (off the async runtime).
pub async fn probe(dir: &Path) -> std::io::Result<()> {
    let path: PathBuf = dir.join(PROBE_FILE);
    let r = tokio::task::spawn_blocking(move || {
        let result = (|| {
            let mut f = std::fs::File::create(&path)?;
            f.write_all(&vec![0u8; PROBE_BYTES])?;
            f.sync_all()
        })();
        let _ = std::fs::remove_file(&path);
        result
    })
    .await;
    r.unwrap_or_else(|e| Err(std::io::Error::other(e.to_string())))
}

/// Whether the disk of `dir` is full: a probe fails for want of space.
pub async fn is_full(dir: &Path) -> bool {
    matches!(probe(dir).await, Err(e) if is_no_space(&e))
}
