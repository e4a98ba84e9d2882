//! What the coordinator does not take on a worker's word (ARCHITECTURE.md §6, "Untrusted
//! workers"): who is calling (a session secret issued at registration), which lease a
//! result answers (a seal over the lease), and how much of the store and the log one
//! worker's faults may fill.
//!
//! - [`new_session`]: 128 random bits from the operating system, in hex, handed to a worker
//!   once (`RegisterResponse.session`) and compared in constant time ([`same_secret`]) on
//!   every later call under its id, so no worker acts under another's id.
//! - [`FenceKey`]: HMAC-SHA256 over (lease id, job, unit, worker name), keyed by a secret
//!   kept in the store ([`crate::store::Store::fence_key`]). A lease id is guessable; its
//!   seal is not, and it names one unit of one job for one worker (by name, so that the
//!   same worker registered again, or a coordinator restarted on the same store, still
//!   recognises it).
//! - [`FaultBudget`]: a worker's fault events are stored and logged at most
//!   [`FAULTS_PER_WINDOW`] per [`FAULT_WINDOW_MS`]; beyond, they are counted only.
//! - [`printable`]: a worker's free text, cut and with control characters escaped, before
//!   it reaches a log line or a job's error.

use ring::hmac;
use ring::rand::{SecureRandom, SystemRandom};
use tessera_farm::{JobId, WorkUnit};

/// Fault events of one worker stored and logged per window; more are only counted.
pub const FAULTS_PER_WINDOW: u32 = 20;
/// The window of [`FAULTS_PER_WINDOW`], ms.
pub const FAULT_WINDOW_MS: u64 = 10_000;

/// Random bytes from the operating system's generator.
///
/// # Panics
///
/// If the operating system has no random source: nothing secure can be issued then.
pub fn random_bytes<const N: usize>() -> [u8; N] {
    let mut b = [0u8; N];
    SystemRandom::new()
        .fill(&mut b)
        .expect("the operating system's random number generator failed");
    b
}

/// A new session secret: 128 random bits as 32 lowercase hex characters.
pub fn new_session() -> String {
    random_bytes::<16>()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Whether `given` is `expected`, compared in time independent of where they differ (a
/// session secret must not be learnt a byte at a time from response times). An empty
/// `expected` matches nothing.
pub fn same_secret(given: &[u8], expected: &[u8]) -> bool {
    if expected.is_empty() || given.len() != expected.len() {
        return false;
    }
    given
        .iter()
        .zip(expected)
        .fold(0u8, |acc, (x, y)| acc | (x ^ y))
        == 0
}

/// The key that seals leases (see the module docs).
#[derive(Clone)]
pub struct FenceKey(hmac::Key);

impl std::fmt::Debug for FenceKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FenceKey(..)")
    }
}

impl FenceKey {
    /// The key of the 32 secret bytes `key`.
    pub fn new(key: &[u8; 32]) -> Self {
        Self(hmac::Key::new(hmac::HMAC_SHA256, key))
    }

    /// The bytes sealed: every field at a fixed width, the name last with its length, so
    /// no two leases share them.
    fn message(lease_id: u64, job: JobId, unit: &WorkUnit, worker_name: &str) -> Vec<u8> {
        let mut m = Vec::with_capacity(64 + worker_name.len());
        m.extend_from_slice(b"tessera.lease.v1");
        m.extend_from_slice(&lease_id.to_le_bytes());
        m.extend_from_slice(&job.to_le_bytes());
        for v in [unit.frame, unit.tile, unit.first_pass, unit.pass_count] {
            m.extend_from_slice(&v.to_le_bytes());
        }
        m.extend_from_slice(&(worker_name.len() as u64).to_le_bytes());
        m.extend_from_slice(worker_name.as_bytes());
        m
    }

    /// The seal of lease `lease_id` of `unit` of `job`, issued to a worker named
    /// `worker_name` (`Lease.fence`).
    pub fn seal(&self, lease_id: u64, job: JobId, unit: &WorkUnit, worker_name: &str) -> Vec<u8> {
        hmac::sign(&self.0, &Self::message(lease_id, job, unit, worker_name))
            .as_ref()
            .to_vec()
    }

    /// Whether `fence` is the seal of exactly that lease, unit, job and worker name
    /// (compared in constant time).
    pub fn verify(
        &self,
        fence: &[u8],
        lease_id: u64,
        job: JobId,
        unit: &WorkUnit,
        worker_name: &str,
    ) -> bool {
        hmac::verify(
            &self.0,
            &Self::message(lease_id, job, unit, worker_name),
            fence,
        )
        .is_ok()
    }
}

/// A worker's allowance of stored and logged fault events (see the module docs).
#[derive(Debug, Clone, Copy, Default)]
pub struct FaultBudget {
    window_start_ms: u64,
    in_window: u32,
    /// Fault events not stored nor logged since the last one that was.
    pub suppressed: u64,
}

impl FaultBudget {
    /// Whether a fault at `now` may be stored and logged; counts it either way.
    pub fn allow(&mut self, now: u64) -> bool {
        if now.saturating_sub(self.window_start_ms) >= FAULT_WINDOW_MS {
            self.window_start_ms = now;
            self.in_window = 0;
        }
        self.in_window = self.in_window.saturating_add(1);
        if self.in_window <= FAULTS_PER_WINDOW {
            true
        } else {
            self.suppressed += 1;
            false
        }
    }

    /// Whether the fault [`FaultBudget::allow`] just refused was the window's first one
    /// refused (said once in the log, then silence until the window ends).
    pub fn first_refused_in_window(&self) -> bool {
        self.in_window == FAULTS_PER_WINDOW + 1
    }
}

/// A worker's free text made safe to log or show: at most `max_chars` characters, every
/// control character (a newline would forge a log line) escaped as `\n`, `\u{1b}`, ...
pub fn printable(text: &str, max_chars: usize) -> String {
    let mut out = String::new();
    for c in text.chars().take(max_chars) {
        if c.is_control() {
            out.extend(c.escape_default());
        } else {
            out.push(c);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sessions_are_random_hex_and_compared_exactly() {
        let (a, b) = (new_session(), new_session());
        assert_eq!(a.len(), 32);
        assert!(a.bytes().all(|c| c.is_ascii_hexdigit()));
        assert_ne!(a, b);
        assert!(same_secret(a.as_bytes(), a.as_bytes()));
        assert!(!same_secret(b.as_bytes(), a.as_bytes()));
        assert!(!same_secret(&a.as_bytes()[..31], a.as_bytes()));
        assert!(!same_secret(b"", b""));
    }

    #[test]
    fn a_seal_names_one_lease_unit_job_and_worker() {
        let key = FenceKey::new(&[7; 32]);
        let unit = WorkUnit {
            frame: 0,
            tile: 3,
            first_pass: 2,
            pass_count: 1,
        };
        let seal = key.seal(42, 5, &unit, "node-a");
        assert_eq!(seal.len(), 32);
        assert!(key.verify(&seal, 42, 5, &unit, "node-a"));
        assert!(!key.verify(&seal, 43, 5, &unit, "node-a"));
        assert!(!key.verify(&seal, 42, 6, &unit, "node-a"));
        let other = WorkUnit { tile: 4, ..unit };
        assert!(!key.verify(&seal, 42, 5, &other, "node-a"));
        assert!(!key.verify(&seal, 42, 5, &unit, "node-b"));
        assert!(!key.verify(&[], 42, 5, &unit, "node-a"));
        assert!(!FenceKey::new(&[8; 32]).verify(&seal, 42, 5, &unit, "node-a"));
    }

    #[test]
    fn fault_budget_and_printable() {
        let mut b = FaultBudget::default();
        let allowed = (0..100).filter(|_| b.allow(1_000_000)).count();
        assert_eq!(allowed, FAULTS_PER_WINDOW as usize);
        assert_eq!(b.suppressed, 100 - u64::from(FAULTS_PER_WINDOW));
        assert!(b.allow(1_000_000 + FAULT_WINDOW_MS));
        assert_eq!(printable("a\nb\u{1b}[31m", 100), "a\\nb\\u{1b}[31m");
        assert_eq!(printable("ééé", 2), "éé");
    }
}
