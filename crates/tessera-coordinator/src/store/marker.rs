//! The commit marker: a small file next to the database that records how far the
//! database had got when its last acknowledged commit returned (docs/store.md).
//!
//! SQLite keeps recent commits in the `-wal` file until a checkpoint copies them into
//! the database. If that file is deleted or damaged, SQLite opens the database without
//! complaint and the commits are simply gone: jobs answered 201 vanish, a done job is
//! running again, and job ids are issued a second time. The marker makes that loss
//! visible. Every commit that an answer depends on (a new job, a job's state change, a
//! stored scene, a reservation of lease ids) increments the database's commit generation
//! in the same transaction; after the commit, and before the caller is answered, the
//! marker is replaced with the new generation, the highest job id ever issued and the
//! lease-id high-water mark, and fsynced.
//!
//! At open the database must not be *behind* its marker. A crash between the commit and
//! the marker write leaves the database one generation ahead, which is fine; only a
//! database older than what was acknowledged is refused.
//!
//! The generation is kept in two files that no single deletion removes together: the
//! marker, and the main database file (a start copies the WAL into it once it has
//! written its first marker). A database whose generation is above 0 was opened by a
//! coordinator that wrote a marker, so a missing marker means it was deleted, perhaps
//! with the `-wal` file and the commits in it, and such a store is refused as well
//! ([`StoreError::MarkerMissing`](super::StoreError::MarkerMissing)).
//!
//! Format (text, one field per line, so an operator can read it; `lease_high_water` is
//! absent from markers of older builds and then reads as 0):
//!
//! ```text
//! tessera commit marker 1
//! generation 42
//! max_job_id 17
//! lease_high_water 4096
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
    /// The lease-id high-water mark: fencing tokens up to it may have been issued.
    pub lease_high_water: u64,
}

impl CommitMark {
    /// Whether `self` (the database) is behind `marker`: it lacks acknowledged commits or
    /// would issue a job id or a lease id again.
    pub fn is_behind(&self, marker: &CommitMark) -> bool {
        self.generation < marker.generation
            || self.max_job_id < marker.max_job_id
            || self.lease_high_water < marker.lease_high_water
    }
}

impl std::fmt::Display for CommitMark {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "commit generation {}, job ids up to {}, lease ids up to {}",
            self.generation, self.max_job_id, self.lease_high_water
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
    let lines: Vec<&str> = text.lines().collect();
    if lines.first() != Some(&HEADER) {
        return Err(format!("{} does not start with {HEADER:?}", path.display()));
    }
    let field = |i: usize, name: &str| -> Result<u64, String> {
        lines
            .get(i)
            .and_then(|l| l.strip_prefix(name))
            .and_then(|v| v.strip_prefix(' '))
            .and_then(|v| v.trim().parse().ok())
            .ok_or_else(|| format!("{}: expected a line `{name} N`", path.display()))
    };
    Ok(Some(CommitMark {
        generation: field(1, "generation")?,
        max_job_id: field(2, "max_job_id")?,
        // Markers of builds before the lease high-water mark end after max_job_id.
        lease_high_water: match lines.get(3) {
            None => 0,
            Some(_) => field(3, "lease_high_water")?,
        },
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
        "{HEADER}\ngeneration {}\nmax_job_id {}\nlease_high_water {}\n",
        mark.generation, mark.max_job_id, mark.lease_high_water
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
            lease_high_water: 1024,
        };
        write_marker(dir.path(), m).unwrap();
        assert_eq!(read_marker(dir.path()), Ok(Some(m)));
        std::fs::write(marker_path(dir.path()), "garbage").unwrap();
        assert!(read_marker(dir.path())
            .unwrap_err()
            .contains("does not start"));
        std::fs::write(marker_path(dir.path()), format!("{HEADER}\ngeneration x\n")).unwrap();
        assert!(read_marker(dir.path()).unwrap_err().contains("generation"));
        // A marker of an older build, without the lease line.
        std::fs::write(
            marker_path(dir.path()),
            format!("{HEADER}\ngeneration 42\nmax_job_id 17\n"),
        )
        .unwrap();
        assert_eq!(
            read_marker(dir.path()),
            Ok(Some(CommitMark {
                lease_high_water: 0,
                ..m
            }))
        );
        let db = CommitMark {
            generation: 43,
            max_job_id: 16,
            lease_high_water: 1024,
        };
        assert!(db.is_behind(&m), "a job id could be issued again");
        assert!(!CommitMark {
            max_job_id: 17,
            ..db
        }
        .is_behind(&m));
        assert!(
            CommitMark {
                max_job_id: 17,
                lease_high_water: 1000,
                ..db
            }
            .is_behind(&m),
            "a fencing token could be issued again"
        );
    }
}
