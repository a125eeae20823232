//! Connections: the accept loop that serves the router over HTTP/1.1, and the bounds that stop
//! sockets from holding file descriptors for as long as a client likes.
//!
//! Without them, a connection that sends nothing or stops mid-headers stayed open until the
//! client went away: 20,000 of them exhausted the open-file limit, and `/readyz` timed out until
//! they left. Every connection is now bounded three ways:
//!
//! - **Header timeout**: a request's headers must arrive complete within `header_timeout` of the
//!   connection being accepted, or of the first byte of a later request on a kept-alive
//!   connection. Bytes trickling in do not extend it.
//! - **Idle timeout**: a kept-alive connection with no request in progress is closed after
//!   `idle_timeout` without the first byte of a new request.
//! - **Connection cap**: at most `max_connections` are open. Past it, the connection with no
//!   request in progress that has been idle the longest (since its last response, or since it
//!   was accepted if it never completed a request) is closed to admit the new one. When every
//!   connection has a request in progress, the new one is refused (see [`too_many_connections`]).
//!
//! A request is *in progress* from the moment its headers are parsed (the router is called)
//! until its response body has been sent or dropped; the request's own deadlines (the timeout
//! layer in `app`) bound that phase, and nothing here closes a connection during it.
//!
//! hyper's `header_read_timeout` is not used. In hyper 1.12 it is armed whenever the connection
//! starts reading a request head, and after each response the connection goes idle and starts
//! reading the next head at once (`State::idle` sets `notify_read` when the timeout is set), so it
//! would bound the keep-alive wait with the header timeout and the two could not differ. The
//! phase is tracked here instead: reads mark the first byte of a request, the service marks its
//! start, and a guard in the response body marks its end.
//!
//! Every accept and close is counted in [`Metrics`], closes by reason.

use std::collections::HashMap;
use std::convert::Infallible;
use std::future::Future;
use std::io;
use std::pin::{Pin, pin};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::task::{Context, Poll};
use std::time::Duration;

use axum::Router;
use axum::body::Body;
use axum::http::{HeaderValue, Request, Response, header};
use axum::response::IntoResponse;
use bytes::Bytes;
use hyper::body::Incoming;
use hyper::server::conn::http1;
use hyper_util::rt::TokioIo;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Notify, OwnedSemaphorePermit, Semaphore, watch};
use tokio::task::JoinSet;
use tokio::time::Instant;

use super::http::ApiError;
use super::metrics::Metrics;

/// Connections being answered `too_many_connections` at once; past this many, a refused
/// connection is closed without an answer, so that refusing never holds more than this many
/// descriptors beyond the cap.
const REFUSALS: usize = 32;

/// The longest a refused connection is kept to read its request and write the 503.
const REFUSAL_TIMEOUT: Duration = Duration::from_secs(1);

/// How long the accept loop pauses after an `accept` failure that is not about one connection
/// (the open-file limit, for one): retrying at once would spin, and logging each retry would
/// flood the log.
const ACCEPT_BACKOFF: Duration = Duration::from_secs(1);

/// The bounds [`serve_connections`] applies, from the server configuration.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Limits {
    /// Most connections open at once.
    pub max_connections: usize,
    /// Time allowed for a request's headers.
    pub header_timeout: Duration,
    /// Time a kept-alive connection may wait for its next request.
    pub idle_timeout: Duration,
}

/// Why a connection was closed: the `reason` label of `crowdmorph_connections_closed_total`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Close {
    /// It ended on its own: the client closed it, or asked for `Connection: close`.
    Closed,
    /// A protocol or I/O error (a malformed request, a reset, a task that panicked).
    Error,
    /// Its request's headers did not arrive in time.
    HeaderTimeout,
    /// It waited too long for its next request.
    IdleTimeout,
    /// Closed to admit a new connection past the cap.
    Evicted,
    /// Shut down with the server.
    Shutdown,
}

impl Close {
    fn label(self) -> &'static str {
        match self {
            Close::Closed => "closed",
            Close::Error => "error",
            Close::HeaderTimeout => "header_timeout",
            Close::IdleTimeout => "idle_timeout",
            Close::Evicted => "evicted",
            Close::Shutdown => "shutdown",
        }
    }
}

/// Set in [`Slot::state`] once a connection has been chosen for eviction.
const EVICTED: u64 = 1 << 63;

/// What the accept loop and a connection's own task share about it.
#[derive(Debug)]
struct Slot {
    id: u64,
    /// Requests in progress (0 or 1 with HTTP/1.1), or [`EVICTED`]. One word, so that eviction
    /// (only from 0) and the start of a request (only without the flag) exclude each other.
    state: AtomicU64,
    /// Whether the header timeout runs (accepted, or a request's first byte arrived) rather
    /// than the idle timeout (kept alive after a response).
    awaiting_headers: AtomicBool,
    /// When the running timeout started, in nanoseconds since `epoch`; with no request in
    /// progress, also how long the connection has been idle.
    since: AtomicU64,
    epoch: Instant,
    /// Wakes the connection's task when it is evicted.
    evict: Notify,
}

impl Slot {
    fn new(id: u64, epoch: Instant) -> Slot {
        let slot = Slot {
            id,
            state: AtomicU64::new(0),
            awaiting_headers: AtomicBool::new(true),
            since: AtomicU64::new(0),
            epoch,
            evict: Notify::new(),
        };
        slot.since.store(slot.now(), Ordering::Release);
        slot
    }

    fn now(&self) -> u64 {
        u64::try_from(self.epoch.elapsed().as_nanos()).unwrap_or(u64::MAX)
    }

    /// Bytes arrived: on a connection kept alive after a response, they start a request, and
    /// its headers' time starts now.
    fn on_bytes(&self) {
        if self.state.load(Ordering::Acquire) == 0 && !self.awaiting_headers.load(Ordering::Acquire)
        {
            self.since.store(self.now(), Ordering::Release);
            self.awaiting_headers.store(true, Ordering::Release);
        }
    }

    /// Marks a request in progress; `false` if the connection was evicted.
    fn begin(&self) -> bool {
        self.state
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |s| {
                (s & EVICTED == 0).then_some(s + 1)
            })
            .is_ok()
    }

    /// Marks a request finished: the connection is idle from now.
    fn end(&self) {
        // The time is stored before the count drops, so that an evictor that sees no request
        // in progress also sees when the connection went idle.
        self.since.store(self.now(), Ordering::Release);
        self.awaiting_headers.store(false, Ordering::Release);
        self.state.fetch_sub(1, Ordering::AcqRel);
    }

    /// Chooses this connection for eviction if it has no request in progress.
    fn try_evict(&self) -> bool {
        self.state
            .compare_exchange(0, EVICTED, Ordering::AcqRel, Ordering::Acquire)
            .is_ok()
    }

    /// When it went idle, if it has no request in progress and was not evicted already.
    fn idle_since(&self) -> Option<u64> {
        (self.state.load(Ordering::Acquire) == 0).then(|| self.since.load(Ordering::Acquire))
    }

    /// The running timeout: when it expires and why; none while a request is in progress (or
    /// when a timeout is too long to be represented, which is as good as none).
    fn deadline(&self, limits: Limits) -> Option<(Instant, Close)> {
        if self.state.load(Ordering::Acquire) != 0 {
            return None;
        }
        let since = self.epoch + Duration::from_nanos(self.since.load(Ordering::Acquire));
        let (timeout, why) = if self.awaiting_headers.load(Ordering::Acquire) {
            (limits.header_timeout, Close::HeaderTimeout)
        } else {
            (limits.idle_timeout, Close::IdleTimeout)
        };
        Some((since.checked_add(timeout)?, why))
    }
}

/// The open connections, for choosing which one to evict.
#[derive(Debug)]
struct Table {
    limit: usize,
    epoch: Instant,
    open: Mutex<Open>,
}

#[derive(Debug, Default)]
struct Open {
    next_id: u64,
    slots: HashMap<u64, Arc<Slot>>,
}

/// The outcome of [`Table::admit`].
enum Admission {
    /// Admitted, having evicted this connection to make room, if any.
    Admitted(Arc<Slot>, Option<Arc<Slot>>),
    /// At the cap with every connection busy.
    Full,
}

impl Table {
    fn lock(&self) -> MutexGuard<'_, Open> {
        // Nothing panics while holding the lock; if something did, the map is still whole.
        self.open.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Admits a new connection, evicting the longest-idle one at the cap. The scan is linear
    /// in the open connections, and runs only at the cap.
    fn admit(&self) -> Admission {
        let mut open = self.lock();
        let mut evicted = None;
        if open.slots.len() >= self.limit.max(1) {
            // A candidate can start a request between the scan and its eviction; it is then
            // skipped (it is busy) and the scan repeats, a bounded number of times.
            for _ in 0..8 {
                let victim = open
                    .slots
                    .values()
                    .filter_map(|s| s.idle_since().map(|t| (t, s)))
                    .min_by_key(|&(t, _)| t)
                    .map(|(_, s)| s.clone());
                match victim {
                    Some(v) if v.try_evict() => {
                        open.slots.remove(&v.id);
                        evicted = Some(v);
                        break;
                    }
                    Some(_) => {}
                    None => break,
                }
            }
            if evicted.is_none() {
                return Admission::Full;
            }
        }
        let id = open.next_id;
        open.next_id += 1;
        let slot = Arc::new(Slot::new(id, self.epoch));
        open.slots.insert(id, slot.clone());
        Admission::Admitted(slot, evicted)
    }

    fn remove(&self, id: u64) {
        self.lock().slots.remove(&id);
    }
}

/// A connection's place in the table and the gauge; leaving it (the task ending, panicking or
/// being dropped unpolled) counts the close.
struct Tenancy {
    table: Arc<Table>,
    metrics: Arc<Metrics>,
    slot: Arc<Slot>,
    reason: Close,
}

impl Drop for Tenancy {
    fn drop(&mut self) {
        self.table.remove(self.slot.id);
        self.metrics.connections_open.dec();
        self.metrics.connection_closed(self.reason.label());
    }
}

/// The socket, noting the first byte of each request for the header timeout.
struct Watched {
    tcp: TcpStream,
    slot: Arc<Slot>,
}

impl AsyncRead for Watched {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        let read = Pin::new(&mut this.tcp).poll_read(cx, buf);
        if matches!(read, Poll::Ready(Ok(()))) && buf.filled().len() > before {
            this.slot.on_bytes();
        }
        read
    }
}

impl AsyncWrite for Watched {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().tcp).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().tcp).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.tcp.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().tcp).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().tcp).poll_shutdown(cx)
    }
}

/// A request in progress on a connection, until dropped.
struct InProgress(Arc<Slot>);

impl Drop for InProgress {
    fn drop(&mut self) {
        self.0.end();
    }
}

/// A response body that keeps its request in progress until hyper has sent it (or dropped it).
struct TrackedBody {
    inner: Body,
    _request: Option<InProgress>,
}

impl http_body::Body for TrackedBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.get_mut().inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// The router as a hyper service on one connection, marking its requests in progress.
#[derive(Clone)]
struct ConnService {
    router: Router,
    slot: Arc<Slot>,
}

type ServiceFuture =
    Pin<Box<dyn Future<Output = Result<Response<TrackedBody>, Infallible>> + Send>>;

impl hyper::service::Service<Request<Incoming>> for ConnService {
    type Response = Response<TrackedBody>;
    type Error = Infallible;
    type Future = ServiceFuture;

    fn call(&self, req: Request<Incoming>) -> ServiceFuture {
        if !self.slot.begin() {
            // Evicted just as this request's headers completed: its task is closing the
            // socket, and this answer goes out only if it wins that race.
            let resp = too_many_connections().map(|inner| TrackedBody {
                inner,
                _request: None,
            });
            return Box::pin(std::future::ready(Ok(resp)));
        }
        let request = InProgress(self.slot.clone());
        let mut router = self.router.clone();
        Box::pin(async move {
            // The router is always ready (axum's documented low-level serving does the same).
            let resp = match tower::Service::call(&mut router, req).await {
                Ok(resp) => resp,
                Err(never) => match never {},
            };
            Ok(resp.map(|inner| TrackedBody {
                inner,
                _request: Some(request),
            }))
        })
    }
}

/// The answer to a connection past the cap when every open one has a request in progress.
///
/// A 503 rather than a bare close: clients (and the Rust client's error type) then see why,
/// with `Retry-After`, instead of a reset they cannot tell from a crash. It costs a descriptor
/// for at most [`REFUSAL_TIMEOUT`], for at most [`REFUSALS`] connections at once; past that,
/// refused connections are closed without an answer.
fn too_many_connections() -> Response<Body> {
    let mut resp = ApiError::unavailable(
        "too_many_connections",
        "the server has as many connections open as it allows, each with a request in \
         progress; retry shortly",
        1,
    )
    .into_response();
    resp.headers_mut()
        .insert(header::CONNECTION, HeaderValue::from_static("close"));
    resp
}

/// Serves `router` on connections from `listener` within `limits` until `shutdown` resolves;
/// then stops accepting, lets requests in progress finish (idle connections close at once) and
/// returns when every connection has closed.
pub(crate) async fn serve_connections(
    listener: TcpListener,
    router: Router,
    metrics: Arc<Metrics>,
    limits: Limits,
    shutdown: impl Future<Output = ()>,
) {
    let (stop, stopped) = watch::channel(false);
    let acceptor = Acceptor {
        table: Arc::new(Table {
            limit: limits.max_connections,
            epoch: Instant::now(),
            open: Mutex::new(Open::default()),
        }),
        refusals: Arc::new(Semaphore::new(REFUSALS)),
        metrics,
        router,
        limits,
        stopped,
    };
    let mut tasks = JoinSet::new();
    let mut shutdown = pin!(shutdown);
    loop {
        tokio::select! {
            () = &mut shutdown => break,
            Some(done) = tasks.join_next() => reap(done),
            accepted = listener.accept() => match accepted {
                Ok((tcp, _)) => acceptor.take(tcp, &mut tasks),
                // The client gave up between connecting and being accepted.
                Err(e) if matches!(
                    e.kind(),
                    io::ErrorKind::ConnectionAborted
                        | io::ErrorKind::ConnectionReset
                        | io::ErrorKind::ConnectionRefused
                        | io::ErrorKind::Interrupted
                ) => {}
                Err(error) => {
                    acceptor.metrics.accept_errors.inc();
                    tracing::warn!(
                        %error,
                        pause_s = ACCEPT_BACKOFF.as_secs_f64(),
                        "accepting connections failed; pausing"
                    );
                    tokio::time::sleep(ACCEPT_BACKOFF).await;
                }
            },
        }
    }
    drop(listener);
    // Every connection now closes once it has no request in progress: idle ones at once,
    // those mid-headers when their request has been answered or their header timeout fires.
    let _ = stop.send(true);
    while let Some(done) = tasks.join_next().await {
        reap(done);
    }
}

/// What the accept loop hands each new connection.
struct Acceptor {
    table: Arc<Table>,
    /// Refusals answered at once (a 503 written before closing), at most [`REFUSALS`].
    refusals: Arc<Semaphore>,
    metrics: Arc<Metrics>,
    router: Router,
    limits: Limits,
    stopped: watch::Receiver<bool>,
}

impl Acceptor {
    /// Serves an accepted connection on its own task, evicting the longest-idle one when the
    /// table is full, or refuses it when every connection has a request in progress.
    fn take(&self, tcp: TcpStream, tasks: &mut JoinSet<()>) {
        self.metrics.connections_accepted.inc();
        // Responses go out as a header write then body writes; without TCP_NODELAY, Nagle's
        // algorithm holds the tail back until the client's delayed ACK (≈40 ms) at moderate
        // load.
        if let Err(error) = tcp.set_nodelay(true) {
            tracing::debug!(%error, "cannot set TCP_NODELAY");
        }
        match self.table.admit() {
            Admission::Admitted(slot, evicted) => {
                if let Some(victim) = evicted {
                    victim.evict.notify_one();
                }
                self.metrics.connections_open.inc();
                let tenancy = Tenancy {
                    table: self.table.clone(),
                    metrics: self.metrics.clone(),
                    slot,
                    reason: Close::Error,
                };
                tasks.spawn(serve_one(
                    tcp,
                    tenancy,
                    self.router.clone(),
                    self.limits,
                    self.stopped.clone(),
                ));
            }
            Admission::Full => {
                self.metrics.connection_closed("refused");
                // Without a permit, dropping the socket closes it at once.
                if let Ok(permit) = self.refusals.clone().try_acquire_owned() {
                    tasks.spawn(refuse(tcp, permit));
                }
            }
        }
    }
}

fn reap(done: Result<(), tokio::task::JoinError>) {
    if let Err(e) = done
        && e.is_panic()
    {
        tracing::error!(error = %e, "a connection task panicked");
    }
}

/// Serves one admitted connection until it closes, times out or is evicted.
async fn serve_one(
    tcp: TcpStream,
    mut tenancy: Tenancy,
    router: Router,
    limits: Limits,
    mut stopped: watch::Receiver<bool>,
) {
    let slot = tenancy.slot.clone();
    let io = TokioIo::new(Watched {
        tcp,
        slot: slot.clone(),
    });
    let service = ConnService {
        router,
        slot: slot.clone(),
    };
    let conn = http1::Builder::new()
        // The timeouts are this module's (see the module doc), so hyper needs no timer.
        .header_read_timeout(None)
        .serve_connection(io, service)
        // Session streams upgrade to WebSockets; an upgraded connection leaves this loop (and
        // the connection cap): sessions bound their viewers themselves.
        .with_upgrades();
    let mut conn = pin!(conn);
    let mut evicted = pin!(slot.evict.notified());
    let mut stop = pin!(async move {
        // A dropped sender also means stop.
        let _ = stopped.wait_for(|stop| *stop).await;
    });
    let mut timer = pin!(tokio::time::sleep(limits.header_timeout));
    let mut stopping = false;
    tenancy.reason = std::future::poll_fn(|cx| {
        if evicted.as_mut().poll(cx).is_ready() {
            return Poll::Ready(Close::Evicted);
        }
        if !stopping && stop.as_mut().poll(cx).is_ready() {
            stopping = true;
            conn.as_mut().graceful_shutdown();
        }
        if let Poll::Ready(result) = conn.as_mut().poll(cx) {
            return Poll::Ready(match result {
                Ok(()) if stopping => Close::Shutdown,
                Ok(()) => Close::Closed,
                Err(error) => {
                    tracing::debug!(%error, "connection failed");
                    Close::Error
                }
            });
        }
        // The connection's reads, requests and responses move the deadline, and all of them
        // happen inside the poll above, so the timer is reset here, after it.
        let Some((at, why)) = slot.deadline(limits) else {
            return Poll::Pending;
        };
        if timer.deadline() != at {
            timer.as_mut().reset(at);
        }
        timer.as_mut().poll(cx).map(|()| why)
    })
    .await;
}

/// Answers a refused connection [`too_many_connections`] and closes it.
async fn refuse(tcp: TcpStream, _permit: OwnedSemaphorePermit) {
    let service = hyper::service::service_fn(|_req: Request<Incoming>| async {
        Ok::<_, Infallible>(too_many_connections())
    });
    let conn = http1::Builder::new()
        .keep_alive(false)
        .header_read_timeout(None)
        .serve_connection(TokioIo::new(tcp), service);
    let _ = tokio::time::timeout(REFUSAL_TIMEOUT, conn).await;
}
