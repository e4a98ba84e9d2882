//! The commit marker: a small file next to the database that records how far the
//! database had got when its last acknowledged commit returned (docs/store.md).
//!
//! SQLite keeps recent commits in the `-wal` file until a checkpoint copies them into
//! the database. If that file is deleted or damaged, SQLite opens the database without
//! complaint and the commits are simply gone: jobs answered 201 vanish, a done job is
//! running again, and job ids are issued a second time. The marker makes that loss
//! visible. Every commit that an answer depends on (a new job, a job's state change, a
//! stored scene) increments the database's commit generation in the same transaction;
//! after the commit, and before the caller is answered, the marker is replaced with the
//! new generation and the highest job id ever issued, and fsynced.
//!
//! At open the database must not be *behind* its marker. A crash between the commit and
//! the marker write leaves the database one generation ahead, which is fine; only a
//! database older than what was acknowledged is refused.
//!
//! Format (text, one field per line, so an operator can read it):
//!
//! ```text
//! tessera commit marker 1
//! generation 42
//! max_job_id 17
//! ```

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Name of the marker file inside the data directory.
pub const MARKER_FILE: &str = "tessera.commit-marker";

const HEADER: &str = "tessera commit marker 1";

/// What the marker records (and what the database is compared with).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash)]
pub struct CommitMark {
    /// The commit generation: increases with every acknowledged commit.
    pub generation: u64,
    /// The highest job id ever issued.
    pub max_job_id: u64,
}

impl CommitMark {
    /// Whether `self` (the database) is behind `marker`: it lacks acknowledged commits or
    /// would issue a job id again.
    pub fn is_behind(&self, marker: &CommitMark) -> bool {
        self.generation < marker.generation || self.max_job_id < marker.max_job_id
    }
}

impl std::fmt::Display for CommitMark {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "commit generation {}, job ids up to {}",
            self.generation, self.max_job_id
        )
    }
}

/// The marker's path in a data directory.
pub fn marker_path(dir: &Path) -> PathBuf {
    dir.join(MARKER_FILE)
}

/// Reads the marker of `dir`: `Ok(None)` if there is none, `Err` naming the problem if
/// it cannot be read or parsed.
pub fn read_marker(dir: &Path) -> Result<Option<CommitMark>, String> {
    let path = marker_path(dir);
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(format!("cannot read {}: {e}", path.display())),
    };
    let mut lines = text.lines();
    if lines.next() != Some(HEADER) {
        return Err(format!("{} does not start with {HEADER:?}", path.display()));
    }
    let mut field = |name: &str| -> Result<u64, String> {
        lines
            .next()
            .and_then(|l| l.strip_prefix(name))
            .and_then(|v| v.strip_prefix(' '))
            .and_then(|v| v.trim().parse().ok())
            .ok_or_else(|| format!("{}: expected a line `{name} N`", path.display()))
    };
    Ok(Some(CommitMark {
        generation: field("generation")?,
        max_job_id: field("max_job_id")?,
    }))
}

/// Replaces the marker of `dir` atomically and durably: written to a temporary file,
/// fsynced, renamed over the marker, and the directory fsynced, so after a crash the
/// marker is either the old one or the new one.
pub fn write_marker(dir: &Path, mark: CommitMark) -> std::io::Result<()> {
    let path = marker_path(dir);
    let tmp = dir.join(format!("{MARKER_FILE}.tmp"));
    let mut f = OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .open(&tmp)?;
    write!(
        f,
        "{HEADER}\ngeneration {}\nmax_job_id {}\n",
        mark.generation, mark.max_job_id
    )?;
    f.sync_all()?;
    drop(f);
    std::fs::rename(&tmp, &path)?;
    // The rename is durable only once the directory entry is.
    File::open(dir)?.sync_all()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_refusals() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(read_marker(dir.path()), Ok(None));
        let m = CommitMark {
            generation: 42,
            max_job_id: 17,
        };
        write_marker(dir.path(), m).unwrap();
        assert_eq!(read_marker(dir.path()), Ok(Some(m)));
        std::fs::write(marker_path(dir.path()), "garbage").unwrap();
        assert!(read_marker(dir.path())
            .unwrap_err()
            .contains("does not start"));
        std::fs::write(marker_path(dir.path()), format!("{HEADER}\ngeneration x\n")).unwrap();
        assert!(read_marker(dir.path()).unwrap_err().contains("generation"));
        let db = CommitMark {
            generation: 43,
            max_job_id: 16,
        };
        assert!(db.is_behind(&m), "a job id could be issued again");
        assert!(!CommitMark {
            max_job_id: 17,
            ..db
        }
        .is_behind(&m));
    }
}
