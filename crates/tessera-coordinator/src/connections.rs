//! The HTTP port's connections: the accept loop, the connection limits and the read and
//! idle timeouts that keep slow or idle clients from holding the coordinator
//! (ARCHITECTURE.md §6, docs/limits.md).
//!
//! axum's own `serve` has no timeouts and no limits, so the HTTP port runs this loop over
//! hyper's HTTP/1.1 connection instead. Per connection:
//!
//! - **Admission.** At most [`HttpLimits::max_connections`] connections are open at once,
//!   and at most [`HttpLimits::max_connections_per_address`] from one IP address. A
//!   connection beyond either limit gets a one-shot `503` (written without waiting) and is
//!   closed; nothing of it is read.
//! - **Header timeout.** A request's head must arrive whole within
//!   [`HttpLimits::header_timeout`], counted from the connection's opening for the first
//!   request and from the request's first byte for later ones (slowloris).
//! - **Body timeout.** A request body must arrive within [`HttpLimits::body_timeout`] of
//!   its head, extended by one second per [`HttpLimits::body_min_rate`] bytes received, so
//!   a large upload at a reasonable rate is never cut and a trickled body always is; the
//!   answer is `408` and the connection is closed.
//! - **Idle timeout.** A keep-alive connection with no request in flight and no bytes in
//!   either direction for [`HttpLimits::idle_timeout`] is closed. The same rule closes a
//!   connection whose client stopped reading its response.
//!
//! A request whose handler is running is never cut by the header or idle timeouts (its
//! body has its own). On shutdown the loop stops accepting, asks every connection to
//! finish its request in flight and close (hyper's graceful shutdown), and returns when
//! all are closed; the caller bounds that wait.

use std::collections::HashMap;
use std::error::Error as StdError;
use std::future::Future;
use std::io;
use std::net::{IpAddr, SocketAddr};
use std::pin::Pin;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::Bytes;
use axum::http::Request;
use axum::Router;
use http_body::{Body, Frame, SizeHint};
use hyper_util::rt::TokioIo;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{watch, Notify, OwnedSemaphorePermit, Semaphore};
use tokio::time::Instant;

type BoxError = Box<dyn StdError + Send + Sync>;

/// The HTTP port's connection limits and timeouts (module documentation; defaults in
/// [`HttpLimits::default`], flags of `tessera coordinator` and `tessera serve`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct HttpLimits {
    /// A request head must arrive within this.
    pub header_timeout: Duration,
    /// A request body must arrive within this of its head (plus the rate allowance).
    pub body_timeout: Duration,
    /// Bytes per second of body that earn one more second of body timeout (0: none), so
    /// that large scene uploads over a slow link are not cut.
    pub body_min_rate: u64,
    /// A connection without a request in flight and without traffic is closed after this.
    pub idle_timeout: Duration,
    /// Most connections open at once.
    pub max_connections: usize,
    /// Most connections open at once from one IP address.
    pub max_connections_per_address: usize,
}

impl Default for HttpLimits {
    /// Header 10 s, body 30 s plus one second per 64 KiB, idle 60 s, 1024 connections,
    /// 64 per address.
    fn default() -> Self {
        Self {
            header_timeout: Duration::from_secs(10),
            body_timeout: Duration::from_secs(30),
            body_min_rate: 64 * 1024,
            idle_timeout: Duration::from_secs(60),
            max_connections: 1024,
            max_connections_per_address: 64,
        }
    }
}

/// Connection counters of the HTTP port, exposed in `/metrics`.
#[derive(Debug, Default)]
pub struct ConnectionStats {
    open: AtomicU64,
    accepted: AtomicU64,
    refused_overall: AtomicU64,
    refused_per_address: AtomicU64,
    header_timeouts: AtomicU64,
    idle_timeouts: AtomicU64,
    body_timeouts: AtomicU64,
}

impl ConnectionStats {
    /// The counters in the Prometheus text exposition format.
    pub fn prometheus(&self) -> String {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        format!(
            "# HELP tessera_http_connections_open Open HTTP connections.\n\
             # TYPE tessera_http_connections_open gauge\n\
             tessera_http_connections_open {}\n\
             # HELP tessera_http_connections_accepted_total HTTP connections admitted.\n\
             # TYPE tessera_http_connections_accepted_total counter\n\
             tessera_http_connections_accepted_total {}\n\
             # HELP tessera_http_connections_refused_total HTTP connections refused at a connection limit.\n\
             # TYPE tessera_http_connections_refused_total counter\n\
             tessera_http_connections_refused_total{{limit=\"overall\"}} {}\n\
             tessera_http_connections_refused_total{{limit=\"per_address\"}} {}\n\
             # HELP tessera_http_timeouts_total HTTP connections closed or requests cut by a timeout.\n\
             # TYPE tessera_http_timeouts_total counter\n\
             tessera_http_timeouts_total{{timeout=\"header\"}} {}\n\
             tessera_http_timeouts_total{{timeout=\"body\"}} {}\n\
             tessera_http_timeouts_total{{timeout=\"idle\"}} {}\n",
            get(&self.open),
            get(&self.accepted),
            get(&self.refused_overall),
            get(&self.refused_per_address),
            get(&self.header_timeouts),
            get(&self.body_timeouts),
            get(&self.idle_timeouts),
        )
    }
}

/// Serves `router` on `listener` under `limits` until `stop` completes, then lets every
/// connection finish its request in flight and returns once all are closed.
///
/// With `tls`, every connection first completes a TLS handshake within the header timeout
/// (counted as a header timeout when it does not), with the certificate in force when it
/// was accepted (`crate::tls`); a refused connection is then closed without an answer.
pub async fn serve_http(
    listener: TcpListener,
    router: Router,
    limits: HttpLimits,
    stats: Arc<ConnectionStats>,
    tls: Option<Arc<crate::tls::ServerTls>>,
    stop: impl Future<Output = ()>,
) {
    let admission = Arc::new(Admission::new(limits));
    // Every connection holds a receiver; `closed()` completes when all are gone.
    let (stop_tx, stop_rx) = watch::channel(false);
    tokio::pin!(stop);
    loop {
        let (stream, peer) = tokio::select! {
            _ = &mut stop => break,
            accepted = listener.accept() => match accepted {
                Ok(a) => a,
                Err(e) => {
                    // Out of file descriptors, or a connection reset before it was
                    // accepted: not fatal. Pause so that a full descriptor table does not
                    // spin the loop.
                    tracing::warn!(error = %e, "cannot accept an HTTP connection");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
        };
        let ticket = match admission.admit(peer.ip()) {
            Ok(t) => t,
            Err(limit) => {
                let counter = match limit {
                    Limit::Overall => &stats.refused_overall,
                    Limit::PerAddress => &stats.refused_per_address,
                };
                counter.fetch_add(1, Ordering::Relaxed);
                tracing::debug!(peer = %peer, limit = limit.as_str(), "HTTP connection refused");
                if tls.is_none() {
                    refuse(&stream, limit);
                }
                continue;
            }
        };
        stats.accepted.fetch_add(1, Ordering::Relaxed);
        let _ = stream.set_nodelay(true);
        let conn = Connection {
            router: router.clone(),
            limits,
            stats: stats.clone(),
            peer,
        };
        let stop_rx = stop_rx.clone();
        let acceptor = tls.as_ref().map(|t| t.http_acceptor());
        tokio::spawn(async move {
            match acceptor {
                None => conn.serve(stream, stop_rx).await,
                Some(acceptor) => {
                    match tokio::time::timeout(limits.header_timeout, acceptor.accept(stream)).await
                    {
                        Ok(Ok(stream)) => conn.serve(stream, stop_rx).await,
                        Ok(Err(e)) => {
                            tracing::debug!(peer = %peer, error = %e, "HTTP TLS handshake refused")
                        }
                        Err(_) => {
                            conn.stats.header_timeouts.fetch_add(1, Ordering::Relaxed);
                            tracing::debug!(peer = %peer, "HTTP TLS handshake timed out");
                        }
                    }
                }
            }
            drop(ticket);
        });
    }
    drop(listener);
    let _ = stop_tx.send(true);
    drop(stop_rx);
    stop_tx.closed().await;
}

/// Writes a short 503 to a refused connection if the socket takes it at once (never
/// waits: a refused client gets no time), then closes it.
fn refuse(stream: &TcpStream, limit: Limit) {
    let body = format!(
        "{{\"error\":{{\"code\":\"unavailable\",\"message\":\"too many connections ({}); try again later\"}}}}",
        limit.as_str().replace('_', " ")
    );
    let resp = format!(
        "HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/json\r\ncontent-length: {}\r\nconnection: close\r\nretry-after: 1\r\n\r\n{body}",
        body.len()
    );
    let _ = stream.try_write(resp.as_bytes());
}

/// Which connection limit refused a connection.
#[derive(Clone, Copy, Debug)]
enum Limit {
    Overall,
    PerAddress,
}

impl Limit {
    fn as_str(self) -> &'static str {
        match self {
            Self::Overall => "overall",
            Self::PerAddress => "per_address",
        }
    }
}

/// The two connection limits.
struct Admission {
    overall: Arc<Semaphore>,
    per_address: Mutex<HashMap<IpAddr, usize>>,
    max_per_address: usize,
}

/// An admitted connection's place under both limits, given back on drop.
struct Ticket {
    _permit: OwnedSemaphorePermit,
    admission: Arc<Admission>,
    ip: IpAddr,
}

impl Admission {
    fn new(limits: HttpLimits) -> Self {
        Self {
            overall: Arc::new(Semaphore::new(limits.max_connections.max(1))),
            per_address: Mutex::new(HashMap::new()),
            max_per_address: limits.max_connections_per_address.max(1),
        }
    }

    fn admit(self: &Arc<Self>, ip: IpAddr) -> Result<Ticket, Limit> {
        let permit = self
            .overall
            .clone()
            .try_acquire_owned()
            .map_err(|_| Limit::Overall)?;
        let mut map = self.per_address.lock().map_err(|_| Limit::Overall)?;
        let n = map.entry(ip).or_insert(0);
        if *n >= self.max_per_address {
            return Err(Limit::PerAddress);
        }
        *n += 1;
        Ok(Ticket {
            _permit: permit,
            admission: self.clone(),
            ip,
        })
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        if let Ok(mut map) = self.admission.per_address.lock() {
            if let Some(n) = map.get_mut(&self.ip) {
                *n -= 1;
                if *n == 0 {
                    map.remove(&self.ip);
                }
            }
        }
    }
}

/// One admitted connection.
struct Connection {
    router: Router,
    limits: HttpLimits,
    stats: Arc<ConnectionStats>,
    peer: SocketAddr,
}

impl Connection {
    async fn serve<S>(self, stream: S, mut stop: watch::Receiver<bool>)
    where
        S: AsyncRead + AsyncWrite + Unpin + Send + 'static,
    {
        let stats = self.stats.clone();
        stats.open.fetch_add(1, Ordering::Relaxed);
        let clock = Arc::new(Clock::new());
        let io = TokioIo::new(Watched {
            inner: stream,
            clock: clock.clone(),
        });
        let (router, limits, body_stats) = (self.router, self.limits, stats.clone());
        let req_clock = clock.clone();
        let service = hyper::service::service_fn(move |req: Request<hyper::body::Incoming>| {
            let in_flight = InFlight::begin(req_clock.clone());
            let req = req.map(|b| TimedBody::new(b, limits, body_stats.clone()));
            let mut router = router.clone();
            async move {
                let resp = tower_service::Service::call(&mut router, req).await;
                drop(in_flight);
                resp
            }
        });
        // No hyper header timeout: it would also cut idle keep-alive connections after the
        // header timeout; the clock below applies the two separately.
        let conn = hyper::server::conn::http1::Builder::new()
            .keep_alive(true)
            .serve_connection(io, service);
        tokio::pin!(conn);
        let mut draining = false;
        loop {
            let wake = clock.next_check(&limits);
            tokio::select! {
                r = conn.as_mut() => {
                    if let Err(e) = r {
                        tracing::debug!(peer = %self.peer, error = %e, "HTTP connection ended");
                    }
                    break;
                }
                _ = stop.changed(), if !draining => {
                    conn.as_mut().graceful_shutdown();
                    draining = true;
                }
                _ = clock.changed.notified() => {}
                _ = tokio::time::sleep_until(wake) => {
                    if let Some(t) = clock.expired(&limits) {
                        let counter = match t {
                            Timeout::Header => &stats.header_timeouts,
                            Timeout::Idle => &stats.idle_timeouts,
                        };
                        counter.fetch_add(1, Ordering::Relaxed);
                        tracing::debug!(peer = %self.peer, timeout = t.as_str(), "HTTP connection timed out");
                        // Dropping the connection closes the socket.
                        break;
                    }
                }
            }
        }
        stats.open.fetch_sub(1, Ordering::Relaxed);
    }
}

/// Which connection timeout closed a connection.
#[derive(Clone, Copy, Debug)]
enum Timeout {
    Header,
    Idle,
}

impl Timeout {
    fn as_str(self) -> &'static str {
        match self {
            Self::Header => "header",
            Self::Idle => "idle",
        }
    }
}

/// What a connection is doing, as its timeouts need it: times are milliseconds since the
/// connection opened.
struct Clock {
    opened: Instant,
    /// Last byte read or written.
    last_io: AtomicU64,
    /// When the head now being read began, plus one (0: no head being read).
    head_since: AtomicU64,
    /// Requests whose handler is running.
    in_flight: AtomicU32,
    /// Poked when a head begins or a request starts or ends, to re-arm the timer.
    changed: Notify,
}

impl Clock {
    fn new() -> Self {
        Self {
            opened: Instant::now(),
            last_io: AtomicU64::new(0),
            // The first request's head is awaited from the connection's opening.
            head_since: AtomicU64::new(1),
            in_flight: AtomicU32::new(0),
            changed: Notify::new(),
        }
    }

    fn now(&self) -> u64 {
        self.opened.elapsed().as_millis() as u64
    }

    fn read(&self) {
        let now = self.now();
        self.last_io.store(now, Ordering::Relaxed);
        if self.in_flight.load(Ordering::Acquire) == 0
            && self
                .head_since
                .compare_exchange(0, now + 1, Ordering::AcqRel, Ordering::Relaxed)
                .is_ok()
        {
            self.changed.notify_one();
        }
    }

    fn wrote(&self) {
        self.last_io.store(self.now(), Ordering::Relaxed);
    }

    /// The timeout that has run out, if any.
    fn expired(&self, limits: &HttpLimits) -> Option<Timeout> {
        if self.in_flight.load(Ordering::Acquire) > 0 {
            return None;
        }
        let now = self.now();
        match self.head_since.load(Ordering::Acquire) {
            0 => (now.saturating_sub(self.last_io.load(Ordering::Relaxed))
                >= ms(limits.idle_timeout))
            .then_some(Timeout::Idle),
            since => (now.saturating_sub(since - 1) >= ms(limits.header_timeout))
                .then_some(Timeout::Header),
        }
    }

    /// When to look again: the running timeout's end, or (a handler running) after the
    /// shorter timeout, since requests end without waking the timer late.
    fn next_check(&self, limits: &HttpLimits) -> Instant {
        let at = if self.in_flight.load(Ordering::Acquire) > 0 {
            self.now() + ms(limits.header_timeout.min(limits.idle_timeout))
        } else {
            match self.head_since.load(Ordering::Acquire) {
                0 => self.last_io.load(Ordering::Relaxed) + ms(limits.idle_timeout),
                since => since - 1 + ms(limits.header_timeout),
            }
        };
        self.opened + Duration::from_millis(at)
    }
}

fn ms(d: Duration) -> u64 {
    d.as_millis().min(u128::from(u64::MAX / 4)) as u64
}

/// A request's handler running, from its head's arrival until its response is ready.
struct InFlight(Arc<Clock>);

impl InFlight {
    fn begin(clock: Arc<Clock>) -> Self {
        clock.in_flight.fetch_add(1, Ordering::AcqRel);
        clock.head_since.store(0, Ordering::Release);
        clock.changed.notify_one();
        Self(clock)
    }
}

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.wrote();
        self.0.in_flight.fetch_sub(1, Ordering::AcqRel);
        self.0.changed.notify_one();
    }
}

/// The connection's stream (TCP, or TLS over TCP), recording its traffic on the
/// connection's [`Clock`].
struct Watched<S> {
    inner: S,
    clock: Arc<Clock>,
}

impl<S: AsyncRead + Unpin> AsyncRead for Watched<S> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let before = buf.filled().len();
        let r = Pin::new(&mut self.inner).poll_read(cx, buf);
        if matches!(r, Poll::Ready(Ok(()))) && buf.filled().len() > before {
            self.clock.read();
        }
        r
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for Watched<S> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let r = Pin::new(&mut self.inner).poll_write(cx, buf);
        if matches!(r, Poll::Ready(Ok(n)) if n > 0) {
            self.clock.wrote();
        }
        r
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let r = Pin::new(&mut self.inner).poll_write_vectored(cx, bufs);
        if matches!(r, Poll::Ready(Ok(n)) if n > 0) {
            self.clock.wrote();
        }
        r
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

/// The error of a request body that did not arrive in time; the handler answers `408`
/// ([`is_body_timeout`]).
#[derive(Debug, thiserror::Error)]
#[error("the request body did not arrive within {0:?}")]
pub struct BodyTimedOut(Duration);

/// Whether `e`, or an error it was caused by, is a [`BodyTimedOut`].
pub fn is_body_timeout(e: &(dyn StdError + 'static)) -> bool {
    let mut cur = Some(e);
    while let Some(e) = cur {
        if e.is::<BodyTimedOut>() {
            return true;
        }
        cur = e.source();
    }
    false
}

/// A request body with a deadline: [`HttpLimits::body_timeout`] after the head, plus one
/// second per [`HttpLimits::body_min_rate`] bytes received.
struct TimedBody<B> {
    inner: B,
    sleep: Pin<Box<tokio::time::Sleep>>,
    start: Instant,
    limits: HttpLimits,
    received: u64,
    stats: Arc<ConnectionStats>,
}

impl<B> TimedBody<B> {
    fn new(inner: B, limits: HttpLimits, stats: Arc<ConnectionStats>) -> Self {
        let start = Instant::now();
        Self {
            inner,
            sleep: Box::pin(tokio::time::sleep_until(start + limits.body_timeout)),
            start,
            limits,
            received: 0,
            stats,
        }
    }

    fn allowed(&self) -> Duration {
        let extra = match self.limits.body_min_rate {
            0 => Duration::ZERO,
            rate => Duration::from_secs_f64(self.received as f64 / rate as f64),
        };
        self.limits.body_timeout.saturating_add(extra)
    }
}

impl<B> Body for TimedBody<B>
where
    B: Body<Data = Bytes> + Unpin,
    B::Error: Into<BoxError>,
{
    type Data = Bytes;
    type Error = BoxError;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, BoxError>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(data) = frame.data_ref() {
                    if this.limits.body_min_rate > 0 && !data.is_empty() {
                        this.received += data.len() as u64;
                        let deadline = this.start + this.allowed();
                        this.sleep.as_mut().reset(deadline);
                    }
                }
                Poll::Ready(Some(Ok(frame)))
            }
            Poll::Ready(Some(Err(e))) => Poll::Ready(Some(Err(e.into()))),
            Poll::Ready(None) => Poll::Ready(None),
            Poll::Pending => {
                if this.sleep.as_mut().poll(cx).is_ready() {
                    this.stats.body_timeouts.fetch_add(1, Ordering::Relaxed);
                    Poll::Ready(Some(Err(Box::new(BodyTimedOut(this.allowed())))))
                } else {
                    Poll::Pending
                }
            }
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_per_address_limit_counts_addresses_separately_and_frees_on_drop() {
        let limits = HttpLimits {
            max_connections: 3,
            max_connections_per_address: 2,
            ..HttpLimits::default()
        };
        let a = Arc::new(Admission::new(limits));
        let (x, y): (IpAddr, IpAddr) = ("10.0.0.1".parse().unwrap(), "10.0.0.2".parse().unwrap());
        let t1 = a.admit(x).unwrap();
        let _t2 = a.admit(x).unwrap();
        assert!(matches!(a.admit(x), Err(Limit::PerAddress)));
        let _t3 = a.admit(y).unwrap();
        assert!(matches!(a.admit(y), Err(Limit::Overall)));
        drop(t1);
        let _t4 = a.admit(x).unwrap();
    }

    #[test]
    fn a_body_timeout_is_found_through_its_causes() {
        #[derive(Debug, thiserror::Error)]
        #[error("outer")]
        struct Outer(#[source] BodyTimedOut);
        assert!(is_body_timeout(&Outer(BodyTimedOut(Duration::from_secs(
            1
        )))));
        assert!(!is_body_timeout(&io::Error::other("x")));
    }
}
