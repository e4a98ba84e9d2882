//! `GET /metrics`: the farm's counters and gauges in the Prometheus text exposition
//! format (ARCHITECTURE.md §6).

use std::collections::BTreeMap;
use std::fmt::Write;

use super::Coordinator;
use crate::error::CoordResult;
use crate::state::{now_ms, Farm};

impl Coordinator {
    /// Prometheus text exposition of the farm's counters and gauges. The job counts are
    /// the store's (every job, also those finished before a restart).
    pub async fn metrics(&self) -> CoordResult<String> {
        let by_state: BTreeMap<&str, u64> = self
            .inner
            .store
            .count_jobs_by_state()
            .await?
            .into_iter()
            .map(|(st, n)| (st.as_str(), n))
            .collect();
        let now = now_ms();
        let lost_after = self.lost_after_ms();
        let farm = self.lock()?;
        let mut s = String::new();
        let _ = writeln!(
            s,
            "# HELP tessera_jobs Jobs in the store, by state.\n# TYPE tessera_jobs gauge"
        );
        for st in ["queued", "running", "done", "failed", "canceled"] {
            let _ = writeln!(
                s,
                "tessera_jobs{{state=\"{st}\"}} {}",
                by_state.get(st).unwrap_or(&0)
            );
        }
        let lost = farm
            .workers
            .values()
            .filter(|w| now.saturating_sub(w.last_seen_ms) > lost_after)
            .count();
        let forgotten = farm.forgotten;
        let _ = writeln!(s, "# HELP tessera_workers Listed workers (lost ones included).\n# TYPE tessera_workers gauge\ntessera_workers {}", farm.workers.len());
        let _ = writeln!(s, "# HELP tessera_workers_lost Listed workers that stopped heartbeating.\n# TYPE tessera_workers_lost gauge\ntessera_workers_lost {lost}");
        let _ = writeln!(s, "# HELP tessera_workers_forgotten_total Lost workers removed from the listing.\n# TYPE tessera_workers_forgotten_total counter\ntessera_workers_forgotten_total {}", forgotten.workers);
        let units: u64 =
            farm.workers.values().map(|w| w.units_done).sum::<u64>() + forgotten.units_done;
        let faults: u64 = farm.workers.values().map(|w| w.faults).sum::<u64>() + forgotten.faults;
        let _ = writeln!(s, "# HELP tessera_units_merged_total Units accepted from workers.\n# TYPE tessera_units_merged_total counter\ntessera_units_merged_total {units}");
        let render_seconds: f64 =
            farm.workers.values().map(|w| w.render_seconds).sum::<f64>() + forgotten.render_seconds;
        let _ = writeln!(s, "# HELP tessera_worker_render_seconds_total Seconds workers spent rendering the units they delivered, as they reported them (summed over their threads' units; `tessera bench-farm` compares it with the wall time).\n# TYPE tessera_worker_render_seconds_total counter\ntessera_worker_render_seconds_total {render_seconds:.3}");
        let pixel_passes: u64 =
            farm.workers.values().map(|w| w.pixel_passes).sum::<u64>() + forgotten.pixel_passes;
        let _ = writeln!(s, "# HELP tessera_worker_pixel_passes_total Pixel-passes workers traced for the units merged from them, as they reported them (pixels traced times passes: an adaptive lease names the pixels still wanted and the rest are not traced; 0 from workers that do not report it).\n# TYPE tessera_worker_pixel_passes_total counter\ntessera_worker_pixel_passes_total {pixel_passes}");
        let (waiting, woken, expired) = self.lease_wait_counts();
        let _ = writeln!(s, "# HELP tessera_lease_requests_waiting Lease requests held waiting for work (long polls of idle workers, LeaseRequest.wait_ms).\n# TYPE tessera_lease_requests_waiting gauge\ntessera_lease_requests_waiting {waiting}");
        let _ = writeln!(s, "# HELP tessera_lease_waits_total Waits of lease requests for work, by how they ended: woken when units may have become leasable, or at the request's deadline.\n# TYPE tessera_lease_waits_total counter\ntessera_lease_waits_total{{ended=\"woken\"}} {woken}\ntessera_lease_waits_total{{ended=\"deadline\"}} {expired}");
        let _ = writeln!(s, "# HELP tessera_worker_faults_total Refused results and mismatching duplicates.\n# TYPE tessera_worker_faults_total counter\ntessera_worker_faults_total {faults}");
        let quarantined = farm
            .workers
            .values()
            .filter(|w| w.quarantined.is_some())
            .count();
        let _ = writeln!(s, "# HELP tessera_workers_quarantined Listed workers quarantined by a spot check (no leases, results refused).\n# TYPE tessera_workers_quarantined gauge\ntessera_workers_quarantined {quarantined}");
        let spot = farm.spot;
        let _ = writeln!(s, "# HELP tessera_spot_checks_total Spot checks ended: match (two workers agreed), mismatch (a copy differed; its worker quarantined), alone (a worker alone re-rendered its own copy).\n# TYPE tessera_spot_checks_total counter");
        for (outcome, n) in [
            ("match", spot.matched),
            ("mismatch", spot.mismatched),
            ("alone", spot.alone),
        ] {
            let _ = writeln!(s, "tessera_spot_checks_total{{outcome=\"{outcome}\"}} {n}");
        }
        let (waiting, disputed) = farm.scheduler.spot_checks_waiting();
        let _ = writeln!(s, "# HELP tessera_spot_checks_waiting Spot-checked units with a copy held, waiting for another worker's copy.\n# TYPE tessera_spot_checks_waiting gauge\ntessera_spot_checks_waiting {waiting}");
        let _ = writeln!(s, "# HELP tessera_spot_checks_disputed Spot-checked units whose copies differ, waiting for a third worker to decide.\n# TYPE tessera_spot_checks_disputed gauge\ntessera_spot_checks_disputed {disputed}");
        let _ = writeln!(s, "# HELP tessera_workers_quarantined_total Workers quarantined since the coordinator started.\n# TYPE tessera_workers_quarantined_total counter\ntessera_workers_quarantined_total {}", spot.quarantined);
        let _ = writeln!(s, "# HELP tessera_quarantines_lifted_total Quarantines lifted by an operator (DELETE /api/v1/workers/NAME/quarantine) since the coordinator started.\n# TYPE tessera_quarantines_lifted_total counter\ntessera_quarantines_lifted_total {}", spot.lifted);
        let _ = writeln!(s, "# HELP tessera_tiles_reset_total Tiles dropped and merged again because a quarantined worker had merged units into them unverified.\n# TYPE tessera_tiles_reset_total counter\ntessera_tiles_reset_total {}", spot.tiles_reset);
        let _ = writeln!(s, "# HELP tessera_units_reverified_total Units of quarantined workers rendered again by others: identical (its copy was right) or differed (its corrupt copy had been merged and was repaired).\n# TYPE tessera_units_reverified_total counter");
        for (outcome, n) in [
            ("identical", spot.reverified_identical),
            ("differed", spot.reverified_differed),
        ] {
            let _ = writeln!(
                s,
                "tessera_units_reverified_total{{outcome=\"{outcome}\"}} {n}"
            );
        }
        let _ = writeln!(s, "# HELP tessera_units_unrepaired_total Unverified units of quarantined workers that could not be rendered again (their frame or job had finished).\n# TYPE tessera_units_unrepaired_total counter\ntessera_units_unrepaired_total {}", spot.unrepaired);
        let _ = writeln!(s, "# HELP tessera_leases_expired_total Leases that lapsed without a result; their units were leased again.\n# TYPE tessera_leases_expired_total counter\ntessera_leases_expired_total {}", farm.leases_expired);
        let _ = writeln!(s, "# HELP tessera_leases_outstanding Leases currently held by workers.\n# TYPE tessera_leases_outstanding gauge\ntessera_leases_outstanding {}", farm.scheduler.leases().count());
        let (queued, leased) = units_waiting_and_leased(&farm);
        let _ = writeln!(s, "# HELP tessera_units_queued Units of queued and running jobs waiting to be leased (the queue depth workers autoscale on; for adaptive jobs an upper bound).\n# TYPE tessera_units_queued gauge\ntessera_units_queued {queued}");
        let _ = writeln!(s, "# HELP tessera_units_leased Units of queued and running jobs leased to workers now.\n# TYPE tessera_units_leased gauge\ntessera_units_leased {leased}");
        let _ = writeln!(s, "# HELP tessera_merge_state_bytes Bytes of per-pixel merge state in memory (the frames in progress of every job, ARCHITECTURE.md section 6).\n# TYPE tessera_merge_state_bytes gauge\ntessera_merge_state_bytes {}", farm.scheduler.resident_bytes());
        let _ = writeln!(s, "# HELP tessera_merge_state_budget_bytes The merge state's budget (--memory-budget); frames that do not fit wait.\n# TYPE tessera_merge_state_budget_bytes gauge\ntessera_merge_state_budget_bytes {}", self.inner.cfg.memory_budget);
        let _ = writeln!(s, "# HELP tessera_worker_paths_per_second Last reported throughput per worker.\n# TYPE tessera_worker_paths_per_second gauge");
        // One series per name: names need not be unique (worker.proto), and a scrape
        // with two samples of one series is refused; workers sharing a name are summed.
        let mut by_name: std::collections::BTreeMap<&str, f64> = std::collections::BTreeMap::new();
        for w in farm.workers.values() {
            *by_name.entry(w.name.as_str()).or_default() += w.paths_per_second;
        }
        for (name, paths_per_second) in by_name {
            let _ = writeln!(
                s,
                "tessera_worker_paths_per_second{{worker={name:?}}} {paths_per_second}"
            );
        }
        let _ = writeln!(s, "# HELP tessera_uptime_seconds Seconds since the coordinator started.\n# TYPE tessera_uptime_seconds gauge\ntessera_uptime_seconds {:.3}", self.uptime_seconds());
        Ok(s)
    }
}

/// Units of the jobs still to finish (queued or running) that wait to be leased, and
/// those leased now: from the scheduler's [`Progress`](tessera_farm::Progress) of each
/// unfinished job (one walk over its frames per scrape). A canceled, failed or done job
/// counts nothing. An adaptive job
/// may stop before its planned units, so its waiting count is an upper bound.
fn units_waiting_and_leased(farm: &Farm) -> (u64, u64) {
    farm.runtime
        .iter()
        .filter(|(_, rt)| !rt.state.is_terminal())
        .filter_map(|(&id, _)| farm.scheduler.progress(id))
        .fold((0, 0), |(queued, leased), p| {
            let waiting = p.units_total.saturating_sub(p.units_done + p.units_leased);
            (queued + waiting, leased + p.units_leased)
        })
}
