//! Hosts in network namespaces for the multi-host suite (`tests/e2e/netns_partition.rs`): a
//! coordinator namespace joined to one namespace per worker by a veth pair, each pair its
//! own /24 (`10.77.N.1` on the coordinator's side, `10.77.N.2` on worker N's), so a
//! worker's link can be cut, restored or degraded without touching the others. The
//! namespaces have no route anywhere else: traffic stays between the test's own hosts.
//!
//! Needs root (CAP_NET_ADMIN) and iproute2's `ip`; [`unavailable`] says why not. Every
//! namespace is named `tsn-PID-TAG-HOST`; [`Hosts`] deletes its own when dropped (test
//! failures included, since a panic unwinds through the drop) and, when made, those of
//! earlier runs whose process is gone (a run killed before its drops ran).

use std::fs::File;
use std::os::fd::AsFd;
use std::path::Path;
use std::process::Command;

/// The name prefix of every namespace this module makes.
const PREFIX: &str = "tsn-";

/// Runs `ip ARGS`; `Err` with its stderr unless it succeeded.
pub fn ip(args: &[&str]) -> Result<(), String> {
    let o = Command::new("ip")
        .args(args)
        .output()
        .map_err(|e| format!("cannot run ip: {e}"))?;
    if o.status.success() {
        Ok(())
    } else {
        Err(format!(
            "ip {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&o.stderr).trim()
        ))
    }
}

/// Runs `ip ARGS` and fails the test unless it succeeded.
fn ip_ok(args: &[&str]) {
    ip(args).unwrap_or_else(|e| panic!("{e}"));
}

/// Why network namespaces cannot be made here (no `ip`, not root, no CAP_NET_ADMIN), or
/// `None` when they can: a probe namespace `tsn-PID-TAG-probe` is made and deleted.
pub fn unavailable(tag: &str) -> Option<String> {
    let probe = format!("{PREFIX}{}-{tag}-probe", std::process::id());
    match ip(&["netns", "add", &probe]) {
        Ok(()) => {
            let _ = ip(&["netns", "delete", &probe]);
            None
        }
        Err(e) => Some(e),
    }
}

/// Deletes namespaces `tsn-PID-...` whose process PID no longer runs.
fn remove_stale() {
    let Ok(entries) = std::fs::read_dir("/run/netns") else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().to_string();
        let Some(pid) = name
            .strip_prefix(PREFIX)
            .and_then(|rest| rest.split('-').next())
            .and_then(|p| p.parse::<u32>().ok())
        else {
            continue;
        };
        if !Path::new(&format!("/proc/{pid}")).exists() {
            eprintln!("removing stale network namespace {name}");
            let _ = ip(&["netns", "delete", &name]);
        }
    }
}

/// A coordinator namespace and `workers` worker namespaces, each joined to the
/// coordinator's by its own veth pair. Deleted when dropped.
pub struct Hosts {
    /// The coordinator's namespace.
    pub coordinator: String,
    /// The workers' namespaces.
    pub workers: Vec<String>,
}

impl Hosts {
    /// Makes the namespaces `tsn-PID-TAG-c` and `tsn-PID-TAG-wN` and their links
    /// (loopback up in each). `tag` must be unique among the suite's tests, which run in
    /// parallel in one process.
    pub fn new(tag: &str, workers: usize) -> Self {
        remove_stale();
        let base = format!("{PREFIX}{}-{tag}", std::process::id());
        let hosts = Self {
            coordinator: format!("{base}-c"),
            workers: (0..workers).map(|i| format!("{base}-w{i}")).collect(),
        };
        for ns in hosts.all() {
            // Left over by an earlier process with the same id.
            let _ = ip(&["netns", "delete", ns]);
        }
        // From here on a failure unwinds through `hosts`' drop, which deletes what exists.
        for ns in hosts.all() {
            ip_ok(&["netns", "add", ns]);
            ip_ok(&["-n", ns, "link", "set", "lo", "up"]);
        }
        for (i, w) in hosts.workers.iter().enumerate() {
            let (link, net) = (Self::link(i), i + 1);
            // Made inside the namespaces, so the names never meet the host's interfaces.
            ip_ok(&[
                "-n",
                &hosts.coordinator,
                "link",
                "add",
                &link,
                "type",
                "veth",
                "peer",
                "name",
                "eth0",
                "netns",
                w,
            ]);
            let c_addr = format!("10.77.{net}.1/24");
            let w_addr = format!("10.77.{net}.2/24");
            ip_ok(&[
                "-n",
                &hosts.coordinator,
                "addr",
                "add",
                &c_addr,
                "dev",
                &link,
            ]);
            ip_ok(&["-n", w, "addr", "add", &w_addr, "dev", "eth0"]);
            ip_ok(&["-n", &hosts.coordinator, "link", "set", &link, "up"]);
            ip_ok(&["-n", w, "link", "set", "eth0", "up"]);
        }
        hosts
    }

    fn all(&self) -> impl Iterator<Item = &String> {
        std::iter::once(&self.coordinator).chain(&self.workers)
    }

    /// The coordinator's end of worker `i`'s veth pair, in the coordinator's namespace.
    pub fn link(i: usize) -> String {
        format!("w{i}")
    }

    /// The coordinator's address as worker `i` reaches it.
    pub fn coordinator_addr(i: usize) -> String {
        format!("10.77.{}.1", i + 1)
    }

    /// `ip netns exec NS PROGRAM`: a command that runs in namespace `ns` (iproute2 execs
    /// the program in place, so the child's pid is the program's).
    pub fn exec(ns: &str, program: impl AsRef<std::ffi::OsStr>) -> Command {
        let mut c = Command::new("ip");
        c.args(["netns", "exec", ns]).arg(program);
        c
    }

    /// Cuts (`up = false`) or restores worker `i`'s link at the coordinator's end: the
    /// worker's side sees its carrier go, as when a cable is pulled, and packets either way
    /// are dropped; connections are not reset, so TCP retransmits once it is back.
    pub fn set_link(&self, i: usize, up: bool) {
        let state = if up { "up" } else { "down" };
        ip_ok(&[
            "-n",
            &self.coordinator,
            "link",
            "set",
            &Self::link(i),
            state,
        ]);
    }

    /// Runs `f` on a thread moved into namespace `ns` (setns(2)), so that the sockets it
    /// opens are that host's: how the test, in the host's namespace, talks to the
    /// coordinator's HTTP API on the coordinator's loopback.
    pub fn within<T: Send>(ns: &str, f: impl FnOnce() -> T + Send) -> T {
        std::thread::scope(|s| {
            s.spawn(|| {
                let file = File::open(format!("/run/netns/{ns}"))
                    .unwrap_or_else(|e| panic!("namespace {ns}: {e}"));
                rustix::thread::move_into_link_name_space(
                    file.as_fd(),
                    Some(rustix::thread::LinkNameSpaceType::Network),
                )
                .unwrap_or_else(|e| panic!("setns into {ns}: {e}"));
                f()
            })
            .join()
            .unwrap_or_else(|p| std::panic::resume_unwind(p))
        })
    }
}

/// How [`Hosts::degrade`] made a link worse: the first of these the kernel supports.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Degradation {
    /// tc netem: delay with jitter and random loss, on both ends' egress.
    Netem,
    /// No netem in this kernel: nftables drops packets at random (`numgen random`) on
    /// both ends' ingress, as a lossy wire would, and tc's token bucket filter (tbf)
    /// limits the rate, which queues packets and so delays them.
    NftLossAndTbf,
}

/// The loss both mechanisms apply in each direction, percent.
pub const LOSS_PERCENT: u32 = 5;

/// Runs `nft -f -` with `rules` in namespace `ns`.
fn nft(ns: &str, rules: &str) -> Result<(), String> {
    use std::io::Write;
    let mut child = Hosts::exec(ns, "nft")
        .args(["-f", "-"])
        .stdin(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .map_err(|e| format!("cannot run nft: {e}"))?;
    child
        .stdin
        .take()
        .unwrap()
        .write_all(rules.as_bytes())
        .map_err(|e| e.to_string())?;
    let o = child.wait_with_output().map_err(|e| e.to_string())?;
    if o.status.success() {
        Ok(())
    } else {
        Err(format!(
            "nft: {}",
            String::from_utf8_lossy(&o.stderr).trim()
        ))
    }
}

impl Hosts {
    /// Both ends of worker `i`'s link: (namespace, device).
    fn ends(&self, i: usize) -> [(String, String); 2] {
        [
            (self.coordinator.clone(), Self::link(i)),
            (self.workers[i].clone(), "eth0".to_string()),
        ]
    }

    /// Makes worker `i`'s link slow and lossy in both directions with real kernel
    /// mechanisms (never a userspace proxy): netem where the kernel has it, else
    /// nftables random drop plus tbf. Returns what it used, or why neither works.
    pub fn degrade(&self, i: usize) -> Result<Degradation, String> {
        let ends = self.ends(i);
        let loss = format!("{LOSS_PERCENT}%");
        let netem = |(ns, dev): &(String, String)| {
            ip(&[
                "netns", "exec", ns, "tc", "qdisc", "add", "dev", dev, "root", "netem", "delay",
                "20ms", "5ms", "loss", &loss,
            ])
        };
        let netem_err = match netem(&ends[0]) {
            Ok(()) => {
                netem(&ends[1])?;
                return Ok(Degradation::Netem);
            }
            Err(e) => e,
        };
        for (ns, dev) in &ends {
            // The netdev ingress hook sees packets as they come off the wire, before
            // routing or sockets: dropping there is loss on the link.
            nft(
                ns,
                &format!(
                    "table netdev tessera_loss {{\n chain ingress {{\n  type filter hook ingress device \"{dev}\" priority 0;\n  numgen random mod 100 < {LOSS_PERCENT} counter drop\n }}\n}}\n"
                ),
            )
            .map_err(|e| format!("no netem ({netem_err}); {e}"))?;
            // 1 Mbit/s with a 4 KiB bucket: a unit's result (3 KiB of pixels for a 16 x 16
            // tile, more for larger ones) queues for tens of milliseconds, and heartbeats
            // and leases behind it wait too (tbf's "overlimits" count them).
            ip(&[
                "netns", "exec", ns, "tc", "qdisc", "add", "dev", dev, "root", "tbf", "rate",
                "1mbit", "burst", "4kb", "latency", "400ms",
            ])?;
        }
        Ok(Degradation::NftLossAndTbf)
    }

    /// Packets dropped so far by [`Hosts::degrade`]'s nftables rules on worker `i`'s link
    /// (both ends), and tbf's drops and overlimits; for netem, tc's drop counts. Shown so
    /// a reader can see the link really was degraded.
    pub fn degradation_stats(&self, i: usize) -> String {
        // A command's stdout on one line ("" if it fails: nft has no table under netem).
        let one_line = |ns: &str, program: &str, args: &[&str]| {
            Self::exec(ns, program)
                .args(args)
                .output()
                .map(|o| {
                    String::from_utf8_lossy(&o.stdout)
                        .split_whitespace()
                        .collect::<Vec<_>>()
                        .join(" ")
                })
                .unwrap_or_default()
        };
        let mut out = Vec::new();
        for (ns, dev) in self.ends(i) {
            let tc = one_line(&ns, "tc", &["-s", "qdisc", "show", "dev", &dev]);
            let nft = one_line(&ns, "nft", &["list", "table", "netdev", "tessera_loss"]);
            out.push(format!("{ns}/{dev}: tc [{tc}] nft [{nft}]"));
        }
        out.join("\n")
    }
}

impl Drop for Hosts {
    fn drop(&mut self) {
        // Deleting a namespace deletes the veth ends in it, and so their peers.
        for ns in self.all() {
            if let Err(e) = ip(&["netns", "delete", ns]) {
                eprintln!("{e}");
            }
        }
    }
}
