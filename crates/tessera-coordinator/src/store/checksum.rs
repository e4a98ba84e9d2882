//! Row checksums (docs/store.md, "Checksums"): a SHA-256 over every column an image
//! depends on, written with the row and verified whenever the row is read, so a byte
//! changed on disk (a filesystem or device fault, an edit by hand) is an error naming the
//! row instead of a wrong image.
//!
//! SQLite's page checks (`quick_check`, `integrity_check`) and PostgreSQL's page
//! checksums only see the structure of pages: a changed byte inside a blob or a text
//! column passes both. So each row of `jobs`, `tiles` and `scenes` carries its own
//! `checksum` column (schema version 7 on SQLite, 6 on PostgreSQL), 32 bytes.
//!
//! A checksum covers the row's key as well as its values (a row that moved to another
//! key fails too) and each field with its length (no two rows hash alike by shifting
//! bytes from one field to the next); a domain tag per table keeps the three kinds apart.

use sha2::{Digest, Sha256};
use tessera_api::FrameRange;
use tessera_farm::FramePlan;

/// Bytes of a stored checksum.
pub(super) const CHECKSUM_BYTES: usize = 32;

/// An incremental checksum of length-prefixed fields.
struct Sum(Sha256);

impl Sum {
    fn new(tag: &str) -> Self {
        let mut s = Self(Sha256::new());
        s.bytes(tag.as_bytes());
        s
    }

    fn bytes(&mut self, b: &[u8]) -> &mut Self {
        self.0.update((b.len() as u64).to_le_bytes());
        self.0.update(b);
        self
    }

    fn int(&mut self, v: i64) -> &mut Self {
        self.bytes(&v.to_le_bytes())
    }

    /// An optional field: absent and present-but-empty hash apart.
    fn opt(&mut self, b: Option<&[u8]>) -> &mut Self {
        match b {
            None => self.0.update([0u8]),
            Some(b) => {
                self.0.update([1u8]);
                self.bytes(b);
            }
        }
        self
    }

    fn finish(&mut self) -> Vec<u8> {
        std::mem::take(&mut self.0).finalize().to_vec()
    }
}

/// The immutable columns of a `jobs` row: what the job renders (scene, settings, plan,
/// frames, units) and what it was accepted as. The state, error, times and the
/// crash-loop counters change as the job runs and are not covered.
#[derive(Debug, Clone, Copy)]
pub(super) struct JobSum<'a> {
    pub id: i64,
    pub idempotency_key: Option<&'a str>,
    pub name: Option<&'a str>,
    pub scene_ref: &'a str,
    pub settings_json: &'a str,
    pub plan: FramePlan,
    pub frames: FrameRange,
    pub passes_per_unit: u32,
    pub priority: i32,
    pub created_unix_ms: i64,
    pub render_plan_json: Option<&'a str>,
    pub error_estimate_caveat: Option<&'a str>,
}

impl JobSum<'_> {
    /// The checksum of these columns.
    pub fn checksum(&self) -> Vec<u8> {
        let p = self.plan;
        let mut s = Sum::new("tessera jobs row 1");
        s.int(self.id)
            .opt(self.idempotency_key.map(str::as_bytes))
            .opt(self.name.map(str::as_bytes))
            .bytes(self.scene_ref.as_bytes())
            .bytes(self.settings_json.as_bytes());
        for v in [p.width, p.height, p.tile_size, p.samples_per_pass, p.passes] {
            s.int(i64::from(v));
        }
        s.int(i64::from(self.frames.start))
            .int(i64::from(self.frames.end))
            .int(i64::from(self.passes_per_unit))
            .int(i64::from(self.priority))
            .int(self.created_unix_ms)
            .opt(self.render_plan_json.map(str::as_bytes))
            .opt(self.error_estimate_caveat.map(str::as_bytes));
        s.finish()
    }
}

impl<'a> From<&'a super::JobRecord> for JobSum<'a> {
    fn from(r: &'a super::JobRecord) -> Self {
        Self {
            id: i64::try_from(r.id).unwrap_or(i64::MAX),
            idempotency_key: r.idempotency_key.as_deref(),
            name: r.name.as_deref(),
            scene_ref: &r.scene_ref,
            settings_json: &r.settings_json,
            plan: r.plan,
            frames: r.frames,
            passes_per_unit: r.passes_per_unit,
            priority: r.priority,
            created_unix_ms: i64::try_from(r.created_unix_ms).unwrap_or(i64::MAX),
            render_plan_json: r.render_plan_json.as_deref(),
            error_estimate_caveat: r.error_estimate_caveat.as_deref(),
        }
    }
}

/// The columns of a `tiles` row, as stored (the encoded blobs).
#[derive(Debug, Clone, Copy)]
pub(super) struct TileSum<'a> {
    pub job: i64,
    pub frame: i64,
    pub tile: i64,
    pub merged_passes: i64,
    pub rejected_samples: i64,
    pub stats: &'a [u8],
    pub units: &'a [u8],
    pub adaptive: Option<&'a [u8]>,
}

impl TileSum<'_> {
    /// The checksum of these columns.
    pub fn checksum(&self) -> Vec<u8> {
        Sum::new("tessera tiles row 1")
            .int(self.job)
            .int(self.frame)
            .int(self.tile)
            .int(self.merged_passes)
            .int(self.rejected_samples)
            .bytes(self.stats)
            .bytes(self.units)
            .opt(self.adaptive)
            .finish()
    }
}

/// The checksum of a `scenes` row: its key (the content hash the caller computed) and
/// its bytes.
pub(super) fn scene_checksum(hash: &str, data: &[u8]) -> Vec<u8> {
    Sum::new("tessera scenes row 1")
        .bytes(hash.as_bytes())
        .bytes(data)
        .finish()
}

/// `Ok` if `stored` is `expected`; otherwise why not, for a message that names the row.
pub(super) fn verify(stored: Option<&[u8]>, expected: &[u8]) -> Result<(), String> {
    match stored {
        Some(s) if s == expected => Ok(()),
        Some(s) if s.len() != CHECKSUM_BYTES => Err(format!(
            "its checksum is {} bytes, not {CHECKSUM_BYTES}: the row was damaged",
            s.len()
        )),
        Some(_) => Err(
            "the row does not match its checksum: it changed after it was \
                        written (a disk or filesystem fault, or an edit by hand)"
                .into(),
        ),
        None => Err(
            "the row has no checksum (every row has one since schema version 7; \
                     PostgreSQL 6): the row was damaged or written behind the store"
                .into(),
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_do_not_run_into_each_other() {
        let t = |stats: &'static [u8], units: &'static [u8], adaptive| TileSum {
            job: 1,
            frame: 0,
            tile: 2,
            merged_passes: 3,
            rejected_samples: 0,
            stats,
            units,
            adaptive,
        };
        let a = t(b"ab", b"c", None).checksum();
        assert_eq!(a.len(), CHECKSUM_BYTES);
        assert_ne!(a, t(b"a", b"bc", None).checksum());
        assert_ne!(a, t(b"ab", b"c", Some(b"")).checksum());
        assert_eq!(verify(Some(&a), &a), Ok(()));
        let mut flipped = a.clone();
        flipped[5] ^= 1;
        assert!(verify(Some(&flipped), &a).unwrap_err().contains("checksum"));
        assert!(verify(None, &a).unwrap_err().contains("no checksum"));
        assert_ne!(scene_checksum("h", b"x"), scene_checksum("hx", b""));
    }
}
