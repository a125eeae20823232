//! Sessions mode of the load generator (`crowdmorph load --session`): N viewers of one crowd
//! session, each reading the session's WebSocket stream for the run; and the viewer client
//! itself ([`Viewer`]), which `bench sessions` uses too.
//!
//! A session is not a [`Lane`](super::Lane): nothing is requested, the server's tick clock
//! decides when each message goes, so the core's dispatcher has nothing to dispatch. What the
//! two modes share is [`Live`]: the counters, the HdrHistograms, the [`LoadReport`] (with a
//! [`SessionReport`] added) and so the table, `--json` and the progress line.
//!
//! **Latency of a tick message.** The session's tick `k` (from 1) is due at `T0 + (k − 1) / fps`
//! on the server's clock, `T0` unknown to the viewers. Each message carries the server's own
//! time from the tick's start to the message being ready (`timings.total_us`), and a message
//! cannot arrive before its tick was due plus that time, so every message gives an upper bound
//! of `T0`: `arrival − (k − 1) / fps − total`. The run keeps the smallest bound seen by any
//! viewer during the warm-up (the first message fixes it, later ones can only lower it) and
//! freezes it when the window opens, so the window's messages and its count of due ticks use
//! one clock; it measures each message from `T0 + (k − 1) / fps` to its arrival (a message
//! faster than every warm-up message counts 0). So the latency
//! holds the tick timer's lateness, the blend, the encoding, the wait in the viewer's outbox,
//! the socket and the viewer's read, all on one clock shared by the viewers (a viewer served
//! last in every tick shows it); it leaves out only what the fastest message of the run had
//! anyway: its one-way transfer and its timer lateness (tens of microseconds on loopback).
//!
//! A tick counts in the window when its due time does. Per viewer, *due* ticks are those whose
//! due time falls in the window, *missed* ticks are gaps in the tick numbers it received (ticks
//! the server skipped, or that its one-message outbox replaced because the viewer read
//! slowly); the report's `unfinished` counts every due tick a viewer did not receive (the
//! missed ones, and those after a viewer was closed early). A viewer stops at its first tick
//! due after the window, or `grace` after the window's end. A close other than a normal one
//! (1000) is an error by close code and reason.

use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::Bytes;
use crowdmorph_proto::ViewerHello;
use crowdmorph_proto::skim::{TickSummary, skim};
use futures_util::{SinkExt, StreamExt};
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::protocol::CloseFrame;
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;

use super::{Live, LoadError, LoadReport, ServerTiming, SessionReport, ViewerReport, micros};

/// The WebSocket of one viewer.
type Socket =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

/// How long a viewer's own close may take before its socket is dropped.
const CLOSE_TIMEOUT: Duration = Duration::from_secs(2);

/// `ws://host:port/v1/sessions/{id}/stream` for a server at `url` (`http://host:port`).
pub fn stream_url(url: &str, session: &str) -> Result<String, LoadError> {
    let authority = super::http::authority_of(url)?;
    Ok(format!("ws://{authority}/v1/sessions/{session}/stream"))
}

/// What a viewer's stream gives next.
#[derive(Debug)]
pub enum ViewerEvent {
    /// A binary message (one tick), and when it was read.
    Tick(Bytes, Instant),
    /// The server closed the stream: its code (1005 when its close frame had none, 1006 when
    /// the connection ended without one) and reason.
    Closed(u16, String),
    /// The connection failed.
    Failed(String),
}

/// One viewer of a session: a WebSocket client that has sent its hello.
#[derive(Debug)]
pub struct Viewer {
    ws: Socket,
}

impl Viewer {
    /// Connects to `ws_url` (see [`stream_url`]) and sends `hello`.
    pub async fn connect(ws_url: &str, hello: &ViewerHello) -> Result<Viewer, LoadError> {
        let hello = serde_json::to_string(hello).map_err(|e| LoadError::Encode(e.to_string()))?;
        // A tick of a large crowd in f32 is tens of MB, sent as one frame: past tungstenite's
        // default 16 MiB frame limit. This client reads a server it was pointed at, so it
        // takes what a browser would (up to 1 GiB).
        let config = tokio_tungstenite::tungstenite::protocol::WebSocketConfig::default()
            .max_message_size(Some(1 << 30))
            .max_frame_size(Some(1 << 30));
        // Messages are measured on arrival: no Nagle delay on the hello or the close.
        let (mut ws, _) = tokio_tungstenite::connect_async_with_config(ws_url, Some(config), true)
            .await
            .map_err(|e| LoadError::Http(format!("connecting a viewer to {ws_url}: {e}")))?;
        ws.send(Message::text(hello))
            .await
            .map_err(|e| LoadError::Http(format!("sending a viewer's hello: {e}")))?;
        Ok(Viewer { ws })
    }

    /// The next tick, close or failure (text, ping and pong messages are passed over).
    pub async fn next(&mut self) -> ViewerEvent {
        loop {
            match self.ws.next().await {
                Some(Ok(Message::Binary(b))) => return ViewerEvent::Tick(b, Instant::now()),
                Some(Ok(Message::Close(c))) => {
                    return match c {
                        Some(c) => ViewerEvent::Closed(u16::from(c.code), c.reason.to_string()),
                        None => ViewerEvent::Closed(1005, String::new()),
                    };
                }
                Some(Ok(_)) => {}
                Some(Err(e)) => return ViewerEvent::Failed(e.to_string()),
                None => return ViewerEvent::Closed(1006, "closed without a close frame".into()),
            }
        }
    }

    /// Closes the stream normally (1000) and waits, briefly, for the server's reply.
    pub async fn close(mut self) {
        let frame = CloseFrame {
            code: CloseCode::Normal,
            reason: "".into(),
        };
        let _ = tokio::time::timeout(CLOSE_TIMEOUT, async {
            if self.ws.send(Message::Close(Some(frame))).await.is_ok() {
                while let Some(Ok(_)) = self.ws.next().await {}
            }
        })
        .await;
    }
}

/// One viewer's tallies over the window.
#[derive(Clone, Debug, Default)]
pub(super) struct ViewerTally {
    received: u64,
    missed: u64,
    bytes: u64,
    heads: u64,
    latency_sum_us: u64,
    latency_max_us: u64,
    last_tick: Option<u64>,
    closed: Option<(u16, String)>,
}

/// A sessions run's own state, kept with the run's other counters.
#[derive(Clone, Debug)]
pub(super) struct SessionTally {
    id: String,
    created: bool,
    fps: f64,
    heads: u64,
    /// The estimate of the session's `T0` (see the module doc), seconds from the run's start.
    clock: Option<f64>,
    viewers: Vec<ViewerTally>,
}

impl SessionTally {
    /// Ticks due per viewer in the window `[from, to)` (seconds from the run's start): those
    /// `k ≥ 1` with `from ≤ T0 + (k − 1) / fps < to`, or `(to − from) × fps` before the first
    /// message fixed `T0`.
    fn due(&self, from: f64, to: f64) -> u64 {
        let Some(t0) = self.clock else {
            return ((to - from) * self.fps).round().max(0.0) as u64;
        };
        let first = ((from - t0) * self.fps).ceil().max(0.0);
        let end = ((to - t0) * self.fps).ceil().max(0.0);
        (end - first).max(0.0) as u64
    }

    /// Per viewer and overall session fields of the report, with `window` the seconds of the
    /// window so far.
    pub(super) fn report(&self, warmup: f64, window: f64) -> SessionReport {
        let due = self.due(warmup, warmup + window);
        let received: u64 = self.viewers.iter().map(|v| v.received).sum();
        let bytes: u64 = self.viewers.iter().map(|v| v.bytes).sum();
        let heads: u64 = self.viewers.iter().map(|v| v.heads).sum();
        let per_message = |x: u64| {
            if received == 0 {
                0.0
            } else {
                x as f64 / received as f64
            }
        };
        SessionReport {
            id: self.id.clone(),
            created: self.created,
            fps: self.fps,
            heads: self.heads,
            viewers: self.viewers.len(),
            ticks_due: due,
            ticks_received: received,
            ticks_missed: self.viewers.iter().map(|v| v.missed).sum(),
            bytes_per_message: per_message(bytes),
            changed_heads_per_message: per_message(heads),
            per_viewer: self
                .viewers
                .iter()
                .map(|v| ViewerReport {
                    received: v.received,
                    missed: v.missed,
                    bytes: v.bytes,
                    heads: v.heads,
                    latency_mean_ms: if v.received == 0 {
                        0.0
                    } else {
                        v.latency_sum_us as f64 / v.received as f64 / 1e3
                    },
                    latency_max_ms: v.latency_max_us as f64 / 1e3,
                    close_code: v.closed.as_ref().map(|c| c.0),
                    close_reason: v.closed.as_ref().map(|c| c.1.clone()),
                })
                .collect(),
        }
    }
}

/// Whether a message was past the window (the viewer can stop).
enum Recorded {
    Before,
    InWindow,
    After,
}

impl Live {
    fn record_tick(&self, viewer: usize, at: Instant, bytes: u64, t: &TickSummary) -> Recorded {
        self.completed
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let Some(&start) = self.start.get() else {
            return Recorded::Before;
        };
        let Ok(mut guard) = self.rec.lock() else {
            return Recorded::Before;
        };
        let r = &mut *guard;
        let Some(s) = r.session.as_mut() else {
            return Recorded::Before;
        };
        let now = at.saturating_duration_since(start).as_secs_f64();
        let since_t0 = t.tick.saturating_sub(1) as f64 / s.fps;
        let server = t.timings.map_or(0.0, |t| t.total_us as f64 / 1e6);
        let bound = now - since_t0 - server;
        let from = self.opts.warmup.as_secs_f64();
        let to = from + self.opts.duration.as_secs_f64();
        // The clock settles during the warm-up and is frozen when the window opens, so that
        // every message of the window and the count of due ticks use the same clock (a clock
        // lowered mid-window would move the window's first tick after it was counted).
        let t0 = match s.clock {
            Some(c) if now >= from => c,
            Some(c) => c.min(bound),
            None => bound,
        };
        s.clock = Some(t0);
        let intended = t0 + since_t0;
        let Some(v) = s.viewers.get_mut(viewer) else {
            return Recorded::Before;
        };
        let gap = v
            .last_tick
            .map_or(0, |last| t.tick.saturating_sub(last.saturating_add(1)));
        v.last_tick = Some(t.tick);
        if intended < from {
            return Recorded::Before;
        }
        if intended >= to {
            return Recorded::After;
        }
        let latency = micros(Duration::from_secs_f64((now - intended).max(0.0)));
        v.received += 1;
        v.missed += gap;
        v.bytes += bytes;
        v.heads += t.changed;
        v.latency_sum_us += latency;
        v.latency_max_us = v.latency_max_us.max(latency);
        r.ok += 1;
        r.heads += t.changed;
        r.bytes += bytes;
        r.latency.saturating_record(latency);
        if let Some(t) = &t.timings {
            r.record_server(&ServerTiming {
                queue: Some(Duration::from_micros(t.queue_us)),
                compute: Some(Duration::from_micros(t.compute_us)),
                encode: None,
                total: Some(Duration::from_micros(t.total_us)),
            });
        }
        Recorded::InWindow
    }

    /// A viewer's stream ended before the viewer was done: an error by close code and reason
    /// (code 0 and `transport` when the connection failed, `malformed` for a message that does
    /// not read), except a normal close (1000), which only ends the viewer.
    fn viewer_failed(&self, viewer: usize, code: u16, reason: &str) {
        let Ok(mut r) = self.rec.lock() else {
            return;
        };
        if code != 1000 {
            r.failed += 1;
            let label = if reason.is_empty() { "close" } else { reason };
            *r.errors.entry((code, label.to_string())).or_insert(0) += 1;
        }
        if let Some(v) = r.session.as_mut().and_then(|s| s.viewers.get_mut(viewer)) {
            v.closed = Some((code, reason.to_string()));
        }
    }
}

/// A session to load and its viewers.
#[derive(Clone, Debug)]
pub struct SessionLoad {
    /// `http://host:port` of the server.
    pub url: String,
    /// The session's id.
    pub id: String,
    /// Whether this run created it (the report says so).
    pub created: bool,
    /// Its ticks per second.
    pub fps: f64,
    /// Its heads.
    pub heads: u64,
    /// One hello per viewer.
    pub hellos: Vec<ViewerHello>,
}

impl SessionLoad {
    /// Messages per second the viewers are due, together: the rate of the run's
    /// [`super::RunOptions`].
    pub fn rate(&self) -> f64 {
        self.fps * self.hellos.len() as f64
    }
}

async fn read_viewer(mut viewer: Viewer, index: usize, live: Arc<Live>, deadline: Instant) {
    loop {
        let event = match tokio::time::timeout_at(deadline.into(), viewer.next()).await {
            Ok(e) => e,
            // The grace after the window ran out: what has not come is unfinished.
            Err(_) => break,
        };
        match event {
            ViewerEvent::Tick(bytes, at) => match skim(&bytes) {
                Ok(t) => {
                    if let Recorded::After = live.record_tick(index, at, bytes.len() as u64, &t) {
                        break;
                    }
                }
                Err(e) => {
                    live.viewer_failed(index, 0, "malformed");
                    tracing::warn!("viewer {index}: {e}");
                    break;
                }
            },
            ViewerEvent::Closed(code, reason) => {
                live.viewer_failed(index, code, &reason);
                return;
            }
            ViewerEvent::Failed(e) => {
                live.viewer_failed(index, 0, "transport");
                tracing::warn!("viewer {index}: {e}");
                return;
            }
        }
    }
    viewer.close().await;
}

/// Connects the viewers of `load` (all before the run starts, so that an unknown session or
/// a refused connection fails at once), reads their streams for `live`'s warm-up and window,
/// closes them and returns the final report. Must be called inside a tokio runtime.
pub async fn run(load: &SessionLoad, live: &Arc<Live>) -> Result<LoadReport, LoadError> {
    live.opts.check()?;
    if load.hellos.is_empty() {
        return Err(LoadError::Invalid(
            "a sessions run needs at least one viewer".into(),
        ));
    }
    if !(load.fps.is_finite() && load.fps > 0.0) {
        return Err(LoadError::Invalid(format!(
            "the session's tick rate must be positive, not {}",
            load.fps
        )));
    }
    let url = stream_url(&load.url, &load.id)?;
    let mut viewers = Vec::with_capacity(load.hellos.len());
    for hello in &load.hellos {
        viewers.push(Viewer::connect(&url, hello).await?);
    }
    live.lanes
        .store(viewers.len() as u64, std::sync::atomic::Ordering::Relaxed);
    if let Ok(mut r) = live.rec.lock() {
        r.session = Some(SessionTally {
            id: load.id.clone(),
            created: load.created,
            fps: load.fps,
            heads: load.heads,
            clock: None,
            viewers: vec![ViewerTally::default(); viewers.len()],
        });
    }
    let start = Instant::now();
    let _ = live.start.set(start);
    let deadline = start + live.opts.warmup + live.opts.duration + live.opts.grace;
    let mut tasks = tokio::task::JoinSet::new();
    for (i, v) in viewers.into_iter().enumerate() {
        tasks.spawn(read_viewer(v, i, live.clone(), deadline));
    }
    while tasks.join_next().await.is_some() {}
    live.finished
        .store(true, std::sync::atomic::Ordering::Release);
    Ok(live.snapshot())
}

/// The LOD level of each of `n` viewers from a weighted mix, in proportion to the weights
/// (viewer `v` takes the level whose cumulative share covers `(v + ½) / n`), in level order.
pub fn viewer_lods(mix: &std::collections::BTreeMap<u32, f64>, n: usize) -> Vec<u32> {
    let total: f64 = mix.values().filter(|w| w.is_finite() && **w > 0.0).sum();
    (0..n)
        .map(|v| {
            let mut x = (v as f64 + 0.5) / n as f64 * total;
            for (&level, &w) in mix {
                if !(w.is_finite() && w > 0.0) {
                    continue;
                }
                if x < w {
                    return level;
                }
                x -= w;
            }
            mix.iter()
                .rev()
                .find(|(_, w)| w.is_finite() && **w > 0.0)
                .map_or(0, |(l, _)| *l)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    // A test that meets an unexpected error should fail loudly.
    #![allow(clippy::unwrap_used)]

    use std::collections::BTreeMap;

    use super::*;

    #[test]
    fn viewers_take_levels_in_proportion_to_the_mix() {
        let mix = BTreeMap::from([(0, 1.0), (2, 3.0)]);
        assert_eq!(viewer_lods(&mix, 4), vec![0, 2, 2, 2]);
        assert_eq!(viewer_lods(&mix, 1), vec![2]);
        assert_eq!(viewer_lods(&BTreeMap::from([(1, 1.0)]), 3), vec![1, 1, 1]);
    }

    #[test]
    fn due_ticks_follow_the_session_clock() {
        let mut s = SessionTally {
            id: "s".into(),
            created: true,
            fps: 10.0,
            heads: 1,
            clock: None,
            viewers: Vec::new(),
        };
        assert_eq!(s.due(1.0, 3.0), 20);
        // T0 = 0.95 s: ticks due at 0.95, 1.05, ... 2.95 fall in [1, 3): k = 2..=21.
        s.clock = Some(0.95);
        assert_eq!(s.due(1.0, 3.0), 20);
        // A session that starts inside the window: only its ticks are due.
        s.clock = Some(2.5);
        assert_eq!(s.due(1.0, 3.0), 5);
    }
}

/// `ws://host:port/v1/sessions/{id}/live` for a server at `url` (`http://host:port`): the
/// producers' socket of a session's live heads.
pub fn live_url(url: &str, session: &str) -> Result<String, LoadError> {
    let authority = super::http::authority_of(url)?;
    Ok(format!("ws://{authority}/v1/sessions/{session}/live"))
}

/// One producer of live input (a face tracker, Audio2Face): a WebSocket to a session's
/// `/live` that sends bincode [`crowdmorph_proto::LiveInput`] messages.
#[derive(Debug)]
pub struct Producer {
    ws: Socket,
}

impl Producer {
    /// Connects to `ws_url` (see [`live_url`]), with the admin token when the server has one.
    pub async fn connect(ws_url: &str, token: Option<&str>) -> Result<Producer, LoadError> {
        use tokio_tungstenite::tungstenite::client::IntoClientRequest;
        let mut request = ws_url
            .into_client_request()
            .map_err(|e| LoadError::Http(format!("a producer's request to {ws_url}: {e}")))?;
        if let Some(t) = token {
            let value = format!("Bearer {t}")
                .parse()
                .map_err(|_| LoadError::Http("the admin token is not a header value".into()))?;
            request.headers_mut().insert("authorization", value);
        }
        let (ws, _) = tokio_tungstenite::connect_async_with_config(request, None, true)
            .await
            .map_err(|e| LoadError::Http(format!("connecting a producer to {ws_url}: {e}")))?;
        Ok(Producer { ws })
    }

    /// Sends one message.
    pub async fn send(&mut self, input: &crowdmorph_proto::LiveInput) -> Result<(), LoadError> {
        let bytes = crowdmorph_proto::wire::to_bincode(input)
            .map_err(|e| LoadError::Encode(e.to_string()))?;
        self.ws
            .send(Message::binary(bytes))
            .await
            .map_err(|e| LoadError::Http(format!("sending live input: {e}")))
    }

    /// Closes the socket normally.
    pub async fn close(mut self) {
        let _ = tokio::time::timeout(CLOSE_TIMEOUT, self.ws.close(None)).await;
    }
}
