//! Asking the coordinator for units, with their scenes loaded before the clock starts,
//! and giving back units the worker will not render.

use crate::connect::Client;
use crate::render::Batch;
use crate::scene_cache::{scene_for, SceneCache};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tessera_proto::v1;
use tessera_proto::LeasedUnit;
use tonic::Status;

/// What one lease request brought.
pub(crate) enum Fetched<B = Batch> {
    /// Units to render.
    Batch(B),
    /// No unit (none usable): ask again after this long.
    Empty(Duration),
}

/// How long a lease request may wait at the coordinator for work (a long poll,
/// `LeaseRequest.wait_ms`). Without it an idle worker asks again every 50 ms, and a unit
/// that becomes leasable in between (an adaptive decision taken, a job queued) waits for
/// the next ask.
const LEASE_WAIT_MS: u32 = 1000;

/// Leases up to `max_units` units and makes sure every scene is here and built before
/// the clock starts; the leases of units whose scene cannot be used are returned as
/// unusable, saying why, so that the coordinator fails a job whose scene no worker can
/// use.
pub(crate) async fn fetch_batch(
    mut client: Client,
    cache: Arc<Mutex<SceneCache>>,
    worker_id: u64,
    max_units: u32,
) -> Result<Fetched, Status> {
    let resp = client
        .lease_work(v1::LeaseRequest {
            worker_id,
            max_units,
            wait_ms: LEASE_WAIT_MS,
        })
        .await?
        .into_inner();
    let wait = Duration::from_millis(u64::from(resp.retry_after_ms.clamp(20, 2000)));
    let mut units = Vec::with_capacity(resp.leases.len());
    let mut unusable = Vec::new();
    let mut why = String::new();
    for l in resp.leases {
        let l = match LeasedUnit::try_from(l) {
            Ok(l) => l,
            Err(e) => {
                tracing::warn!(error = %e, "coordinator sent an invalid lease");
                continue;
            }
        };
        match scene_for(&mut client, &cache, &l).await {
            Ok(rs) => units.push((l, rs)),
            Err(e) => {
                tracing::warn!(scene = %l.scene.source, error = %e, "cannot load scene; returning lease");
                unusable.push(l.lease_id);
                if why.is_empty() {
                    why = format!("scene {}: {e}", l.scene.source);
                }
            }
        }
    }
    if !unusable.is_empty() {
        client
            .return_leases(v1::ReturnLeasesRequest {
                worker_id,
                lease_ids: unusable,
                unusable: why,
            })
            .await?;
    }
    Ok(if units.is_empty() {
        Fetched::Empty(wait)
    } else {
        Fetched::Batch(Batch { units })
    })
}

/// Gives a batch that was never started back to the coordinator (a worker stopping):
/// its units are leased again at once instead of when their leases lapse. Sent with an
/// empty batch too, which tells the coordinator the worker is draining.
pub(crate) async fn give_back(client: &mut Client, worker_id: u64, batch: Batch) {
    let lease_ids: Vec<u64> = batch.lease_ids().collect();
    let n = lease_ids.len();
    match client
        .return_leases(v1::ReturnLeasesRequest {
            worker_id,
            lease_ids,
            unusable: String::new(),
        })
        .await
    {
        Ok(_) => tracing::info!(
            worker_id,
            leases = n,
            "draining: returned the units not started"
        ),
        Err(s) => {
            tracing::warn!(worker_id, leases = n, error = %s, "could not return the units not started; they lapse")
        }
    }
}

/// Returns the leases of units whose rendering panicked as unusable, with the first
/// panic's message: a fault of their scene, not of this worker, so the coordinator fails
/// the job after a few such returns instead of leasing the units forever
/// (docs/ARCHITECTURE.md §6).
pub(crate) async fn return_unusable(
    client: &mut Client,
    worker_id: u64,
    lease_ids: Vec<u64>,
    why: String,
) -> Result<(), Status> {
    client
        .return_leases(v1::ReturnLeasesRequest {
            worker_id,
            lease_ids,
            unusable: why,
        })
        .await
        .map(drop)
}
