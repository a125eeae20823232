//! Live input into a session (issue 47): `POST /v1/sessions/{id}/live` for simple producers,
//! and the producers' WebSocket at `GET /v1/sessions/{id}/live` for streams (JSON text or
//! bincode binary messages, each a `LiveInput` of many heads). Both need the admin token.
//!
//! Phases of a message: the session's rate budget (`--max-live-rate`) first, before the
//! message is even decoded, so a flood costs a counter per message; then decode, charged;
//! then each sample checked against its head's rig ([`crate::admission::live`]) and charged
//! for as long as it is kept; then one push under the live inputs' lock. A bad sample refuses
//! its whole message with a named 4xx (over the socket, a text message with the same JSON
//! body; the socket stays open).

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use axum::body::Body;
use axum::extract::ws::{CloseFrame, Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::Response;
use crowdmorph_import::clips::is_live_link_angle;
use crowdmorph_proto::{LiveAck, LiveInput, LiveSample, LiveWeights, SessionHead};

use super::session;
use crate::admission::live::{resolve_sample, sample_bytes};
use crate::admission::mapping::{map_named, map_named_bytes};
use crate::admission::memory::decode_reservation;
use crate::admission::names::LiveNames;
use crate::admission::{Admission, Charge, Priced, decode_held};
use crate::http::{Accept, Admin, ApiError, ApiResult};
use crate::live::Sample;
use crate::registry::RigEntry;
use crate::services::Parts;
use crate::sessions::{CLOSE_TIMEOUT, Session, bump, close};
use crate::state::AppState;

/// Largest message on the live socket.
pub const MAX_LIVE_MESSAGE_BYTES: usize = 1 << 20;
/// Seconds' worth of messages over the rate a socket may send in a row before it is closed
/// (1008 `live_rate_exceeded`): a producer that ignores the shedding is flooding.
const FLOOD_SECONDS: u32 = 2;

/// A live input is checked sample by sample into samples that carry their own charges; only
/// its decoding is charged.
impl Priced for LiveInput {
    fn price(&self, _: Accept) -> u64 {
        0
    }
}

fn rate_exceeded(rate: u32) -> ApiError {
    let mut e = ApiError::new(
        StatusCode::TOO_MANY_REQUESTS,
        "live_rate_exceeded",
        format!(
            "the session takes at most {rate} live messages a second (--max-live-rate); \
             send several heads per message"
        ),
    );
    e.retry_after = Some(1);
    e
}

/// `POST /v1/sessions/{id}/live`: one message of samples.
pub async fn post_live(
    State(state): State<AppState>,
    _admin: Admin,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Body,
) -> ApiResult {
    let s = session(&state, &id)?;
    let m = &state.sessions.metrics;
    let rate = state.config.sessions.max_live_rate;
    if !s.live.admit(rate) {
        bump(&m.live_shed, 1);
        return Err(rate_exceeded(rate));
    }
    let accept = Accept::of(&headers);
    let decoded =
        decode_held::<LiveInput>(&state.queue_memory, state.body_limits(), &headers, body)
            .await
            .inspect_err(|_| bump(&m.live_invalid, 1))?;
    let (input, _decoded) = decoded.into_parts();
    let accepted = take(&state, &s, input).inspect_err(|_| bump(&m.live_invalid, 1))?;
    bump(&m.live_accepted, 1);
    accept.reply(StatusCode::OK, &LiveAck { accepted })
}

/// The session's heads as the next tick will have them, by id (built once per layout and
/// shared by the messages until it changes).
fn heads_now(s: &Session) -> Result<Arc<Vec<SessionHead>>, ApiError> {
    let i = s
        .inner
        .lock()
        .map_err(|_| ApiError::internal("session poisoned"))?;
    Ok(i.next_heads.clone().unwrap_or_else(|| i.heads.clone()))
}

/// Checks every sample of `input` against its head's rig, charges what each keeps, and hands
/// them to the session's live inputs: the number taken, or the first problem.
fn take(state: &AppState, s: &Session, input: LiveInput) -> Result<u32, ApiError> {
    let max = state.config.sessions.max_heads;
    if input.heads.len() > max {
        return Err(ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "too_many_heads",
            format!(
                "{} samples in one message; at most {max} (--max-session-heads)",
                input.heads.len()
            ),
        ));
    }
    let heads = heads_now(s)?;
    let index = s.live.index(&heads);
    // Per rig (by name) within the message: its entry and names, charged once.
    let mut rigs: HashMap<&str, (Arc<RigEntry>, LiveNames, Charge)> = HashMap::new();
    let mut samples = Vec::with_capacity(input.heads.len());
    for sample in &input.heads {
        let h = index
            .get(&sample.head)
            .and_then(|&k| heads.get(k))
            .ok_or_else(|| {
                ApiError::new(
                    StatusCode::NOT_FOUND,
                    "unknown_head",
                    format!("the session has no head {}", sample.head),
                )
            })?;
        if h.live.is_none() {
            return Err(ApiError::bad_request(
                "not_live",
                format!(
                    "head {} is not live; PATCH it with \"live\": {{}} first",
                    sample.head
                ),
            ));
        }
        if !rigs.contains_key(h.rig.as_str()) {
            let entry = state.rig(&h.rig)?;
            let charge = state.queue_memory.reserve(LiveNames::bytes(entry.rig()))?;
            let names = LiveNames::new(entry.rig());
            rigs.insert(h.rig.as_str(), (entry, names, charge));
        }
        let Some((entry, names, _)) = rigs.get(h.rig.as_str()) else {
            continue;
        };
        let mut charge = state
            .queue_memory
            .reserve(sample_bytes(entry.rig().targets.len(), sample))?;
        let values = match h.live.as_ref().and_then(|l| l.mapping.as_deref()) {
            Some(mapping) => mapped_sample(state, entry, names, mapping, sample, &mut charge)?,
            None => resolve_sample(entry, names, sample)?,
        };
        // What the sample keeps: its values (the check's scratch is given back).
        charge.keep(values.heap_bytes() + size_of::<Sample>() as u64);
        samples.push((
            sample.head,
            sample.t,
            Sample {
                generation: entry.generation,
                values,
                _charge: charge,
            },
        ));
    }
    let n = samples.len() as u32;
    s.live.push(samples);
    Ok(n)
}

/// A sample of a head whose live settings name a mapping: its named weights through the
/// mapping (its scratch charged to `charge` first), Live Link's head and eye angles among
/// them and its joints resolved as without one.
fn mapped_sample(
    state: &AppState,
    entry: &RigEntry,
    names: &LiveNames,
    mapping: &str,
    sample: &LiveSample,
    charge: &mut Charge,
) -> Result<crowdmorph_anim::live::LiveValues, ApiError> {
    let pairs = match &sample.weights {
        None => &[][..],
        Some(LiveWeights::Named(p)) => &p[..],
        Some(LiveWeights::Dense(_)) => {
            return Err(ApiError::bad_request(
                "invalid_live",
                format!(
                    "head {}: dense weights cannot go through mapping {mapping:?}; send them by name",
                    sample.head
                ),
            ));
        }
    };
    charge.merge(state.queue_memory.reserve(map_named_bytes(
        entry,
        &state.registry.maps,
        mapping,
        pairs.len(),
    ))?);
    let weights = map_named(entry, &state.registry.maps, mapping, pairs)?;
    // The angles and joints, as a sample without the mapping's names.
    let rest = LiveSample {
        weights: Some(LiveWeights::Named(
            pairs
                .iter()
                .filter(|(n, _)| is_live_link_angle(n))
                .cloned()
                .collect(),
        )),
        head: sample.head,
        joints: sample.joints.clone(),
        t: sample.t,
    };
    let mut values = resolve_sample(entry, names, &rest)?;
    values.weights = weights;
    Ok(values)
}

/// `GET /v1/sessions/{id}/live`: the WebSocket upgrade of a producer.
pub async fn live_socket(
    State(state): State<AppState>,
    _admin: Admin,
    Path(id): Path<String>,
    ws: WebSocketUpgrade,
) -> Result<Response, ApiError> {
    let s = session(&state, &id)?;
    Ok(ws
        .max_message_size(MAX_LIVE_MESSAGE_BYTES)
        .max_frame_size(MAX_LIVE_MESSAGE_BYTES)
        .on_upgrade(move |socket| serve_producer(state, s, socket)))
}

async fn close_with(socket: &mut WebSocket, code: u16, reason: String) {
    let frame = CloseFrame {
        code,
        reason: close::truncate(reason).into(),
    };
    let _ = tokio::time::timeout(CLOSE_TIMEOUT, socket.send(Message::Close(Some(frame)))).await;
}

/// Gives a producer's slot back when its socket task ends, however it ends.
struct Slot<'a>(&'a Session);

impl Drop for Slot<'_> {
    fn drop(&mut self) {
        self.0.live.producers.fetch_sub(1, Ordering::AcqRel);
    }
}

/// One producer's socket: messages taken as `POST .../live` bodies are, errors answered as
/// text messages, a flood shed and then closed, an idle socket closed.
async fn serve_producer(state: AppState, s: Arc<Session>, mut socket: WebSocket) {
    let limits = &state.config.sessions;
    let open = s.live.producers.fetch_add(1, Ordering::AcqRel);
    let _slot = Slot(&s);
    if open >= limits.max_live_producers {
        close_with(
            &mut socket,
            close::AGAIN,
            format!("the session has {open} live producers, its most (--max-live-producers)"),
        )
        .await;
        return;
    }
    let m = &state.sessions.metrics;
    let mut idle = Duration::ZERO;
    let mut shed_run: u32 = 0;
    let poll = Duration::from_millis(250)
        .min(limits.live_idle_timeout)
        .max(Duration::from_millis(10));
    loop {
        if s.stopped.load(Ordering::Acquire) {
            close_with(&mut socket, close::AWAY, "the session ended".into()).await;
            return;
        }
        let msg = match tokio::time::timeout(poll, socket.recv()).await {
            Err(_) => {
                idle += poll;
                if idle >= limits.live_idle_timeout {
                    close_with(
                        &mut socket,
                        close::AWAY,
                        format!(
                            "idle: no message for {} s",
                            limits.live_idle_timeout.as_secs_f64()
                        ),
                    )
                    .await;
                    return;
                }
                continue;
            }
            Ok(None) | Ok(Some(Err(_))) => return,
            Ok(Some(Ok(m))) => m,
        };
        idle = Duration::ZERO;
        let (bytes, bincode) = match msg {
            Message::Text(t) => (bytes::Bytes::from(t), false),
            Message::Binary(b) => (b, true),
            Message::Close(_) => return,
            Message::Ping(_) | Message::Pong(_) => continue,
        };
        if !s.live.admit(limits.max_live_rate) {
            bump(&m.live_shed, 1);
            shed_run += 1;
            if shed_run > FLOOD_SECONDS.saturating_mul(limits.max_live_rate) {
                close_with(
                    &mut socket,
                    close::POLICY,
                    format!(
                        "live_rate_exceeded: more than {} messages a second for {FLOOD_SECONDS} s (--max-live-rate)",
                        limits.max_live_rate
                    ),
                )
                .await;
                return;
            }
            continue;
        }
        shed_run = 0;
        match receive(&state, &s, &bytes, bincode) {
            Ok(_) => bump(&m.live_accepted, 1),
            Err(e) => {
                bump(&m.live_invalid, 1);
                let body = serde_json::to_string(&e.body()).unwrap_or_default();
                if tokio::time::timeout(CLOSE_TIMEOUT, socket.send(Message::Text(body.into())))
                    .await
                    .is_err()
                {
                    return;
                }
            }
        }
    }
}

/// One socket message: decoded within its charge, then taken.
fn receive(state: &AppState, s: &Session, bytes: &[u8], bincode: bool) -> Result<u32, ApiError> {
    let _decoding = state
        .queue_memory
        .reserve(decode_reservation(bincode, bytes.len() as u64))?;
    let input: LiveInput = crate::http::negotiate::decode_as(bincode, bytes)?;
    take(state, s, input)
}
