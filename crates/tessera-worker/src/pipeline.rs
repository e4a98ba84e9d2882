//! The unit pipeline of one session with a coordinator (docs/ARCHITECTURE.md §9, "The
//! worker's pipeline"): one batch renders while the next is leased and its scenes loaded
//! (prefetched), and the results of the one before are submitted in the background, so
//! the render threads wait on the network only when the coordinator has no work.
//!
//! [`Pipeline`] holds that state and decides; it does no I/O and reads no clock. The
//! session loop (`session.rs`) asks it, step by step, what to do next — give back the
//! prefetched batch, start a batch, lease, submit, end — does it, and tells it what came
//! back: a batch rendered, a lease request answered, a submission ended, a heartbeat's
//! answer. Its rules:
//!
//! - At most two batches in hand: one rendering, one prefetched. A lease request is made
//!   only when nothing is prefetched and none is under way, and not before the wait an
//!   empty answer asked for.
//! - A batch asks for about [`BATCH_SECONDS`] of rendering per thread at the measured
//!   seconds per unit ([`units_to_ask`]); the units themselves never change size.
//! - One submission at a time; results rendered meanwhile wait for the next one.
//! - Heartbeats list every lease held: rendering, prefetched, waiting for or in a
//!   submission; a heartbeat's cancellations drop the prefetched units before they start
//!   and the rendered results before they are submitted.
//! - Stopping (asked, or told by a heartbeat): nothing new is leased; what renders is
//!   finished and submitted; the prefetched batch is given back (on our own stop at once,
//!   announcing the drain even with nothing to give back).
//! - Broken (a failed call): nothing new starts; the batch rendering is finished and its
//!   results kept, with whatever was not delivered, for the next coordinator; the
//!   prefetched batch is dropped (its leases lapse).

use crate::lease::Fetched;
use crate::render::{Batch, Outcome};
use std::collections::HashSet;
use std::time::Duration;
use tokio::time::Instant;
use tonic::Status;

/// What the pipeline needs of a batch of leased units.
pub(crate) trait Leases: Default {
    /// The batch's lease ids, in order.
    fn lease_ids(&self) -> Vec<u64>;
    /// Keeps only the leases for which `keep` is true.
    fn retain_leases(&mut self, keep: impl FnMut(u64) -> bool);
    /// Whether no lease is left.
    fn is_empty(&self) -> bool;
}

/// A rendered unit waiting to be submitted.
pub(crate) struct Rendered {
    /// The unit's lease.
    pub(crate) lease_id: u64,
    /// The unit's job.
    pub(crate) job_id: u64,
    /// The lease's seal, sent back with the result.
    pub(crate) fence: Vec<u8>,
    /// The result.
    pub(crate) result: tessera_farm::UnitResult,
    /// Seconds it took on its thread.
    pub(crate) seconds: f64,
    /// Pixel-passes traced (reported with the result).
    pub(crate) pixel_passes: u64,
}

/// How a submission ended: on a failure, the status with the results it did not deliver
/// (the failed one first).
pub(crate) type Submitted = Result<(), (Status, Vec<Rendered>)>;

/// A batch's outcomes, sorted by [`Pipeline::rendered`].
pub(crate) struct Sorted {
    /// The results to submit (canceled leases left out).
    pub(crate) results: Vec<Rendered>,
    /// The leases whose rendering panicked, to return as unusable.
    pub(crate) panicked: Vec<u64>,
    /// The first panic's message, as the reason given with them.
    pub(crate) why: String,
}

/// What to do with the prefetched batch once the pool is free.
pub(crate) enum Start<B> {
    /// Render it.
    Render(B),
    /// Give it back: the worker is stopping.
    GiveBack(B),
}

/// Seconds of rendering one lease request aims to bring each thread: long enough that
/// the coordinator's work per lease request is small beside it, short enough that the
/// scheduler's tail rule (`tessera_farm::tail_share`) has small batches to hand out. The
/// lease's round trip itself is hidden by prefetching.
const BATCH_SECONDS: f64 = 0.5;
/// Units per thread asked for before any unit was measured.
const FIRST_UNITS_PER_THREAD: u32 = 4;
/// Most units per thread asked for at once, however short they are.
const MAX_UNITS_PER_THREAD: u32 = 64;

/// The state of one session's pipeline. `B` is the batch type: [`Batch`] in the worker,
/// plain lease ids in the tests.
pub(crate) struct Pipeline<B: Leases = Batch> {
    /// Rendering threads (the batch size is per thread).
    threads: usize,
    /// Whether the worker was asked to stop (SIGTERM), as last observed.
    stop_asked: bool,
    /// Whether a heartbeat said the coordinator is shutting down: finish the units in
    /// hand as on our own stop.
    told_to_stop: bool,
    /// Whether the coordinator was told this worker is stopping.
    drain_announced: bool,
    /// The leases of the batch rendering, if one is.
    rendering: Option<Vec<u64>>,
    /// The prefetched batch: leased, scenes loaded, not started.
    next: Option<B>,
    /// Whether a lease request is under way.
    fetching: bool,
    /// When to ask again after a lease request brought no unit.
    retry_at: Option<Instant>,
    /// Results waiting for the next submission.
    to_submit: Vec<Rendered>,
    /// The leases of the submission under way, if one is: heartbeated until it ends, so
    /// a result queued behind a slow submission does not lapse on the way.
    submitting: Option<Vec<u64>>,
    /// Leases the coordinator told us to drop (their job was canceled).
    canceled: HashSet<u64>,
    /// Seconds one unit takes on one thread, measured (a moving average): sizes the
    /// batches.
    unit_seconds: Option<f64>,
    /// The last batch's camera paths per second of wall time (reported in heartbeats).
    paths_per_second: f64,
    /// Whatever broke the session: the units in hand are finished anyway and kept for
    /// the next coordinator, then the session ends with this status.
    broken: Option<Status>,
    /// Results no coordinator took in this session, for the next one.
    undelivered: Vec<Rendered>,
}

impl<B: Leases> Pipeline<B> {
    /// An empty pipeline for `threads` render threads.
    pub(crate) fn new(threads: usize) -> Self {
        Self {
            threads,
            stop_asked: false,
            told_to_stop: false,
            drain_announced: false,
            rendering: None,
            next: None,
            fetching: false,
            retry_at: None,
            to_submit: Vec::new(),
            submitting: None,
            canceled: HashSet::new(),
            unit_seconds: None,
            paths_per_second: 0.0,
            broken: None,
            undelivered: Vec::new(),
        }
    }

    // ---- State ----------------------------------------------------------------------

    /// Records whether the worker is asked to stop; read once per turn of the loop.
    pub(crate) fn observe_stop(&mut self, asked: bool) {
        self.stop_asked = asked;
    }

    /// Whether the worker is finishing what it holds (asked to stop, or told to).
    pub(crate) fn stopping(&self) -> bool {
        self.stop_asked || self.told_to_stop
    }

    /// Whether a call failed in this session.
    pub(crate) fn is_broken(&self) -> bool {
        self.broken.is_some()
    }

    /// When to lease again after an empty answer, if the loop should wake for it.
    pub(crate) fn retry_at(&self) -> Option<Instant> {
        self.retry_at.filter(|_| !self.stopping())
    }

    /// Every lease the worker holds, for a heartbeat: the batch rendering, the prefetched
    /// one, the results waiting for their submission and those in it.
    pub(crate) fn held_leases(&self) -> Vec<u64> {
        let mut ids: Vec<u64> = self.rendering.iter().flatten().copied().collect();
        ids.extend(self.next.iter().flat_map(Leases::lease_ids));
        ids.extend(self.to_submit.iter().map(|r| r.lease_id));
        ids.extend(self.submitting.iter().flatten().copied());
        ids
    }

    /// The last batch's camera paths per second, for a heartbeat.
    pub(crate) fn paths_per_second(&self) -> f64 {
        self.paths_per_second
    }

    /// Takes the results no coordinator took in this session.
    pub(crate) fn take_undelivered(&mut self) -> Vec<Rendered> {
        std::mem::take(&mut self.undelivered)
    }

    // ---- Steps: what to do next -------------------------------------------------------

    /// On our own stop, once: the batch to give back at once (the prefetched one, or an
    /// empty one), which tells the coordinator the worker is draining, so that /workers
    /// shows it and the tail rule stops counting its threads while it finishes.
    pub(crate) fn drain_to_announce(&mut self) -> Option<B> {
        if !self.stop_asked || self.drain_announced || self.is_broken() {
            return None;
        }
        self.drain_announced = true;
        Some(self.next.take().unwrap_or_default())
    }

    /// When the pool is free: the prefetched batch, without its canceled leases, to
    /// start, or to give back when stopping.
    pub(crate) fn batch_to_start(&mut self) -> Option<Start<B>> {
        if self.rendering.is_some() || self.is_broken() {
            return None;
        }
        let mut batch = self.next.take()?;
        batch.retain_leases(|id| !self.canceled.remove(&id));
        if batch.is_empty() {
            None
        } else if self.stopping() {
            Some(Start::GiveBack(batch))
        } else {
            self.rendering = Some(batch.lease_ids());
            Some(Start::Render(batch))
        }
    }

    /// How many units to lease now, if a lease request is due: nothing prefetched, none
    /// under way, not stopping or broken, and past the wait an empty answer asked for.
    pub(crate) fn lease_request(&mut self, now: Instant) -> Option<u32> {
        let may_lease = self.retry_at.is_none_or(|t| t <= now);
        if self.stopping() || self.is_broken() || self.next.is_some() || self.fetching {
            return None;
        }
        if !may_lease {
            return None;
        }
        self.retry_at = None;
        self.fetching = true;
        Some(units_to_ask(self.threads, self.unit_seconds))
    }

    /// The results to submit now, if no submission is under way. The coordinator commits
    /// each result to its store before acknowledging it, and the worker's threads should
    /// not wait for that: the submission runs in the background.
    pub(crate) fn submission(&mut self) -> Option<Vec<Rendered>> {
        if self.submitting.is_some() || self.to_submit.is_empty() || self.is_broken() {
            return None;
        }
        let batch = std::mem::take(&mut self.to_submit);
        self.submitting = Some(batch.iter().map(|r| r.lease_id).collect());
        Some(batch)
    }

    /// How the session ends, once nothing is under way: `Ok` when stopping with nothing
    /// left, the status that broke it otherwise (the results not submitted are then kept,
    /// [`Pipeline::take_undelivered`]); `None` while it goes on.
    pub(crate) fn outcome(&mut self) -> Option<Result<(), Status>> {
        if self.rendering.is_some() || self.fetching || self.submitting.is_some() {
            return None;
        }
        if let Some(s) = self.broken.take() {
            // A prefetched batch, not started, is dropped: its leases lapse.
            self.undelivered.append(&mut self.to_submit);
            return Some(Err(s));
        }
        if self.stopping() && self.next.is_none() && self.to_submit.is_empty() {
            return Some(Ok(()));
        }
        None
    }

    // ---- Events: what came back ---------------------------------------------------------

    /// The batch rendering finished after `elapsed` (wall time): measures it and sorts its
    /// outcomes. The caller returns the panicked leases, then [`Pipeline::keep`]s the
    /// results.
    pub(crate) fn rendered(&mut self, elapsed: Duration, outcomes: Vec<Outcome>) -> Sorted {
        self.rendering = None;
        let seconds = elapsed.as_secs_f64().max(1e-9);
        let paths: f64 = outcomes.iter().map(|o| o.paths).sum();
        self.paths_per_second = paths / seconds;
        self.unit_seconds = measured_unit_seconds(self.unit_seconds, &outcomes);
        sort_results(outcomes, &mut self.canceled)
    }

    /// The batch rendering ended without outcomes (its task failed).
    pub(crate) fn render_failed(&mut self, why: String) {
        self.rendering = None;
        self.broken = Some(Status::internal(format!("render task failed: {why}")));
    }

    /// Rendered results: submitted next, or kept for the next coordinator if the session
    /// broke.
    pub(crate) fn keep(&mut self, results: Vec<Rendered>) {
        match self.broken {
            Some(_) => self.undelivered.extend(results),
            None => self.to_submit.extend(results),
        }
    }

    /// The lease request ended (answered at `now`).
    pub(crate) fn fetched(&mut self, answer: Result<Fetched<B>, Status>, now: Instant) {
        self.fetching = false;
        match answer {
            Ok(Fetched::Batch(b)) if self.is_broken() => drop(b),
            Ok(Fetched::Batch(b)) => self.next = Some(b),
            Ok(Fetched::Empty(wait)) => self.retry_at = Some(now + wait),
            Err(s) => self.break_with(s),
        }
    }

    /// The submission under way ended; on a failure, with the results it did not deliver.
    pub(crate) fn submitted(&mut self, answer: Submitted) {
        self.submitting = None;
        if let Err((s, left)) = answer {
            self.undelivered.extend(left);
            self.break_with(s);
        }
    }

    /// A heartbeat's answer: leases to drop, and whether the coordinator is shutting
    /// down. True when this is the first time it says so.
    pub(crate) fn heartbeat_answered(&mut self, cancel: Vec<u64>, shutdown: bool) -> bool {
        self.canceled.extend(cancel);
        let news = shutdown && !self.told_to_stop;
        self.told_to_stop |= shutdown;
        news
    }

    /// A call failed: the session is broken (the first failure is the one reported).
    pub(crate) fn break_with(&mut self, s: Status) {
        self.broken.get_or_insert(s);
    }

    /// After each event: a broken session starts nothing new, so the prefetched batch is
    /// dropped (its leases lapse, as a worker killed with SIGKILL would leave them) and a
    /// lease request under way abandoned. True if there is one for the caller to abort.
    pub(crate) fn abandon_prefetch(&mut self) -> bool {
        if !self.is_broken() {
            return false;
        }
        self.next = None;
        std::mem::take(&mut self.fetching)
    }
}

/// How many units to ask for: about [`BATCH_SECONDS`] of rendering per thread at the
/// measured seconds per unit, [`FIRST_UNITS_PER_THREAD`] per thread before a measure.
///
/// Only the number of units leased at once depends on the clock, never what a unit is:
/// units are fixed when the job is planned (a tile and a pass range, checkpointed and
/// resumed by index), so the image does not depend on this.
pub(crate) fn units_to_ask(threads: usize, unit_seconds: Option<f64>) -> u32 {
    let per_thread = match unit_seconds {
        Some(s) if s.is_finite() && s > 0.0 => (BATCH_SECONDS / s)
            .round()
            .clamp(1.0, f64::from(MAX_UNITS_PER_THREAD))
            as u32,
        _ => FIRST_UNITS_PER_THREAD,
    };
    (threads as u32).saturating_mul(per_thread)
}

/// The moving average of seconds per unit after a batch: the batch's mean, weighted by
/// half against what was measured before (so a change of scene shows within a few
/// batches). Units that panicked are not counted.
fn measured_unit_seconds(before: Option<f64>, results: &[Outcome]) -> Option<f64> {
    let times: Vec<f64> = results
        .iter()
        .filter(|r| r.result.is_ok())
        .map(|r| r.seconds)
        .collect();
    if times.is_empty() {
        return before;
    }
    let mean = times.iter().sum::<f64>() / times.len() as f64;
    Some(match before {
        Some(b) => 0.5 * b + 0.5 * mean,
        None => mean,
    })
}

/// Splits a batch's outcomes into the results to submit (without those of canceled
/// leases, whose ids leave `canceled`) and the leases whose rendering panicked, with the
/// first panic's message.
fn sort_results(results: Vec<Outcome>, canceled: &mut HashSet<u64>) -> Sorted {
    let mut rendered = Vec::with_capacity(results.len());
    let mut panicked = Vec::new();
    let mut why = String::new();
    for o in results {
        let dropped = canceled.remove(&o.lease_id);
        match o.result {
            Ok(result) if !dropped => rendered.push(Rendered {
                lease_id: o.lease_id,
                job_id: o.job_id,
                fence: o.fence,
                result,
                seconds: o.seconds,
                pixel_passes: o.pixel_passes,
            }),
            Ok(_) => {}
            Err(message) => {
                tracing::error!(lease_id = o.lease_id, job_id = o.job_id, error = %message, "rendering panicked; returning lease");
                if !dropped {
                    panicked.push(o.lease_id);
                }
                if why.is_empty() {
                    why = format!("rendering panicked: {message}");
                }
            }
        }
    }
    Sorted {
        results: rendered,
        panicked,
        why,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::Code;

    /// A batch in the tests: its lease ids.
    type Ids = Vec<u64>;

    impl Leases for Ids {
        fn lease_ids(&self) -> Vec<u64> {
            self.clone()
        }
        fn retain_leases(&mut self, keep: impl FnMut(u64) -> bool) {
            let mut keep = keep;
            self.retain(|&id| keep(id));
        }
        fn is_empty(&self) -> bool {
            Vec::is_empty(self)
        }
    }

    fn unit_result() -> tessera_farm::UnitResult {
        tessera_farm::UnitResult {
            unit: tessera_farm::WorkUnit {
                frame: 0,
                tile: 0,
                first_pass: 0,
                pass_count: 1,
            },
            width: 1,
            height: 1,
            pass_means: vec![[0.5; 3]],
            rejected_samples: 0,
            bias: None,
        }
    }

    /// Lease `id` rendered in `seconds` on its thread, tracing 1000 paths.
    fn ok(id: u64, seconds: f64) -> Outcome {
        Outcome {
            lease_id: id,
            job_id: 1,
            fence: Vec::new(),
            result: Ok(unit_result()),
            seconds,
            paths: 1000.0,
            pixel_passes: 10,
        }
    }

    /// Lease `id`'s rendering panicked with `message`.
    fn panicked(id: u64, message: &str) -> Outcome {
        Outcome {
            lease_id: id,
            job_id: 1,
            fence: Vec::new(),
            result: Err(message.to_string()),
            seconds: 100.0,
            paths: 0.0,
            pixel_passes: 0,
        }
    }

    fn ids(results: &[Rendered]) -> Vec<u64> {
        results.iter().map(|r| r.lease_id).collect()
    }

    /// Leases `batch` and starts it rendering.
    fn lease_and_start(p: &mut Pipeline<Ids>, batch: &[u64], now: Instant) {
        assert!(p.lease_request(now).is_some(), "no lease request");
        p.fetched(Ok(Fetched::Batch(batch.to_vec())), now);
        match p.batch_to_start() {
            Some(Start::Render(b)) => assert_eq!(b, batch),
            _ => panic!("{batch:?} did not start"),
        }
    }

    /// The batch rendering finishes with `outcomes` and nothing panicked; its results are
    /// kept.
    fn finish(p: &mut Pipeline<Ids>, outcomes: Vec<Outcome>) {
        let sorted = p.rendered(Duration::from_millis(100), outcomes);
        assert!(sorted.panicked.is_empty());
        p.keep(sorted.results);
    }

    #[test]
    fn one_batch_renders_while_the_next_is_prefetched_and_no_more() {
        let now = Instant::now();
        let mut p = Pipeline::<Ids>::new(2);
        // Before any measure: 4 units per thread; one request at a time.
        assert_eq!(p.lease_request(now), Some(8));
        assert_eq!(p.lease_request(now), None);
        p.fetched(Ok(Fetched::Batch(vec![1, 2, 3])), now);
        // A prefetched batch waiting: no request until it starts.
        assert_eq!(p.lease_request(now), None);
        assert!(matches!(p.batch_to_start(), Some(Start::Render(b)) if b == [1, 2, 3]));
        // While it renders the next one is leased...
        assert_eq!(p.lease_request(now), Some(8));
        p.fetched(Ok(Fetched::Batch(vec![4, 5])), now);
        // ...and waits for the pool; nothing more is leased: two batches in hand.
        assert!(p.batch_to_start().is_none());
        assert_eq!(p.lease_request(now), None);
        assert_eq!(p.held_leases(), [1, 2, 3, 4, 5]);
        // The pool frees: the prefetched batch starts at once, the next is leased.
        finish(&mut p, vec![ok(1, 0.1), ok(2, 0.1), ok(3, 0.1)]);
        assert!(matches!(p.batch_to_start(), Some(Start::Render(b)) if b == [4, 5]));
        assert!(p.lease_request(now).is_some());
        assert_eq!(p.outcome().map(|r| r.is_ok()), None);
    }

    #[test]
    fn the_batch_size_follows_the_measured_seconds_per_unit() {
        let now = Instant::now();
        let mut p = Pipeline::<Ids>::new(3);
        lease_and_start(&mut p, &[1, 2], now);
        // 50 ms a unit (a panicked unit's time does not count): 0.5 s is 10 units a
        // thread.
        finish(&mut p, vec![ok(1, 0.05), ok(2, 0.05)]);
        assert_eq!(p.lease_request(now), Some(30));
        p.fetched(Ok(Fetched::Batch(vec![3, 4])), now);
        assert!(matches!(p.batch_to_start(), Some(Start::Render(_))));
        // Then 150 ms: the moving average is 100 ms, 5 units a thread.
        let sorted = p.rendered(
            Duration::from_millis(300),
            vec![ok(3, 0.15), panicked(4, "boom")],
        );
        p.keep(sorted.results);
        assert_eq!(p.lease_request(now), Some(15));
        // 1000 paths traced in 0.3 s of wall time.
        assert!((p.paths_per_second() - 1000.0 / 0.3).abs() < 1e-6);
    }

    #[test]
    fn units_asked_for_are_half_a_second_a_thread_from_1_to_64() {
        assert_eq!(units_to_ask(4, None), 16);
        assert_eq!(units_to_ask(4, Some(0.5 / 3.0)), 12);
        // Slow units: one a thread; fast ones: at most 64.
        assert_eq!(units_to_ask(4, Some(10.0)), 4);
        assert_eq!(units_to_ask(4, Some(1e-6)), 256);
        // No usable measure: the first rule.
        for s in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert_eq!(units_to_ask(2, Some(s)), 8, "{s}");
        }
        assert_eq!(units_to_ask(usize::MAX, None), u32::MAX);
    }

    #[test]
    fn an_empty_answer_is_asked_again_after_the_wait_it_gave() {
        let now = Instant::now();
        let wait = Duration::from_millis(200);
        let mut p = Pipeline::<Ids>::new(1);
        assert!(p.lease_request(now).is_some());
        p.fetched(Ok(Fetched::Empty(wait)), now);
        assert_eq!(p.retry_at(), Some(now + wait));
        assert_eq!(p.lease_request(now + wait - Duration::from_millis(1)), None);
        assert_eq!(p.lease_request(now + wait), Some(4));
        assert_eq!(p.retry_at(), None);
        // Stopping: the loop no longer wakes to lease.
        p.fetched(Ok(Fetched::Empty(wait)), now);
        p.observe_stop(true);
        assert_eq!(p.retry_at(), None);
        assert_eq!(p.lease_request(now + wait), None);
    }

    #[test]
    fn one_submission_at_a_time_and_heartbeats_list_every_lease_held() {
        let now = Instant::now();
        let mut p = Pipeline::<Ids>::new(1);
        lease_and_start(&mut p, &[1, 2], now);
        finish(&mut p, vec![ok(1, 0.1), ok(2, 0.1)]);
        assert_eq!(p.submission().map(|b| ids(&b)), Some(vec![1, 2]));
        lease_and_start(&mut p, &[3], now);
        finish(&mut p, vec![ok(3, 0.1)]);
        // [1, 2] are still being submitted: [3] waits its turn.
        assert!(p.submission().is_none());
        lease_and_start(&mut p, &[4], now);
        assert!(p.lease_request(now).is_some());
        p.fetched(Ok(Fetched::Batch(vec![5])), now);
        // Rendering, prefetched, waiting for a submission, in one.
        assert_eq!(p.held_leases(), [4, 5, 3, 1, 2]);
        p.submitted(Ok(()));
        assert_eq!(p.submission().map(|b| ids(&b)), Some(vec![3]));
        assert_eq!(p.held_leases(), [4, 5, 3]);
    }

    #[test]
    fn canceled_leases_are_dropped_before_they_start_and_after_they_render() {
        let now = Instant::now();
        let mut p = Pipeline::<Ids>::new(1);
        lease_and_start(&mut p, &[1, 2], now);
        assert!(p.lease_request(now).is_some());
        p.fetched(Ok(Fetched::Batch(vec![3, 4])), now);
        assert!(!p.heartbeat_answered(vec![2, 3], false));
        finish(&mut p, vec![ok(1, 0.1), ok(2, 0.1)]);
        assert_eq!(p.submission().map(|b| ids(&b)), Some(vec![1]));
        assert!(matches!(p.batch_to_start(), Some(Start::Render(b)) if b == [4]));
        // A prefetched batch canceled whole does not start, and the next is leased.
        finish(&mut p, vec![ok(4, 0.1)]);
        assert!(p.lease_request(now).is_some());
        p.fetched(Ok(Fetched::Batch(vec![5])), now);
        p.heartbeat_answered(vec![5], false);
        assert!(p.batch_to_start().is_none());
        assert!(p.lease_request(now).is_some());
        // The canceled ids were forgotten once used.
        assert!(p.canceled.is_empty());
    }

    #[test]
    fn a_unit_that_panicked_is_returned_as_unusable_not_submitted() {
        let now = Instant::now();
        let mut p = Pipeline::<Ids>::new(1);
        lease_and_start(&mut p, &[1, 2, 3], now);
        let sorted = p.rendered(
            Duration::from_millis(100),
            vec![ok(1, 0.1), panicked(2, "first"), panicked(3, "second")],
        );
        assert_eq!(ids(&sorted.results), [1]);
        assert_eq!(sorted.panicked, [2, 3]);
        assert_eq!(sorted.why, "rendering panicked: first");
    }

    #[test]
    fn our_own_stop_announces_the_drain_at_once_and_finishes_the_batch_in_hand() {
        let now = Instant::now();
        let mut p = Pipeline::<Ids>::new(1);
        lease_and_start(&mut p, &[1], now);
        assert!(p.lease_request(now).is_some());
        p.fetched(Ok(Fetched::Batch(vec![2])), now);
        p.observe_stop(true);
        // The prefetched batch goes back with the announcement, once.
        assert_eq!(p.drain_to_announce(), Some(vec![2]));
        assert_eq!(p.drain_to_announce(), None);
        assert_eq!(p.lease_request(now), None);
        assert!(p.outcome().is_none());
        // The batch rendering is finished and submitted, then the session ends.
        finish(&mut p, vec![ok(1, 0.1)]);
        assert!(p.outcome().is_none());
        assert_eq!(p.submission().map(|b| ids(&b)), Some(vec![1]));
        assert!(p.outcome().is_none());
        p.submitted(Ok(()));
        assert!(matches!(p.outcome(), Some(Ok(()))));
    }

    #[test]
    fn a_stop_with_nothing_in_hand_still_announces_the_drain() {
        let mut p = Pipeline::<Ids>::new(1);
        p.observe_stop(true);
        assert_eq!(p.drain_to_announce(), Some(Vec::new()));
        assert!(matches!(p.outcome(), Some(Ok(()))));
    }

    #[test]
    fn a_coordinator_shutting_down_gets_the_prefetched_batch_back_when_the_pool_frees() {
        let now = Instant::now();
        let mut p = Pipeline::<Ids>::new(1);
        lease_and_start(&mut p, &[1], now);
        assert!(p.lease_request(now).is_some());
        p.fetched(Ok(Fetched::Batch(vec![2])), now);
        assert!(p.heartbeat_answered(Vec::new(), true));
        assert!(!p.heartbeat_answered(Vec::new(), true));
        // Not our own stop: no drain announcement, the batch waits for the pool.
        assert_eq!(p.drain_to_announce(), None);
        assert!(p.batch_to_start().is_none());
        finish(&mut p, vec![ok(1, 0.1)]);
        assert!(matches!(p.batch_to_start(), Some(Start::GiveBack(b)) if b == [2]));
        assert_eq!(p.lease_request(now), None);
        assert!(p.submission().is_some());
        p.submitted(Ok(()));
        assert!(matches!(p.outcome(), Some(Ok(()))));
    }

    #[test]
    fn a_broken_session_finishes_the_batch_in_hand_and_keeps_what_was_not_delivered() {
        let now = Instant::now();
        let mut p = Pipeline::<Ids>::new(1);
        lease_and_start(&mut p, &[1], now);
        finish(&mut p, vec![ok(1, 0.1)]);
        assert!(p.submission().is_some());
        lease_and_start(&mut p, &[2], now);
        assert!(p.lease_request(now).is_some());
        // A heartbeat fails: the lease request under way is abandoned, nothing new starts.
        p.break_with(Status::unavailable("heartbeat"));
        assert!(p.abandon_prefetch());
        assert!(!p.abandon_prefetch());
        assert_eq!(p.lease_request(now), None);
        assert!(p.outcome().is_none());
        // The submission under way fails too, with [1] not delivered; the first failure
        // is the one reported.
        p.submitted(Err((Status::internal("submit"), vec![ok_rendered(1)])));
        // The batch rendering is finished, and kept.
        finish(&mut p, vec![ok(2, 0.1)]);
        assert!(p.submission().is_none());
        match p.outcome() {
            Some(Err(s)) => assert_eq!(s.code(), Code::Unavailable),
            _ => panic!("the session did not end broken"),
        }
        assert_eq!(ids(&p.take_undelivered()), [1, 2]);
    }

    #[test]
    fn a_broken_session_drops_the_prefetched_batch_and_announces_no_drain() {
        let now = Instant::now();
        let mut p = Pipeline::<Ids>::new(1);
        lease_and_start(&mut p, &[1], now);
        assert!(p.lease_request(now).is_some());
        p.fetched(Ok(Fetched::Batch(vec![2])), now);
        p.break_with(Status::unavailable("heartbeat"));
        // No request under way to abort, but the prefetched batch is dropped.
        assert!(!p.abandon_prefetch());
        assert_eq!(p.held_leases(), [1]);
        p.observe_stop(true);
        assert_eq!(p.drain_to_announce(), None);
        finish(&mut p, vec![ok(1, 0.1)]);
        assert!(p.batch_to_start().is_none());
        assert!(matches!(p.outcome(), Some(Err(_))));
        assert_eq!(ids(&p.take_undelivered()), [1]);
    }

    #[test]
    fn a_failed_lease_request_breaks_the_session_and_a_late_batch_is_dropped() {
        let now = Instant::now();
        let mut p = Pipeline::<Ids>::new(1);
        lease_and_start(&mut p, &[1], now);
        assert!(p.lease_request(now).is_some());
        finish(&mut p, vec![ok(1, 0.1)]);
        p.fetched(Err(Status::unavailable("lease")), now);
        assert!(p.is_broken());
        // Nothing is submitted once broken: [1] is kept for the next coordinator.
        assert!(p.submission().is_none());
        assert!(matches!(p.outcome(), Some(Err(_))));
        assert_eq!(ids(&p.take_undelivered()), [1]);
        // A batch that arrives after the break is dropped.
        let mut p = Pipeline::<Ids>::new(1);
        assert!(p.lease_request(now).is_some());
        p.break_with(Status::unavailable("heartbeat"));
        p.fetched(Ok(Fetched::Batch(vec![3])), now);
        assert!(p.held_leases().is_empty());
        assert!(matches!(p.outcome(), Some(Err(_))));
    }

    fn ok_rendered(id: u64) -> Rendered {
        Rendered {
            lease_id: id,
            job_id: 1,
            fence: Vec::new(),
            result: unit_result(),
            seconds: 0.1,
            pixel_passes: 10,
        }
    }
}
