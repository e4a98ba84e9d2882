//! `GET /metrics`: the farm's counters and gauges in the Prometheus text exposition
//! format (ARCHITECTURE.md §6).

use std::collections::BTreeMap;
use std::fmt::Write;

use super::Coordinator;
use crate::error::CoordResult;

impl Coordinator {
    /// Prometheus text exposition of the farm's counters and gauges.
    pub fn metrics(&self) -> CoordResult<String> {
        let farm = self.lock()?;
        let mut by_state: BTreeMap<&str, u64> = BTreeMap::new();
        for rt in farm.runtime.values() {
            *by_state.entry(rt.state.as_str()).or_default() += 1;
        }
        let mut s = String::new();
        let _ = writeln!(
            s,
            "# HELP tessera_jobs Jobs known to this coordinator run, by state.\n# TYPE tessera_jobs gauge"
        );
        for st in ["queued", "running", "done", "failed", "canceled"] {
            let _ = writeln!(
                s,
                "tessera_jobs{{state=\"{st}\"}} {}",
                by_state.get(st).unwrap_or(&0)
            );
        }
        let _ = writeln!(s, "# HELP tessera_workers Registered workers.\n# TYPE tessera_workers gauge\ntessera_workers {}", farm.workers.len());
        let units: u64 = farm.workers.values().map(|w| w.units_done).sum();
        let faults: u64 = farm.workers.values().map(|w| w.faults).sum();
        let _ = writeln!(s, "# HELP tessera_units_merged_total Units accepted from workers.\n# TYPE tessera_units_merged_total counter\ntessera_units_merged_total {units}");
        let _ = writeln!(s, "# HELP tessera_worker_faults_total Refused results and mismatching duplicates.\n# TYPE tessera_worker_faults_total counter\ntessera_worker_faults_total {faults}");
        let _ = writeln!(s, "# HELP tessera_leases_outstanding Leases currently held by workers.\n# TYPE tessera_leases_outstanding gauge\ntessera_leases_outstanding {}", farm.scheduler.leases().count());
        let _ = writeln!(s, "# HELP tessera_worker_paths_per_second Last reported throughput per worker.\n# TYPE tessera_worker_paths_per_second gauge");
        for w in farm.workers.values() {
            let _ = writeln!(
                s,
                "tessera_worker_paths_per_second{{worker={:?}}} {}",
                w.name, w.paths_per_second
            );
        }
        let _ = writeln!(s, "# HELP tessera_uptime_seconds Seconds since the coordinator started.\n# TYPE tessera_uptime_seconds gauge\ntessera_uptime_seconds {:.3}", self.uptime_seconds());
        Ok(s)
    }
}
