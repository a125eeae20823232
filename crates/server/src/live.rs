//! Live input of a session's heads (issue 47): the samples producers sent, per head, with
//! their memory; the session's input rate budget (`--max-live-rate`); and, owned by the
//! session's tick task, what each live head shows ([`LiveShown`]: its fade, its One Euro
//! filter, what it showed last).
//!
//! Producers and the tick meet only at [`LiveInputs`]'s lock, held to push a checked sample
//! or, once per tick, to read every live head's values: a producer's parsing and checking
//! happen before it, so a flooding, stalled or dead producer never delays a tick. A sample
//! keeps its queue-memory charge until it is dropped (replaced, played past or over a head's
//! [`MAX_SAMPLES`]).

use std::collections::HashMap;
use std::sync::atomic::AtomicUsize;
use std::sync::{Arc, Mutex};

use crowdmorph_anim::live::{Fade, JitterBuffer, LiveValues, OneEuroFilter, OneEuroParams};
use crowdmorph_proto::{LiveSpec, SessionHead};

use crate::admission::memory::{Charge, QueueMemory};

/// Most samples kept per head with timecodes (at 60 Hz, half a second more than the longest
/// useful delay needs is far less: producers that send more just push the oldest out).
pub const MAX_SAMPLES: usize = 64;

/// A producer's sample, checked against its head's rig at one generation, with its memory.
#[derive(Debug)]
pub struct Sample {
    /// The rig generation its channels and nodes index.
    pub generation: u64,
    /// Its values.
    pub values: LiveValues,
    /// Its bytes in the queue memory.
    pub _charge: Charge,
}

impl AsRef<LiveValues> for Sample {
    fn as_ref(&self) -> &LiveValues {
        &self.values
    }
}

/// One head's input: timecoded samples in a jitter buffer, or the newest untimed one.
#[derive(Debug)]
struct HeadInput {
    timed: JitterBuffer<Sample>,
    latest: Option<Sample>,
    /// When the newest sample arrived, seconds on the session's live clock.
    newest: f64,
    /// The rig generation every sample held indexes (a sample of another starts over).
    generation: u64,
}

/// The input rate budget: a token bucket of one second's messages.
#[derive(Debug, Default)]
struct Bucket {
    tokens: f64,
    at: f64,
    primed: bool,
}

#[derive(Debug, Default)]
struct Inner {
    heads: HashMap<u64, HeadInput>,
    bucket: Bucket,
}

/// A session's live input.
#[derive(Debug)]
pub struct LiveInputs {
    epoch: std::time::Instant,
    inner: Mutex<Inner>,
    /// The session's heads by id, for the layout it was built from.
    index: Mutex<Option<HeadIndex>>,
    /// Producer sockets open now.
    pub producers: AtomicUsize,
}

impl Default for LiveInputs {
    fn default() -> Self {
        LiveInputs {
            epoch: std::time::Instant::now(),
            inner: Mutex::default(),
            index: Mutex::default(),
            producers: AtomicUsize::new(0),
        }
    }
}

impl LiveInputs {
    /// Seconds since the session started: the clock arrivals and ticks are measured on.
    pub fn now(&self) -> f64 {
        self.epoch.elapsed().as_secs_f64()
    }

    /// Takes one message from the rate budget of `rate` messages a second (bursts of a
    /// second's worth); false when it is spent.
    pub fn admit(&self, rate: u32) -> bool {
        let now = self.now();
        let Ok(mut i) = self.inner.lock() else {
            return false;
        };
        let b = &mut i.bucket;
        let cap = f64::from(rate.max(1));
        if !b.primed {
            *b = Bucket {
                tokens: cap,
                at: now,
                primed: true,
            };
        }
        b.tokens = (b.tokens + (now - b.at) * cap).min(cap);
        b.at = now;
        if b.tokens >= 1.0 {
            b.tokens -= 1.0;
            true
        } else {
            false
        }
    }

    /// Where each head of `heads` is, by id: built once per layout and shared by the
    /// messages until it changes.
    pub fn index(&self, heads: &Arc<Vec<SessionHead>>) -> Arc<HashMap<u64, usize>> {
        let Ok(mut cached) = self.index.lock() else {
            return Arc::new(by_id(heads));
        };
        match &*cached {
            Some((of, index)) if Arc::ptr_eq(of, heads) => index.clone(),
            _ => {
                let index = Arc::new(by_id(heads));
                *cached = Some((heads.clone(), index.clone()));
                index
            }
        }
    }

    /// Adds checked samples (head, producer timecode, sample), all at one arrival time.
    pub fn push(&self, samples: Vec<(u64, Option<f64>, Sample)>) {
        let now = self.now();
        let mut dropped = Vec::new();
        if let Ok(mut i) = self.inner.lock() {
            for (head, t, s) in samples {
                let h = i.heads.entry(head).or_insert_with(|| HeadInput {
                    timed: JitterBuffer::new(MAX_SAMPLES),
                    latest: None,
                    newest: now,
                    generation: s.generation,
                });
                h.newest = now;
                if h.generation != s.generation {
                    // The rig changed: channels and nodes index another generation.
                    dropped.extend(h.timed.clear());
                    dropped.extend(h.latest.take());
                    h.generation = s.generation;
                }
                match t {
                    Some(t) => dropped.extend(h.timed.push(t, now, s)),
                    None => {
                        // A producer that stops sending timecodes is played as it sends now.
                        dropped.extend(h.timed.clear());
                        dropped.extend(h.latest.replace(s));
                    }
                }
            }
        }
        // Their charges are returned outside the lock.
        drop(dropped);
    }
}

/// A layout and its heads by id.
type HeadIndex = (Arc<Vec<SessionHead>>, Arc<HashMap<u64, usize>>);

/// Heads by id (the first of a repeated id, as a scan would find).
fn by_id(heads: &[SessionHead]) -> HashMap<u64, usize> {
    let mut m = HashMap::with_capacity(heads.len());
    for (k, h) in heads.iter().enumerate() {
        m.entry(h.head).or_insert(k);
    }
    m
}

/// Per live head, what the tick keeps between ticks.
#[derive(Debug, Default)]
struct Shown {
    fade: Fade,
    filter: OneEuroFilter,
    /// What `last`, the filter's state and this tick's copy of `last` hold in the queue
    /// memory (the samples they came from may be gone).
    _charge: Option<Charge>,
    /// What it showed last (held while it fades out) and its generation.
    last: Option<(u64, LiveValues)>,
    /// The tick it was last resolved at.
    tick: u64,
}

/// What the tick shows of a live head this tick.
#[derive(Debug)]
pub struct LiveNow {
    /// The rig generation the values index.
    pub generation: u64,
    /// The values.
    pub values: LiveValues,
    /// Their share, in (0, 1].
    pub alpha: f32,
}

/// The live heads' state owned by a session's tick task.
#[derive(Debug, Default)]
pub struct LiveShown {
    by_head: HashMap<u64, Shown>,
}

impl LiveShown {
    /// Every live head's values and share at `tick` (at `fps`), read from `inputs` under one
    /// lock, what each keeps charged to `memory`; heads without input, or faded out, are absent. Forgets the heads (and their
    /// input) no longer live in `heads`.
    pub fn at(
        &mut self,
        inputs: &LiveInputs,
        heads: &[SessionHead],
        tick: u64,
        fps: f32,
        memory: &QueueMemory,
    ) -> HashMap<u64, LiveNow> {
        let now = inputs.now();
        let mut out = HashMap::new();
        let live: HashMap<u64, &LiveSpec> = heads
            .iter()
            .filter_map(|h| h.live.as_ref().map(|l| (h.head, l)))
            .collect();
        let mut dropped = Vec::new();
        let Ok(mut i) = inputs.inner.lock() else {
            return out;
        };
        i.heads.retain(|id, h| {
            let keep = live.contains_key(id);
            if !keep {
                dropped.extend(h.timed.clear());
                dropped.extend(h.latest.take());
            }
            keep
        });
        self.by_head.retain(|id, _| live.contains_key(id));
        for (&id, spec) in &live {
            let input = i.heads.get_mut(&id);
            let shown = self.by_head.entry(id).or_default();
            let dt = (tick.saturating_sub(shown.tick).max(1)) as f64 / f64::from(fps.max(0.1));
            shown.tick = tick;
            let (fresh, on) = match input {
                None => (None, false),
                Some(h) => {
                    let on = now - h.newest <= f64::from(spec.hold_ms) / 1e3;
                    let fresh = if h.timed.is_empty() {
                        h.latest.as_ref().map(|s| {
                            let v = match spec.smoothing {
                                Some(p) => shown.filter.filter(
                                    &s.values,
                                    dt as f32,
                                    OneEuroParams {
                                        min_cutoff: p.min_cutoff,
                                        beta: p.beta,
                                        d_cutoff: p.d_cutoff,
                                    },
                                ),
                                None => s.values.clone(),
                            };
                            (s.generation, v)
                        })
                    } else {
                        let generation = h.generation;
                        h.timed
                            .at(now, f64::from(spec.delay_ms) / 1e3)
                            .map(|v| (generation, v))
                    };
                    (fresh, on)
                }
            };
            // Kept only once charged: the last values, the filter's state for values like
            // them and the copy the tick takes; a full queue keeps what was shown before.
            if let Some(f) = fresh {
                let bytes = 2 * (f.1.heap_bytes() + 64) + OneEuroFilter::bytes_for(&f.1);
                if let Ok(c) = memory.reserve(bytes) {
                    shown.last = Some(f);
                    shown._charge = Some(c);
                }
            }
            let alpha = shown.fade.step(on, dt, f64::from(spec.fade_ms) / 1e3);
            if alpha > 0.0
                && let Some((generation, values)) = &shown.last
            {
                out.insert(
                    id,
                    LiveNow {
                        generation: *generation,
                        values: values.clone(),
                        alpha,
                    },
                );
            } else if alpha == 0.0 {
                // Faded out: its smoothing starts afresh with the next input.
                shown.filter = OneEuroFilter::default();
            }
        }
        drop(i);
        drop(dropped);
        out
    }
}
