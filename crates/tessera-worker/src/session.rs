//! Sessions with coordinators: [`sessions`] connects to one coordinator after another
//! (failover, backoff, the TLS files read again each time) until the worker is stopped;
//! [`session`] registers with one and drives the unit [`Pipeline`] until it is stopped or
//! the connection breaks.

use crate::connect::{self, Client, Failover};
use crate::faults::Hooks;
use crate::lease::{fetch_batch, give_back, return_unusable, Fetched};
use crate::pipeline::{Pipeline, Rendered, Start, Submitted};
use crate::render::Rendering;
use crate::scene_cache::SceneCache;
use crate::{WorkerConfig, WorkerError, WorkerTls};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tessera_proto::v1;
use tokio::sync::watch;
use tokio::task::{JoinError, JoinHandle};
use tokio::time::Instant;
use tonic::transport::Endpoint;
use tonic::Status;

/// What every session of a worker shares.
pub(crate) struct Worker {
    /// The configuration it was started with.
    pub(crate) config: WorkerConfig,
    /// The bearer token on every request.
    pub(crate) auth: connect::Auth,
    /// The render threads.
    pub(crate) pool: Arc<rayon::ThreadPool>,
    /// Scenes fetched and built, kept across sessions.
    pub(crate) cache: Arc<Mutex<SceneCache>>,
    /// The test hooks (nothing without the `fault-injection` feature).
    pub(crate) hooks: Hooks,
}

/// What outlives one session with a coordinator.
#[derive(Default)]
struct Carry {
    /// Results rendered and not yet answered by a coordinator: submitted first in the
    /// next session, whichever coordinator it is with.
    results: Vec<Rendered>,
    /// Whether the last session got as far as registering (then the coordinator was the
    /// active one).
    registered: bool,
}

/// Runs sessions with the coordinators, one after another in [`Failover`] order, until
/// `stop` is set and the results in hand are delivered (or every coordinator was tried
/// once more for them). Ends early only on a refused token or unusable TLS settings.
pub(crate) async fn sessions(
    worker: &Worker,
    mut endpoints: Vec<Endpoint>,
    stop: watch::Receiver<bool>,
) -> Result<(), WorkerError> {
    let urls = &worker.config.coordinators;
    let n = endpoints.len();
    let mut tls = worker.config.tls.clone();
    let mut carry = Carry::default();
    let mut failover = Failover::new(n);
    // Attempts made since the stop was asked for, to deliver results still in hand.
    let mut after_stop = 0usize;
    loop {
        if *stop.borrow() {
            if carry.results.is_empty() || after_stop >= n {
                if !carry.results.is_empty() {
                    tracing::warn!(
                        results = carry.results.len(),
                        "stopping with results no coordinator took; they are rendered again"
                    );
                }
                return Ok(());
            }
            after_stop += 1;
        }
        let next = failover.current();
        let url = &urls[next];
        carry.registered = false;
        // Certificates rotate under a running worker: each connection presents the
        // files as they are now. Bad new files leave the current ones in use.
        if let Some(fresh) = tls.as_ref().and_then(WorkerTls::reread) {
            match fresh.and_then(|f| Ok((connect::endpoints(urls, Some(&f))?, f))) {
                Ok((e, f)) => {
                    tracing::info!("TLS files changed: the next connections present them");
                    endpoints = e;
                    tls = Some(f);
                }
                Err(e) => {
                    tracing::warn!(error = %e, "TLS files changed but cannot be used; keeping the ones in force");
                }
            }
        }
        match endpoints[next].connect().await {
            Ok(channel) => {
                let auth = worker.auth.for_connection();
                let client = connect::client(channel, &auth);
                match session(worker, client, &auth, stop.clone(), &mut carry).await {
                    Ok(()) => return Ok(()),
                    Err(s) if s.code() == tonic::Code::Unauthenticated => {
                        return Err(WorkerError::Unauthenticated(s.message().to_string()))
                    }
                    Err(s) if s.code() == tonic::Code::Unavailable && !carry.registered => {
                        // A standby, or a coordinator that lost the leadership.
                        tracing::debug!(coordinator = %url, error = %s.message(), "coordinator not active");
                    }
                    Err(s) => {
                        tracing::warn!(coordinator = %url, error = %s, "coordinator connection lost");
                    }
                }
            }
            Err(e) => {
                // A refused TLS handshake (a wrong CA, a missing client certificate)
                // looks like this too: say it at the longest backoff, not only in
                // debug logs.
                let cause = connect::error_chain(&e);
                if failover.waited_longest() {
                    tracing::warn!(coordinator = %url, error = %cause, "coordinator not reachable");
                } else {
                    tracing::debug!(coordinator = %url, error = %cause, "coordinator not reachable");
                }
            }
        }
        if let Some(pause) = failover.ended(carry.registered) {
            let mut stop = stop.clone();
            tokio::select! {
                _ = tokio::time::sleep(pause) => {}
                _ = stop.changed() => {}
            }
        }
    }
}

/// Submits `results` in order; on a failure returns the status with the results not yet
/// answered (the failed one first), for the next session.
async fn submit_all(client: &mut Client, worker_id: u64, results: Vec<Rendered>) -> Submitted {
    let mut rest = results.into_iter();
    while let Some(r) = rest.next() {
        let mut req =
            v1::SubmitResultRequest::from_result(worker_id, r.lease_id, &r.result, r.seconds);
        req.fence = r.fence.clone();
        req.job_id = r.job_id;
        req.traced_pixel_passes = r.pixel_passes;
        match client.submit_result(req).await {
            Ok(resp) => {
                let resp = resp.into_inner();
                if !resp.accepted {
                    tracing::warn!(lease_id = r.lease_id, reason = %resp.reason, "result not accepted");
                }
            }
            Err(s) => {
                let mut left = vec![r];
                left.extend(rest);
                return Err((s, left));
            }
        }
    }
    Ok(())
}

/// The tasks a session runs beside its loop, one of each kind at most; each is under way
/// exactly when the [`Pipeline`] counts it as under way.
#[derive(Default)]
struct Tasks {
    /// The batch rendering on the pool.
    render: Option<Rendering>,
    /// The lease request, with the loading of its scenes.
    fetch: Option<JoinHandle<Result<Fetched, Status>>>,
    /// The submission of rendered results.
    submit: Option<JoinHandle<Submitted>>,
}

/// One registered session with a coordinator. Returns `Ok` when asked to stop, or the
/// status that broke the connection; results it could not deliver are left in `carry`.
/// Nothing it started is still under way when it returns.
async fn session(
    worker: &Worker,
    mut client: Client,
    auth: &connect::Auth,
    mut stop: watch::Receiver<bool>,
    carry: &mut Carry,
) -> Result<(), Status> {
    let config = &worker.config;
    let reg = client
        .register(v1::RegisterRequest {
            name: config.name.clone(),
            threads: config.threads as u32,
            version: env!("CARGO_PKG_VERSION").to_string(),
            capabilities: vec!["path".into(), "direct".into()],
        })
        .await?
        .into_inner();
    let worker_id = reg.worker_id;
    // Every later call of this connection carries the registration's session secret.
    auth.set_session(&reg.session)?;
    let heartbeat_every =
        Duration::from_millis(u64::from(reg.heartbeat_interval_ms.clamp(50, 60_000)));
    tracing::info!(worker_id, name = %config.name, "registered");
    carry.registered = true;
    if !carry.results.is_empty() {
        // Rendered for a coordinator that went away (or this one before it restarted).
        let results = std::mem::take(&mut carry.results);
        tracing::warn!(
            worker_id,
            results = results.len(),
            "submitting results rendered before the reconnection"
        );
        if let Err((s, left)) = submit_all(&mut client, worker_id, results).await {
            carry.results = left;
            return Err(s);
        }
    }
    // One heartbeat clock for the whole session, so batches shorter than the interval
    // still heartbeat (a timer restarted per batch would never fire).
    let mut beat = tokio::time::interval_at(Instant::now() + heartbeat_every, heartbeat_every);
    beat.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut pipe = Pipeline::new(config.threads);
    let mut tasks = Tasks::default();
    let outcome = loop {
        pipe.observe_stop(*stop.borrow());

        // 1. Stopping (SIGTERM): tell the coordinator at once, giving back the
        //    prefetched batch if any.
        if let Some(batch) = pipe.drain_to_announce() {
            give_back(&mut client, worker_id, batch).await;
        }

        // 2. The pool is free: start the prefetched batch, or give it back when stopping.
        match pipe.batch_to_start() {
            Some(Start::Render(batch)) => {
                tasks.render = Some(Rendering::start(&worker.pool, batch, worker.hooks));
            }
            Some(Start::GiveBack(batch)) => give_back(&mut client, worker_id, batch).await,
            None => {}
        }

        // 3. Lease the next batch while this one renders.
        if let Some(max_units) = pipe.lease_request(Instant::now()) {
            let (client, cache) = (client.clone(), worker.cache.clone());
            tasks.fetch = Some(tokio::spawn(fetch_batch(
                client, cache, worker_id, max_units,
            )));
        }

        // 4. Submit in the background, one submission at a time; its errors end the
        //    session (what it did not deliver goes to the next one).
        if let Some(results) = pipe.submission() {
            let mut client = client.clone();
            tasks.submit = Some(tokio::spawn(async move {
                submit_all(&mut client, worker_id, results).await
            }));
        }

        // 5. Nothing under way: the session ends if it is stopping or broken.
        if let Some(outcome) = pipe.outcome() {
            break outcome;
        }

        // 6. Wait for the next thing to happen.
        tokio::select! {
            r = join(tasks.render.as_mut().map(|r| &mut r.task)), if tasks.render.is_some() => {
                let elapsed = tasks.render.take().map(|r| r.started.elapsed()).unwrap_or_default();
                match r {
                    Ok(outcomes) => {
                        let sorted = pipe.rendered(elapsed, outcomes);
                        if !sorted.panicked.is_empty() && !pipe.is_broken() {
                            // A unit whose rendering panicked is a fault of its scene, not
                            // of this worker: its lease goes back as unusable.
                            let returned =
                                return_unusable(&mut client, worker_id, sorted.panicked, sorted.why)
                                    .await;
                            if let Err(s) = returned {
                                pipe.break_with(s);
                            }
                        }
                        pipe.keep(sorted.results);
                    }
                    Err(e) => pipe.render_failed(e.to_string()),
                }
            }
            f = join(tasks.fetch.as_mut()), if tasks.fetch.is_some() => {
                tasks.fetch = None;
                let answer = f.unwrap_or_else(|e| Err(task_failed("lease", &e)));
                pipe.fetched(answer, Instant::now());
            }
            s = join(tasks.submit.as_mut()), if tasks.submit.is_some() => {
                tasks.submit = None;
                pipe.submitted(s.unwrap_or_else(|e| Err((task_failed("submit", &e), Vec::new()))));
            }
            _ = beat.tick(), if !pipe.is_broken() => {
                let request = v1::HeartbeatRequest {
                    worker_id,
                    lease_ids: pipe.held_leases(),
                    paths_per_second: pipe.paths_per_second(),
                };
                match client.heartbeat(request).await {
                    Ok(hb) => {
                        let hb = hb.into_inner();
                        if pipe.heartbeat_answered(hb.cancel, hb.shutdown) {
                            tracing::info!(worker_id, "the coordinator is shutting down; finishing the units in hand");
                        }
                    }
                    Err(s) => {
                        tracing::warn!(worker_id, error = %s, "heartbeat failed; finishing the units in hand to deliver them elsewhere");
                        pipe.break_with(s);
                    }
                }
            }
            _ = sleep_until(pipe.retry_at()), if pipe.retry_at().is_some() => {}
            _ = stop.changed(), if !*stop.borrow() => {}
        }

        // 7. Broken: nothing new is started; a lease request under way is abandoned (the
        //    units it may bring lapse and are leased again).
        if pipe.abandon_prefetch() {
            if let Some(f) = tasks.fetch.take() {
                f.abort();
            }
        }
    };
    carry.results.append(&mut pipe.take_undelivered());
    outcome
}

/// The status of a task that ended without an answer (it panicked).
fn task_failed(what: &str, e: &JoinError) -> Status {
    Status::internal(format!("{what} task failed: {e}"))
}

/// Awaits the task `h`; never completes for `None` (the `select!` branches check).
async fn join<T>(h: Option<&mut JoinHandle<T>>) -> Result<T, JoinError> {
    match h {
        Some(h) => h.await,
        None => std::future::pending().await,
    }
}

/// Sleeps until `at`, forever if `None`.
async fn sleep_until(at: Option<Instant>) {
    match at {
        Some(at) => tokio::time::sleep_until(at).await,
        None => std::future::pending().await,
    }
}
