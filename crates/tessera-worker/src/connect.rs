//! Reaching a coordinator: its endpoint (with TLS for `https://`), the bearer token on
//! every request, and the order in which a worker tries its coordinators and how long it
//! waits when every one failed ([`Failover`]).

use crate::{WorkerError, WorkerTls};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tessera_proto::v1;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, Endpoint};
use tonic::{Request, Status};

/// Adds the bearer token to every request, and the session secret of the connection's
/// registration once there is one (worker.proto, "Sessions").
#[derive(Clone)]
pub(crate) struct Auth(Option<MetadataValue<Ascii>>, Session);

/// The session secret of a connection's registration, shared by the clones of its client.
type Session = Arc<Mutex<Option<MetadataValue<Ascii>>>>;

impl Auth {
    /// `Bearer TOKEN`, or nothing without a token; refuses a token that cannot travel in
    /// a header value (a control character).
    pub(crate) fn bearer(token: Option<&str>) -> Result<Self, WorkerError> {
        match token {
            Some(t) => format!("Bearer {t}")
                .parse()
                .map(|v| Self(Some(v), Session::default()))
                .map_err(|_| WorkerError::Config("the token must be printable ASCII".into())),
            None => Ok(Self(None, Session::default())),
        }
    }

    /// The same token with no session yet: one per connection, whose registration sets
    /// it ([`Auth::set_session`]).
    pub(crate) fn for_connection(&self) -> Self {
        Self(self.0.clone(), Session::default())
    }

    /// Sends `secret` (the coordinator's answer to Register) with every later request of
    /// this connection.
    pub(crate) fn set_session(&self, secret: &str) -> Result<(), Status> {
        let v = MetadataValue::try_from(secret)
            .map_err(|_| Status::internal("the coordinator sent a session that is not ASCII"))?;
        if let Ok(mut s) = self.1.lock() {
            *s = Some(v);
        }
        Ok(())
    }
}

impl tonic::service::Interceptor for Auth {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(v) = &self.0 {
            req.metadata_mut().insert("authorization", v.clone());
        }
        if let Some(v) = self.1.lock().ok().and_then(|s| s.clone()) {
            req.metadata_mut()
                .insert(tessera_proto::SESSION_METADATA, v);
        }
        Ok(req)
    }
}

/// A connection to one coordinator's worker service.
pub(crate) type Client =
    v1::worker_service_client::WorkerServiceClient<InterceptedService<Channel, Auth>>;

/// The client of a connected channel, adding the token to every request.
pub(crate) fn client(channel: Channel, auth: &Auth) -> Client {
    v1::worker_service_client::WorkerServiceClient::with_interceptor(channel, auth.clone())
}

/// The endpoints of every coordinator URL, in order, with `tls` for `https://` ones.
pub(crate) fn endpoints(
    urls: &[String],
    tls: Option<&WorkerTls>,
) -> Result<Vec<Endpoint>, WorkerError> {
    urls.iter().map(|url| endpoint(url, tls)).collect()
}

/// The endpoint of one coordinator URL, with TLS for `https://` (and only then).
fn endpoint(url: &str, tls: Option<&WorkerTls>) -> Result<Endpoint, WorkerError> {
    let mut endpoint = Endpoint::from_shared(url.to_string())
        .map_err(|e| WorkerError::Config(format!("coordinator URL {url:?}: {e}")))?
        .connect_timeout(Duration::from_secs(5))
        // HTTP/2 pings find a connection whose peer vanished without closing it (a cut
        // link, a frozen host): without them a call waits on TCP retransmission for many
        // minutes instead of failing over to the next coordinator.
        .http2_keep_alive_interval(Duration::from_secs(10))
        .keep_alive_timeout(Duration::from_secs(10))
        .keep_alive_while_idle(true)
        .tcp_nodelay(true);
    let https = url.starts_with("https://");
    match (tls, https) {
        (Some(tls), true) => {
            endpoint = endpoint
                .tls_config(tls.client_config())
                .map_err(|e| WorkerError::Config(format!("TLS: {e}")))?;
        }
        (Some(_), false) => {
            return Err(WorkerError::Config(format!(
                "TLS files were given but the coordinator URL {url:?} is not https://"
            )))
        }
        (None, true) => {
            return Err(WorkerError::Config(format!(
                "the coordinator URL {url:?} is https://: give the CA to trust (--tls-ca)"
            )))
        }
        (None, false) => {}
    }
    Ok(endpoint)
}

/// An error and its causes, `: `-separated (tonic's transport errors hide the cause).
pub(crate) fn error_chain(e: &dyn std::error::Error) -> String {
    let mut out = e.to_string();
    let mut cur = e.source();
    while let Some(c) = cur {
        out.push_str(": ");
        out.push_str(&c.to_string());
        cur = c.source();
    }
    out
}

/// The pause after the first round of failures.
const FIRST_BACKOFF: Duration = Duration::from_millis(100);
/// The longest pause between rounds.
const MAX_BACKOFF: Duration = Duration::from_secs(5);

/// Which coordinator to try next, and how long to wait first.
///
/// After a failed attempt the next coordinator is tried at once (it may be the active
/// one); only when every one failed in a row does the worker pause, 100 ms and doubling
/// up to 5 s. A session that got as far as registering starts the count and the pauses
/// over.
#[derive(Debug)]
pub(crate) struct Failover {
    /// How many coordinators there are (at least one).
    count: usize,
    /// The index of the one to try next.
    next: usize,
    /// Attempts that failed in a row in this round.
    failed: usize,
    /// The pause after the round, when every coordinator failed.
    backoff: Duration,
}

impl Failover {
    /// Starts with the first of `count` coordinators (at least one).
    pub(crate) fn new(count: usize) -> Self {
        Self {
            count: count.max(1),
            next: 0,
            failed: 0,
            backoff: FIRST_BACKOFF,
        }
    }

    /// The index of the coordinator to try now.
    pub(crate) fn current(&self) -> usize {
        self.next
    }

    /// Whether the pauses have grown to their longest: failures are then worth a
    /// warning, not only a debug line (a refused TLS handshake looks like a coordinator
    /// that is away).
    pub(crate) fn waited_longest(&self) -> bool {
        self.backoff >= MAX_BACKOFF
    }

    /// Records that the attempt at [`Failover::current`] ended (`registered`: after a
    /// session that got as far as registering) and moves to the next coordinator; the
    /// pause to take before trying it, if every coordinator failed in a row.
    pub(crate) fn ended(&mut self, registered: bool) -> Option<Duration> {
        if registered {
            // It served for a while: start over with short waits.
            self.failed = 0;
            self.backoff = FIRST_BACKOFF;
        }
        self.failed += 1;
        self.next = (self.next + 1) % self.count;
        if self.failed < self.count {
            // Another coordinator may be the active one: try it at once.
            return None;
        }
        self.failed = 0;
        let pause = self.backoff;
        self.backoff = (self.backoff * 2).min(MAX_BACKOFF);
        Some(pause)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(ms: u64) -> Duration {
        Duration::from_millis(ms)
    }

    #[test]
    fn one_coordinator_backs_off_doubling_up_to_five_seconds() {
        let mut f = Failover::new(1);
        let pauses: Vec<_> = (0..8).map(|_| f.ended(false)).collect();
        let expected = [100, 200, 400, 800, 1600, 3200, 5000, 5000].map(|m| Some(ms(m)));
        assert_eq!(pauses, expected);
        assert_eq!(f.current(), 0);
        assert!(f.waited_longest());
    }

    #[test]
    fn the_next_coordinator_is_tried_at_once_and_a_round_of_failures_pauses() {
        let mut f = Failover::new(3);
        assert_eq!(f.current(), 0);
        assert_eq!(f.ended(false), None);
        assert_eq!(f.current(), 1);
        assert_eq!(f.ended(false), None);
        assert_eq!(f.current(), 2);
        assert_eq!(f.ended(false), Some(ms(100)));
        assert_eq!(f.current(), 0);
        // The next round pauses twice as long.
        assert_eq!(f.ended(false), None);
        assert_eq!(f.ended(false), None);
        assert_eq!(f.ended(false), Some(ms(200)));
        assert!(!f.waited_longest());
    }

    #[test]
    fn a_registered_session_starts_the_round_and_the_pauses_over() {
        let mut f = Failover::new(2);
        // Seven failed rounds: 100 ms doubled six times is past 5 s.
        for _ in 0..14 {
            f.ended(false);
        }
        assert!(f.waited_longest());
        // Coordinator 0 served, then broke: coordinator 1 is tried at once, and a failed
        // round after that pauses the shortest time again.
        assert_eq!(f.current(), 0);
        assert_eq!(f.ended(true), None);
        assert!(!f.waited_longest());
        assert_eq!(f.current(), 1);
        assert_eq!(f.ended(false), Some(ms(100)));
    }

    #[test]
    fn a_token_becomes_a_bearer_header_and_one_with_a_control_character_is_refused() {
        let Auth(Some(v), _) = Auth::bearer(Some("s3cret")).unwrap() else {
            panic!("no header");
        };
        assert_eq!(v.to_str().unwrap(), "Bearer s3cret");
        assert!(Auth::bearer(None).unwrap().0.is_none());
        assert!(matches!(
            Auth::bearer(Some("line\nbreak")),
            Err(WorkerError::Config(_))
        ));
    }

    #[test]
    fn tls_goes_with_https_only() {
        let url = |u: &str| vec![u.to_string()];
        assert!(endpoints(&url("http://127.0.0.1:1"), None).is_ok());
        let e = endpoints(&url("https://127.0.0.1:1"), None).unwrap_err();
        assert!(e.to_string().contains("--tls-ca"), "{e}");
        let tls = WorkerTls {
            ca_pem: Vec::new(),
            identity: None,
            files: None,
        };
        let e = endpoints(&url("http://127.0.0.1:1"), Some(&tls)).unwrap_err();
        assert!(e.to_string().contains("not https://"), "{e}");
        assert!(endpoints(&url("not a url"), None).is_err());
    }
}
