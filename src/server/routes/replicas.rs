//! Replicas over a shared store (`serve --store URL`, [`crate::store::objects`]): every change
//! of a rig is committed to the store as its next generation before this replica serves it;
//! the store is loaded at start and refreshed every `--store-refresh-ms`; a request naming a
//! rig this replica does not hold looks it up in the store (one listing) before its 404.
//!
//! Invariants: a generation is installed only whole (every object read back, checked and
//! prepared) and under the admin lock that local changes take, so a replica never mixes two
//! generations or overwrites a change it is making; a generation that does not read back is
//! reported once and passed over, and the replica keeps (or falls back to) the newest one
//! that does; what a replica acknowledged is in the store.

use std::sync::{Arc, Weak};
use std::time::Instant;

use axum::extract::{Request, State};
use axum::http::StatusCode;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use crate::budget::Budget;
use crate::server::http::ApiError;
use crate::server::registry::{ClipLayout, NewEntry, RigEntry, quantization_box, valid_id};
use crate::server::state::{AppState, Inner};
use crate::store::objects::{Change, Fetched, SharedError, SharedStore};
use crate::store::{Record, geometry_fingerprint};

/// Why a fetched generation was not installed.
enum Install {
    /// Its contents cannot be used (reported once, passed over).
    Unusable(String),
    /// The memory to prepare it is short now (tried again later).
    Short(String),
}

/// Most rigs one request may make this replica look up in the store.
pub const MAX_LOOKUPS: usize = 4;

impl From<SharedError> for ApiError {
    fn from(e: SharedError) -> ApiError {
        match &e {
            SharedError::Conflict { .. } => {
                ApiError::new(StatusCode::CONFLICT, "store_conflict", e.to_string())
            }
            SharedError::Unavailable { .. } => {
                ApiError::unavailable("store_unavailable", e.to_string(), 2)
            }
            SharedError::Memory(_) => ApiError::unavailable("memory_full", e.to_string(), 1),
            SharedError::Url { .. } | SharedError::Local(_) => ApiError::internal(e),
        }
    }
}

impl AppState {
    /// Commits one change of rig `id` to the shared store: 409 `store_conflict` when another
    /// replica wrote the rig since this one read it, 503 `store_unavailable` when the store
    /// does not answer. Nothing is changed here on either.
    pub(crate) async fn commit_shared(
        &self,
        shared: &Arc<SharedStore>,
        id: &str,
        change: Change,
    ) -> Result<(), ApiError> {
        let generation = match shared.commit(id, change).await {
            Ok(g) => g,
            Err(e) => {
                tracing::warn!(rig = %id, error = %e, "store write refused");
                if matches!(e, SharedError::Conflict { .. }) {
                    // Read the winner's generation now, not at the next refresh, so that the
                    // client's retry is based on it.
                    self.spawn_sync(id);
                }
                return Err(e.into());
            }
        };
        self.store_misses.forget(id);
        tracing::debug!(rig = %id, generation, "store generation written");
        Ok(())
    }

    /// Brings rig `id` up to the store's newest generation in the background (after this
    /// replica lost a race for it; the sync waits for the admin lock the loser holds).
    fn spawn_sync(&self, id: &str) {
        let weak = Arc::downgrade(&self.0);
        let id = id.to_string();
        tokio::spawn(async move {
            let Some(state) = weak.upgrade().map(AppState) else {
                return;
            };
            let Some(shared) = state.shared_store().cloned() else {
                return;
            };
            let synced = match shared.generations(&id).await {
                Ok(g) => state.sync_rig(&shared, &id, &g).await,
                Err(e) => Err(e),
            };
            if let Err(e) = synced {
                tracing::warn!(rig = %id, error = %e, "cannot read the rig after a conflict");
            }
        });
    }

    /// Loads every rig of the shared store (at start, before the server is ready). A rig
    /// that cannot be read is reported in `/readyz` and skipped.
    pub(crate) async fn load_shared(&self, shared: &Arc<SharedStore>) -> usize {
        match self.refresh_shared(shared).await {
            Ok(n) => {
                tracing::info!(rigs = n, store = %shared.url(), "stored rigs loaded");
                n
            }
            Err(e) => {
                tracing::error!(error = %e, "cannot read the rig store");
                self.skip(e.to_string());
                0
            }
        }
    }

    /// Brings every rig up to the store's newest usable generation (one listing, then a read
    /// of each rig that changed); returns how many rigs were installed or removed.
    pub(crate) async fn refresh_shared(
        &self,
        shared: &Arc<SharedStore>,
    ) -> Result<usize, SharedError> {
        let listed = shared.list().await?;
        let mut changed = 0;
        for (id, generations) in &listed {
            match self.sync_rig(shared, id, generations).await {
                Ok(true) => changed += 1,
                Ok(false) => {}
                // One rig that does not fit now does not hold up the others; it is tried
                // again at the next refresh or lookup.
                Err(SharedError::Memory(why)) => {
                    tracing::warn!(rig = %id, error = %why, "a stored rig waits for memory");
                }
                Err(e) => return Err(e),
            }
        }
        Ok(changed)
    }

    /// Installs the newest usable generation of rig `id` newer than the one held; `true`
    /// when one was.
    async fn sync_rig(
        &self,
        shared: &Arc<SharedStore>,
        id: &str,
        generations: &[u64],
    ) -> Result<bool, SharedError> {
        let held = shared.held(id);
        for &g in generations.iter().rev().take_while(|&&g| g > held) {
            if self.store_unusable.contains(id, g) {
                continue;
            }
            let budget = Arc::new(Budget::new(
                self.pool.limit(),
                "--max-rig-memory",
                Some(self.pool.clone()),
            ));
            // A charge refused is memory that is short now, not a damaged generation: it is
            // retried later, never passed over (a later change here would undo it).
            let short = std::sync::atomic::AtomicBool::new(false);
            let charge = |bytes: u64, key: &str| {
                budget
                    .charge(bytes, || format!("stored object {key}"))
                    .map_err(|e| {
                        short.store(true, std::sync::atomic::Ordering::Relaxed);
                        e.to_string()
                    })
            };
            let fetched = shared.fetch(id, g, &charge).await?;
            if short.load(std::sync::atomic::Ordering::Relaxed) {
                let why = fetched.err().unwrap_or_default();
                return Err(SharedError::Memory(format!(
                    "rig {id:?} generation {g}: {why}"
                )));
            }
            let installed = match fetched {
                Ok(f) => {
                    // Under the lock local changes take: a change being made here is either
                    // before this generation (and then in the store, and held) or after.
                    let _admin = self.admin.lock().await;
                    if shared.held(id) >= g {
                        return Ok(false);
                    }
                    let state = self.clone();
                    let b = budget.clone();
                    tokio::task::spawn_blocking(move || state.install(f, &b))
                        .await
                        .unwrap_or_else(|e| Err(Install::Unusable(e.to_string())))
                }
                Err(why) => Err(Install::Unusable(why)),
            };
            match installed {
                Ok(()) => {
                    self.store_misses.forget(id);
                    return Ok(true);
                }
                Err(Install::Short(why)) => {
                    return Err(SharedError::Memory(format!(
                        "rig {id:?} generation {g}: {why}"
                    )));
                }
                Err(Install::Unusable(why)) => {
                    shared.pass_over(id, g);
                    if self.store_unusable.insert(id, g) {
                        let why = format!("rig {id:?} generation {g} is not used: {why}");
                        tracing::error!(error = %why, "skipping a stored generation");
                        self.skip(why);
                    }
                }
            }
        }
        Ok(false)
    }

    /// Makes `fetched` the rig's current generation (blocking: it prepares the rig).
    fn install(&self, fetched: Fetched, budget: &Budget) -> Result<(), Install> {
        let Fetched {
            manifest,
            records,
            graphs,
            dropped,
        } = fetched;
        let id = manifest.rig.clone();
        if manifest.deleted {
            if self.registry.get(&id).is_some_and(|e| !e.builtin) {
                self.forget_rig(&id);
                tracing::info!(rig = %id, generation = manifest.generation, "rig deleted in the store");
            }
            if let Some(s) = self.shared_store() {
                s.set_held(manifest);
            }
            return Ok(());
        }
        for why in dropped {
            self.skip(why);
        }
        // The built-in rig with nothing stored but its graphs (no clips or LOD of its own
        // yet): its geometry and clips stay the embedded ones, only the graphs change.
        if records.is_empty() && self.registry.get(&id).is_some_and(|e| e.builtin) {
            match graphs {
                Some(g) if g.rig == id => self.graphs.load(id.clone(), g.graphs),
                _ => self.graphs.drop_rig(&id),
            }
            tracing::info!(rig = %id, generation = manifest.generation, "built-in rig's graphs loaded from the store");
            if let Some(s) = self.shared_store() {
                s.set_held(manifest);
            }
            return Ok(());
        }
        let mut records = records.into_iter();
        let (mut rig, builtin, mut layout) = match records.next() {
            Some(Record::Rig(r)) if r.id == id => {
                let layout = ClipLayout::in_record(&r.rig.clips);
                (r.rig, false, layout)
            }
            Some(Record::Builtin(b)) if b.id == id => {
                let base = self
                    .registry
                    .get(&id)
                    .filter(|e| e.builtin)
                    .ok_or_else(|| {
                        Install::Unusable(format!("stored clips for unknown built-in rig {id:?}"))
                    })?;
                let mut rig = crate::embedded::default_rig();
                rig.clips.truncate(base.builtin_clips);
                let layout = ClipLayout {
                    record: b.clips.iter().map(|c| c.name.clone()).collect(),
                    files: Vec::new(),
                };
                rig.clips.extend(b.clips);
                if let Some((lod, geometry)) = b.lod
                    && geometry == geometry_fingerprint(&rig)
                {
                    rig.lod = lod;
                }
                (rig, true, layout)
            }
            _ => {
                return Err(Install::Unusable(
                    "its first object is not the rig's record".into(),
                ));
            }
        };
        for record in records {
            let Record::Clips(c) = record else {
                return Err(Install::Unusable("it holds two records".into()));
            };
            if c.id != id {
                return Err(Install::Unusable(format!(
                    "a clip file is for rig {:?}",
                    c.id
                )));
            }
            let names: Vec<String> = c.clips.iter().map(|c| c.name.clone()).collect();
            layout.files.push((c.seq, names));
            rig.clips.extend(c.clips);
        }
        let mut seen = std::collections::HashSet::new();
        if let Some(dup) = rig.clips.iter().find(|c| !seen.insert(c.name.as_str())) {
            return Err(Install::Unusable(format!("it repeats clip {:?}", dup.name)));
        }
        rig.validate()
            .map_err(|e| Install::Unusable(e.to_string()))?;
        let rig = Arc::new(rig);
        self.charge_preparing(&rig, budget)
            .map_err(Install::Short)?;
        let prepared = self
            .engine
            .prepare(rig.clone())
            .map_err(|e| Install::Unusable(e.to_string()))?;
        let qbox = quantization_box(&rig);
        let generation = self.registry.generation();
        let entry = match self.registry.get(&id) {
            Some(old) if builtin && old.builtin => {
                let extra = budget.keep(prepared.memory().host_bytes as u64);
                old.successor(prepared, qbox, layout, generation, Some(extra))
            }
            Some(old) if old.builtin => {
                return Err(Install::Unusable(format!("{id:?} is a built-in rig's id")));
            }
            _ if builtin => {
                return Err(Install::Unusable(format!(
                    "stored clips for unknown built-in rig {id:?}"
                )));
            }
            _ => RigEntry::new(NewEntry {
                id: id.clone(),
                builtin: None,
                charge: budget.keep(prepared.memory().host_bytes as u64),
                prepared,
                generation,
                layout,
                qbox,
            }),
        };
        let entry = Arc::new(entry);
        self.registry.insert(entry.clone());
        match graphs {
            Some(g) if g.rig == id => self.graphs.load(id.clone(), g.graphs),
            _ => self.graphs.drop_rig(&id),
        }
        if let Ok(mut t) = self.render.topologies.lock() {
            t.purge(&id);
        }
        tracing::info!(rig = %id, generation = manifest.generation, "rig loaded from the store");
        if let Some(s) = self.shared_store() {
            s.set_held(manifest);
        }
        // No background LOD here: the replica that uploaded the rig runs it and commits the
        // result as the next generation, which reaches this one like any other change (every
        // replica computing it would be N times the work and N-1 conflicts).
        Ok(())
    }

    /// The rigs among `ids` worth looking up in the shared store: distinct, valid, not held
    /// here and not missed within the refresh interval, at most [`MAX_LOOKUPS`]. Without a
    /// shared store, none. (Synchronous, so that the borrowed iterator of a request's heads
    /// never lives inside a handler's future.)
    pub fn missing<'a>(&self, ids: impl IntoIterator<Item = &'a str>) -> Vec<String> {
        let mut out: Vec<String> = Vec::new();
        if self.shared_store().is_none() {
            return out;
        }
        for id in ids {
            if out.len() >= MAX_LOOKUPS {
                break;
            }
            if out.iter().any(|o| o == id)
                || !valid_id(id)
                || self.registry.get(id).is_some()
                || self.store_misses.recent(id, self.config.store_refresh)
            {
                continue;
            }
            out.push(id.to_string());
        }
        out
    }

    /// `attempt`, and once more after looking up the rigs of `heads` this replica does not
    /// hold when it failed with 404 `unknown_rig` and there is a shared store: a request
    /// whose rigs are all held costs nothing more (crowd frames, the hot path).
    pub async fn after_lookups<T>(
        &self,
        heads: &[crowdmorph_proto::Head],
        attempt: impl Fn() -> Result<T, ApiError>,
    ) -> Result<T, ApiError> {
        match attempt() {
            Err(e) if e.code == "unknown_rig" && self.shared_store().is_some() => {
                let ids = self.missing(heads.iter().map(|h| h.rig.as_str()));
                if ids.is_empty() {
                    return Err(e);
                }
                self.find_missing(ids).await?;
                attempt()
            }
            other => other,
        }
    }

    /// Looks up in the shared store the rigs among `ids` ([`AppState::missing`] picks them):
    /// each costs one listing, and a read of the rig when the store has it.
    pub async fn find_missing(&self, ids: Vec<String>) -> Result<(), ApiError> {
        let Some(shared) = self.shared_store().cloned() else {
            return Ok(());
        };
        for id in ids.iter().take(MAX_LOOKUPS) {
            let started = Instant::now();
            let generations = shared.generations(id).await?;
            let found = self.sync_rig(&shared, id, &generations).await?;
            self.metrics.store_lookup(found, started.elapsed());
            if !found && self.registry.get(id).is_none() {
                self.store_misses.insert(id);
            }
        }
        Ok(())
    }

    /// Forgets rig `id` here: its LOD job, entry, graphs and render topologies.
    pub(crate) fn forget_rig(&self, id: &str) {
        self.lod_jobs.cancel(id);
        self.registry.remove(id);
        self.graphs.drop_rig(id);
        if let Ok(mut t) = self.render.topologies.lock() {
            t.purge(id);
        }
    }

    /// The shared store, when the server has one.
    pub fn shared_store(&self) -> Option<&Arc<SharedStore>> {
        self.shared.as_ref()
    }
}

/// Refreshes `state`'s rigs from its shared store every `--store-refresh-ms` until the state
/// is gone (the task holds it weakly, so it ends with its owner).
pub(crate) fn spawn_refresh(state: &AppState) {
    let Some(shared) = state.shared_store().cloned() else {
        return;
    };
    let every = state.config.store_refresh;
    let weak: Weak<Inner> = Arc::downgrade(&state.0);
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(every);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        tick.tick().await;
        let mut failing = false;
        loop {
            tick.tick().await;
            let Some(inner) = weak.upgrade() else {
                return;
            };
            let state = AppState(inner);
            match state.refresh_shared(&shared).await {
                Ok(_) if failing => {
                    failing = false;
                    tracing::info!(store = %shared.url(), "rig store reachable again");
                }
                Ok(_) => {}
                Err(e) => {
                    state.metrics.store_refresh_failed();
                    if !failing {
                        tracing::warn!(error = %e, "cannot refresh from the rig store; serving what is held");
                    }
                    failing = true;
                }
            }
        }
    });
}

/// Middleware: a request about a rig this replica does not hold (`/v1/rigs/{id}...`) looks it
/// up in the shared store first, so that a replica a balancer sends it to after another one
/// failed serves it rather than 404. (Crowd frames, renders and sessions look up their heads'
/// rigs in their handlers, the `?rig=` hint among them: one bound of lookups per request.)
pub async fn look_up_rigs(State(state): State<AppState>, request: Request, next: Next) -> Response {
    if state.shared_store().is_some() && state.is_ready() {
        let from_path = request
            .uri()
            .path()
            .strip_prefix("/v1/rigs/")
            .map(|rest| rest.split('/').next().unwrap_or_default());
        let ids = state.missing(from_path);
        if let Err(e) = state.find_missing(ids).await {
            return e.into_response();
        }
    }
    next.run(request).await
}
