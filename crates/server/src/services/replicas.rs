//! Replicas over a shared store (`serve --store URL`, [`crowdmorph_store::objects`]): every change
//! of a rig is committed to the store as its next generation before this replica serves it;
//! the store is loaded at start and refreshed every `--store-refresh-ms`; a request naming a
//! rig this replica does not hold looks it up in the store (one listing) before its 404.
//!
//! Invariants: a generation is installed only whole (every object read back, checked and
//! prepared) and under the admin lock that local changes take, so a replica never mixes two
//! generations or overwrites a change it is making; a generation that does not read back is
//! reported once and passed over, and the replica keeps (or falls back to) the newest one
//! that does; what a replica acknowledged is in the store.
//!
//! Damage (an object missing, short or failing its checksum) is repaired, never built on: a
//! commit first reads back every object it carries over and restores a damaged one from this
//! replica's copy ([`commit_shared`]); a replica that cannot use a damaged
//! generation marks it in the store, refuses changes on top of it (503 `store_damaged`) and
//! reports it until it is superseded; the repair ([`salvage`]) is the next
//! generation, written by a replica that holds the damaged objects' exact content at once, or,
//! after a grace period in which none did, by any replica from the newest intact earlier copy
//! (an object with none is dropped and reported; a rig record with none is left for a delete
//! or a new upload).

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use std::collections::HashMap;
use std::sync::Mutex;
use std::sync::atomic::AtomicU64;

use axum::http::StatusCode;

use super::Parts;
use crate::http::ApiError;
use crate::lod_jobs::LodJobs;
use crate::registry::{ClipLayout, NewEntry, RigEntry, clips_named, quantization_box, valid_id};
use crate::skipped::Skipped;
use crate::topologies::SharedTopologies;
use crowdmorph_core::budget::{Budget, MemoryPool};
use crowdmorph_core::rig::{Rig, RigShape};
use crowdmorph_store::objects::{
    Change, Fetched, GRAPHS, LodClaim, Manifest, Misses, ObjectRef, SharedError, SharedStore,
    Unusable,
};
use crowdmorph_store::{Record, RecordRef, StoredGraphs, geometry_fingerprint};

use crate::rig_maps::NamedMaps;

/// What a replica of a shared store keeps beside its rigs.
#[derive(Debug, Default)]
pub struct Replica {
    /// The rig store shared with other replicas (`--store`), in place of the data dir.
    pub store: Option<Arc<SharedStore>>,
    /// Rig ids the shared store did not have when last asked.
    pub misses: Misses,
    /// Generations of the shared store that could not be used (each reported once).
    pub unusable: Unusable,
    /// Other replicas' LOD claims as last seen, with when their heartbeat last moved.
    pub claims_seen: Mutex<HashMap<String, (LodClaim, Instant)>>,
    /// This replica's LOD claim heartbeat.
    pub beat: AtomicU64,
}

/// What replication needs of the server beside [`Parts`]: the replica's own state, the admin
/// lock that local changes take, what a generation installs into (the LOD jobs, the rig
/// memory pool, the render topologies), the `/readyz` reports, and the start of a rig's
/// background LOD (a job of its own, [`crate::services::lod`], that this module does not name).
pub trait Replicating: Parts {
    /// The shared store and what this replica keeps of it.
    fn replica(&self) -> &Replica;
    /// Serializes rig and clip changes.
    fn admin(&self) -> &tokio::sync::Mutex<()>;
    /// Background LOD computations by rig id.
    fn lod_jobs(&self) -> &LodJobs;
    /// Host memory of rigs and of the work that makes them.
    fn pool(&self) -> &Arc<MemoryPool>;
    /// Topologies on the renderer's device, dropped with their rig.
    fn topologies(&self) -> &SharedTopologies;
    /// What `/readyz` reports as skipped.
    fn skips(&self) -> &Skipped;
    /// Starts the background LOD job of a rig that still has the import's quick order.
    fn start_auto_lod(&self, entry: &RigEntry);

    /// The shared store, when the server has one.
    fn shared_store(&self) -> Option<&Arc<SharedStore>> {
        self.replica().store.as_ref()
    }
}

/// Charges what preparing `rig` takes to a loading's budget.
pub fn charge_preparing<S: Parts>(state: &S, rig: &Rig, budget: &Budget) -> Result<(), String> {
    let c = RigShape::of(rig).cost(state.on_gpu());
    budget
        .charge(c.layout + c.transient, || {
            format!("preparing stored rig {:?}", rig.name)
        })
        .map_err(|e| e.to_string())
}

/// Why a fetched generation was not installed.
enum Install {
    /// Its contents cannot be used (reported once, passed over).
    Unusable(String),
    /// The memory to prepare it is short now (tried again later).
    Short(String),
}

/// The repairs of a generation's damaged objects ([`repairs`]).
#[derive(Default)]
struct Repairs {
    /// The changes that replace or drop them.
    changes: Vec<Change>,
    /// What was done with each, for the log.
    notes: Vec<String>,
    /// Whether one came from an earlier copy or was dropped (not this replica's exact copy).
    inexact: bool,
}

/// Charges manifest `key`'s `bytes` to `budget`, as [`SharedStore::manifest`] asks.
fn charge_manifest(budget: &Budget, bytes: u64, key: &str) -> Result<(), String> {
    budget
        .charge(bytes, || format!("manifest {key}"))
        .map(drop)
        .map_err(|e| e.to_string())
}

/// Removes the staging files of changes that will not be committed.
fn drop_staged(changes: Vec<Change>) {
    for change in changes {
        if let Change::File { path, .. } = change
            && let Some(dir) = path.parent().and_then(|p| p.parent())
        {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
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
            SharedError::Damaged { .. } => ApiError::unavailable("store_damaged", e.to_string(), 2),
            SharedError::Url { .. } | SharedError::Local(_) => ApiError::internal(e),
        }
    }
}

/// Commits one change of rig `id` to the shared store: 409 `store_conflict` when another
/// replica wrote the rig since this one read it, 503 `store_unavailable` when the store
/// does not answer, 503 `store_damaged` while the rig's newest generation is damaged and
/// not repaired yet. Nothing is changed here on any of them.
///
/// Every object the new generation carries over is read back first: one that is damaged
/// is restored from this replica's copy (it holds that very object), so a change is never
/// acknowledged on top of damage. (Cost: one read of the rig's stored objects per change.)
pub(crate) async fn commit_shared<S: Replicating>(
    state: &S,
    shared: &Arc<SharedStore>,
    id: &str,
    change: Change,
) -> Result<(), ApiError> {
    let mut changes = vec![change];
    let carried = shared.carried(id, &changes);
    let damaged = match shared.check_objects(&carried).await {
        Ok(d) => d,
        Err(e) => {
            drop_staged(changes);
            return Err(e.into());
        }
    };
    let mut inexact = false;
    if !damaged.is_empty() {
        let held = shared.held(id);
        // Not waiting for a holder: this replica holds every object it carries over.
        match repairs(state, shared, id, held, damaged, false).await {
            Ok(r) => {
                let r = r.unwrap_or_default();
                inexact = r.inexact;
                for note in &r.notes {
                    tracing::error!(rig = %id, generation = held, "{note}");
                }
                if !r.changes.is_empty() {
                    state.metrics().store_repaired(if inexact {
                        "earlier_copy"
                    } else {
                        "restored"
                    });
                }
                changes.extend(r.changes);
            }
            Err(e) => {
                drop_staged(changes);
                return Err(e.into());
            }
        }
    }
    let generation = match shared.commit(id, changes).await {
        Ok(g) => g,
        Err(e) => {
            tracing::warn!(rig = %id, error = %e, "store write refused");
            if matches!(e, SharedError::Conflict { .. }) {
                // Read the winner's generation now, not at the next refresh, so that the
                // client's retry is based on it.
                spawn_sync(state, id);
            }
            return Err(e.into());
        }
    };
    if inexact {
        // A damaged object came back from an earlier copy, or went: what this replica
        // serves is not the generation it wrote, which it installs from the store.
        shared.mark_stale(id);
        spawn_sync(state, id);
    }
    superseded(state, id, generation);
    state.replica().misses.forget(id);
    tracing::debug!(rig = %id, generation, "store generation written");
    Ok(())
}

/// What was reported about generations of rig `id` before `generation` is over.
fn superseded<S: Replicating>(state: &S, id: &str, generation: u64) {
    state.skips().clear(id, generation);
    state.replica().unusable.forget_below(id, generation);
}

/// The repairs of generation `generation` of rig `id`'s `damaged` objects: each restored
/// from this replica's copy where it holds that very object, else (unless
/// `wait_for_holder`, which then answers `None`) from the newest intact earlier copy,
/// else dropped. A rig record with neither is [`SharedError::Damaged`]: a generation
/// without it cannot be used.
async fn repairs<S: Replicating>(
    state: &S,
    shared: &Arc<SharedStore>,
    id: &str,
    generation: u64,
    damaged: Vec<(String, ObjectRef, String)>,
    wait_for_holder: bool,
) -> Result<Option<Repairs>, SharedError> {
    let held: Vec<bool> = damaged
        .iter()
        .map(|(name, object, _)| shared.held_key(id, name).as_deref() == Some(&object.key))
        .collect();
    let names: Vec<String> = damaged
        .iter()
        .zip(&held)
        .filter(|(_, held)| **held)
        .map(|((name, ..), _)| name.clone())
        .collect();
    let mut restored = {
        let state = state.clone();
        let id = id.to_string();
        tokio::task::spawn_blocking(move || restage(&state, &id, &names))
            .await
            .map_err(|e| SharedError::Local(crowdmorph_store::StoreError::Encode(e.to_string())))?
    };
    let mut out = Repairs::default();
    let budget = manifest_budget(state);
    let charge = |bytes: u64, key: &str| charge_manifest(&budget, bytes, key);
    for (name, object, why) in damaged {
        if let Some(change) = restored.remove(&name) {
            out.notes.push(format!(
                "{why}: restored from this replica's copy of {name}"
            ));
            out.changes.push(change);
            continue;
        }
        if wait_for_holder {
            drop_staged(out.changes);
            drop_staged(restored.into_values().collect());
            return Ok(None);
        }
        out.inexact = true;
        match shared
            .earlier_copy(id, generation + 1, &name, &object.key, &charge)
            .await?
        {
            Some((g, earlier)) => {
                out.notes.push(format!(
                    "{why}: no replica holds it; generation {g}'s intact copy of {name} \
                     ({}) takes its place",
                    earlier.key
                ));
                out.changes.push(Change::Keep {
                    name,
                    object: earlier,
                });
            }
            None if name.ends_with(&format!(".{}", crowdmorph_store::EXT)) => {
                drop_staged(out.changes);
                drop_staged(restored.into_values().collect());
                return Err(SharedError::Damaged {
                    url: shared.url().to_string(),
                    rig: id.to_string(),
                    generation,
                    why: format!(
                        "{why}; no replica holds the rig's record and the store has no \
                         intact earlier copy: delete the rig or upload it again"
                    ),
                });
            }
            None => {
                out.notes.push(format!(
                    "{why}: no replica holds it and the store has no intact earlier \
                     copy; {name} is dropped from the rig"
                ));
                out.changes.push(Change::Remove(name));
            }
        }
    }
    Ok(Some(out))
}

/// Stages again, from the rig this replica serves, each of `names` (objects of rig `id`:
/// its record, a clip file, its graphs) that it can; blocking. A clip file whose clips are
/// not all held (a compressed clip that did not decode) is left out.
fn restage<S: Replicating>(state: &S, id: &str, names: &[String]) -> BTreeMap<String, Change> {
    let mut out = BTreeMap::new();
    let (Some(shared), Some(entry)) = (state.shared_store(), state.registry().get(id)) else {
        return out;
    };
    let rig = entry.rig();
    for name in names {
        let staged = if name == GRAPHS {
            let maps = state.registry().maps.of(id);
            SharedStore::graphs_change(&StoredGraphs {
                rig: id.to_string(),
                graphs: state.graphs().specs(id),
                masks: (*maps.masks).clone(),
                mappings: (*maps.mappings).clone(),
            })
            .ok()
        } else if name == &format!("{id}.{}", crowdmorph_store::EXT) {
            let clips = clips_named(rig, &entry.layout.record);
            let record = if entry.builtin {
                RecordRef::Builtin {
                    id,
                    clips: &clips,
                    rig,
                }
            } else {
                RecordRef::Rig {
                    id,
                    rig,
                    clips: &clips,
                }
            };
            shared.stage(record).ok()
        } else {
            let seq = name
                .strip_prefix(id)
                .and_then(|r| r.strip_prefix('@'))
                .and_then(|r| r.split('.').next())
                .and_then(|r| r.parse::<u64>().ok());
            let file = seq.and_then(|seq| entry.layout.files.iter().find(|f| f.0 == seq));
            file.and_then(|(seq, names)| {
                let clips = clips_named(rig, names);
                (clips.len() == names.len())
                    .then(|| {
                        shared
                            .stage(RecordRef::Clips {
                                id,
                                seq: *seq,
                                clips: &clips,
                                rig,
                            })
                            .ok()
                    })
                    .flatten()
            })
        };
        if let Some(change) = staged {
            out.insert(name.clone(), change);
        }
    }
    out
}

/// The budget manifests read for a repair are charged to (`--max-upload-memory`, drawing
/// from the rig memory pool), with [`charge_manifest`].
fn manifest_budget<S: Replicating>(state: &S) -> Budget {
    Budget::new(
        state.config().max_upload_memory,
        "--max-upload-memory",
        Some(state.pool().clone()),
    )
}

/// How long a damaged generation waits for a replica holding its exact objects before
/// any replica repairs it from earlier copies: ten refreshes, at least two seconds.
fn repair_grace<S: Replicating>(state: &S) -> Duration {
    (state.config().store_refresh * 10).max(Duration::from_secs(2))
}

/// Repairs the damaged generations the store's markers name that this replica can: at
/// once where it holds every damaged object's exact content, else once the grace period
/// has passed; a marker of a generation that a later one superseded is removed.
async fn tend_damage<S: Replicating>(
    state: &S,
    shared: &Arc<SharedStore>,
    listed: &BTreeMap<String, Vec<u64>>,
) -> Result<(), SharedError> {
    for (id, g) in shared.damage_reports().await? {
        let newest = listed.get(&id).and_then(|v| v.last().copied()).unwrap_or(0);
        if newest != g {
            // Repaired, written over or deleted since (or a marker of nothing).
            shared.clear_damage(&id, g).await;
            continue;
        }
        // The replica that holds generation `g` can restore it at once; any other waits
        // the grace period for it, then repairs from earlier copies. Either reads the
        // generation back, so it tries at most once per grace period.
        let grace = repair_grace(state);
        let waited = state.replica().unusable.damage_seen(&id, g).elapsed() >= grace;
        let holder = shared.held(&id) == g;
        if !(holder || waited) || !state.replica().unusable.may_try_repair(&id, g, grace) {
            continue;
        }
        if let Err(e) = salvage(state, shared, &id, g, !waited).await {
            tracing::warn!(rig = %id, generation = g, error = %e, "cannot repair a damaged generation now");
        }
    }
    Ok(())
}

/// Writes the repair of damaged generation `g` of rig `id` as generation `g + 1`
/// ([`repairs`]; with `wait_for_holder`, only if this replica holds every
/// damaged object's content). The repair is installed like any other generation.
pub(crate) async fn salvage<S: Replicating>(
    state: &S,
    shared: &Arc<SharedStore>,
    id: &str,
    g: u64,
    wait_for_holder: bool,
) -> Result<(), SharedError> {
    let _admin = state.admin().lock().await;
    if shared.held(id) > g {
        return Ok(());
    }
    let budget = manifest_budget(state);
    let charge = |bytes: u64, key: &str| charge_manifest(&budget, bytes, key);
    let manifest: Manifest = match shared.manifest(id, g, &charge).await? {
        Ok(m) if !m.deleted => m,
        _ => return Ok(()),
    };
    let objects: Vec<(String, ObjectRef)> = manifest
        .objects
        .iter()
        .map(|(n, o)| (n.clone(), o.clone()))
        .collect();
    let damaged = shared.check_objects(&objects).await?;
    if damaged.is_empty() {
        return Ok(());
    }
    let repairs = match repairs(state, shared, id, g, damaged, wait_for_holder).await {
        Ok(Some(r)) => r,
        Ok(None) => return Ok(()),
        Err(e) => {
            let why = e.to_string();
            if state.replica().unusable.insert(id, g) {
                tracing::error!(rig = %id, generation = g, error = %why, "a damaged generation cannot be repaired");
            }
            state.skips().skip_rig(id, g, why);
            return Err(e);
        }
    };
    let how = if repairs.inexact {
        "earlier_copy"
    } else {
        "restored"
    };
    match shared.salvage(manifest, repairs.changes).await {
        Ok(repaired) => {
            for note in &repairs.notes {
                tracing::error!(rig = %id, generation = g, repaired, "{note}");
            }
            state.metrics().store_repaired(how);
            shared.clear_damage(id, g).await;
            Ok(())
        }
        // Another replica repaired it (or wrote the rig) first: its generation is read
        // at the next refresh.
        Err(SharedError::Conflict { .. }) => Ok(()),
        Err(e) => Err(e),
    }
}

/// Brings rig `id` up to the store's newest generation in the background (after this
/// replica lost a race for it; the sync waits for the admin lock the loser holds).
fn spawn_sync<S: Replicating>(state: &S, id: &str) {
    let weak = state.downgrade();
    let id = id.to_string();
    tokio::spawn(async move {
        let Some(state) = S::upgrade(&weak) else {
            return;
        };
        let Some(shared) = state.shared_store().cloned() else {
            return;
        };
        let synced = match shared.generations(&id).await {
            Ok(g) => sync_rig(&state, &shared, &id, &g).await,
            Err(e) => Err(e),
        };
        if let Err(e) = synced {
            tracing::warn!(rig = %id, error = %e, "cannot read the rig after a conflict");
        }
    });
}

/// Loads every rig of the shared store (at start, before the server is ready). A rig
/// that cannot be read is reported in `/readyz` and skipped.
pub(crate) async fn load_shared<S: Replicating>(state: &S, shared: &Arc<SharedStore>) -> usize {
    match refresh_shared(state, shared).await {
        Ok(n) => {
            tracing::info!(rigs = n, store = %shared.url(), "stored rigs loaded");
            n
        }
        Err(e) => {
            tracing::error!(error = %e, "cannot read the rig store");
            state.skips().skip(e.to_string());
            0
        }
    }
}

/// Brings every rig up to the store's newest usable generation (one listing, then a read
/// of each rig that changed); returns how many rigs were installed or removed.
pub(crate) async fn refresh_shared<S: Replicating>(
    state: &S,
    shared: &Arc<SharedStore>,
) -> Result<usize, SharedError> {
    let listed = shared.list().await?;
    let mut changed = 0;
    for (id, generations) in &listed {
        match sync_rig(state, shared, id, generations).await {
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
    tend_damage(state, shared, &listed).await?;
    tend_lod(state, shared).await?;
    Ok(changed)
}

/// Installs the newest usable generation of rig `id` newer than the one held; `true`
/// when one was.
async fn sync_rig<S: Replicating>(
    state: &S,
    shared: &Arc<SharedStore>,
    id: &str,
    generations: &[u64],
) -> Result<bool, SharedError> {
    let held = shared.held(id);
    // The held generation itself too when it is stale (a commit here repaired it from
    // earlier copies, so it is not what this replica serves).
    let stale = shared.is_stale(id);
    for &g in generations
        .iter()
        .rev()
        .take_while(|&&g| g > held || (g == held && stale))
    {
        if state.replica().unusable.contains(id, g) {
            continue;
        }
        let budget = Arc::new(Budget::new(
            state.pool().limit(),
            "--max-rig-memory",
            Some(state.pool().clone()),
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
            let why = fetched.err().map(|u| u.why).unwrap_or_default();
            return Err(SharedError::Memory(format!(
                "rig {id:?} generation {g}: {why}"
            )));
        }
        let mut damaged = false;
        let installed = match fetched {
            Ok(f) => {
                // Under the lock local changes take: a change being made here is either
                // before this generation (and then in the store, and held) or after.
                let _admin = state.admin().lock().await;
                let now = shared.held(id);
                if now > g || (now == g && !shared.is_stale(id)) {
                    return Ok(false);
                }
                let state = state.clone();
                let b = budget.clone();
                tokio::task::spawn_blocking(move || install(&state, f, &b))
                    .await
                    .unwrap_or_else(|e| Err(Install::Unusable(e.to_string())))
            }
            Err(u) => {
                // Damaged objects under a manifest that reads: a repair can mend it, and
                // nothing is committed past it until then (that would drop its intact
                // objects).
                damaged = u.damaged && u.manifest.is_some() && generations.last() == Some(&g);
                Err(Install::Unusable(u.why))
            }
        };
        match installed {
            Ok(()) => {
                state.replica().misses.forget(id);
                return Ok(true);
            }
            Err(Install::Short(why)) => {
                return Err(SharedError::Memory(format!(
                    "rig {id:?} generation {g}: {why}"
                )));
            }
            Err(Install::Unusable(why)) => {
                shared.pass_over(id, g);
                if damaged {
                    shared.mark_damaged(id, g, &why);
                    state.replica().unusable.damage_seen(id, g);
                }
                if state.replica().unusable.insert(id, g) {
                    let why = format!("rig {id:?} generation {g} is not used: {why}");
                    tracing::error!(error = %why, "skipping a stored generation");
                    state.skips().skip_rig(id, g, why.clone());
                    if damaged && let Err(e) = shared.report_damage(id, g, &why).await {
                        tracing::warn!(rig = %id, generation = g, error = %e, "cannot mark a damaged generation");
                    }
                }
            }
        }
    }
    Ok(false)
}

/// How long another replica's LOD claim may go without a heartbeat before this one takes
/// the build over: twenty refreshes, at least five seconds.
fn lod_lease<S: Replicating>(state: &S) -> Duration {
    (state.config().store_refresh * 20).max(Duration::from_secs(5))
}

/// Keeps the LOD of every rig held here moving while it has only the import's quick
/// order: a build running here (or failed here) beats its claim in the store; a rig
/// nobody claims, or whose claim's heartbeat has not moved for a lease (its replica died
/// after the upload's 201), is claimed and built here. The build commits its result as
/// the rig's next generation, like the uploader's would have.
async fn tend_lod<S: Replicating>(state: &S, shared: &Arc<SharedStore>) -> Result<(), SharedError> {
    if !state.config().auto_lod() {
        return Ok(());
    }
    let beat = state
        .replica()
        .beat
        .fetch_add(1, std::sync::atomic::Ordering::Relaxed)
        + 1;
    for entry in state.registry().all() {
        if entry.builtin || entry.rig().lod.method != crowdmorph_core::rig::IMPORT_LOD_METHOD {
            continue;
        }
        let id = entry.id.clone();
        if let Some(job) = state.lod_jobs().get(&id) {
            let failed = job.failed.lock().map(|f| f.is_some()).unwrap_or(false);
            shared.claim_lod(&id, beat, failed).await?;
            continue;
        }
        let take = match shared.lod_claim(&id).await? {
            None => true,
            // This replica's own claim without a job here: its build ended unapplied.
            Some(c) if c.writer == shared.writer() => true,
            Some(c) => {
                let mut seen = state
                    .replica()
                    .claims_seen
                    .lock()
                    .map_err(|_| SharedError::Memory("a lock was poisoned".into()))?;
                let (last, since) = seen
                    .entry(id.clone())
                    .or_insert_with(|| (c.clone(), Instant::now()));
                if *last != c {
                    (*last, *since) = (c, Instant::now());
                    false
                } else {
                    since.elapsed() >= lod_lease(state)
                }
            }
        };
        if take {
            if let Ok(mut seen) = state.replica().claims_seen.lock() {
                seen.remove(&id);
            }
            tracing::info!(rig = %id, "claiming the rig's unfinished LOD build");
            shared.claim_lod(&id, beat, false).await?;
            state.start_auto_lod(&entry);
        }
    }
    Ok(())
}

/// Makes `fetched` the rig's current generation (blocking: it prepares the rig).
fn install<S: Replicating>(state: &S, fetched: Fetched, budget: &Budget) -> Result<(), Install> {
    let Fetched {
        manifest,
        records,
        graphs,
        dropped,
    } = fetched;
    let id = manifest.rig.clone();
    if manifest.deleted {
        if state.registry().get(&id).is_some_and(|e| !e.builtin) {
            forget_rig(state, &id);
            tracing::info!(rig = %id, generation = manifest.generation, "rig deleted in the store");
        }
        superseded(state, &id, manifest.generation);
        if let Some(s) = state.shared_store() {
            s.set_held(manifest);
        }
        return Ok(());
    }
    for why in dropped {
        state.skips().skip_rig(&id, manifest.generation, why);
    }
    // The built-in rig with nothing stored but its graphs (no clips or LOD of its own
    // yet): its geometry and clips stay the embedded ones, only the graphs change.
    if records.is_empty() && state.registry().get(&id).is_some_and(|e| e.builtin) {
        take_named(state, &id, graphs);
        tracing::info!(rig = %id, generation = manifest.generation, "built-in rig's graphs loaded from the store");
        superseded(state, &id, manifest.generation);
        if let Some(s) = state.shared_store() {
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
            let base = state
                .registry()
                .get(&id)
                .filter(|e| e.builtin)
                .ok_or_else(|| {
                    Install::Unusable(format!("stored clips for unknown built-in rig {id:?}"))
                })?;
            let mut rig = crowdmorph_core::embedded::default_rig();
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
    // The store keeps images encoded: decode them (charged) before the rig is served.
    crowdmorph_import::decode_stored_images(&mut rig, budget).map_err(|e| match e {
        crowdmorph_import::ImportError::Budget(b) => Install::Short(b.to_string()),
        e => Install::Unusable(e.to_string()),
    })?;
    let rig = Arc::new(rig);
    charge_preparing(state, &rig, budget).map_err(Install::Short)?;
    let prepared = state
        .engine()
        .prepare(rig.clone())
        .map_err(|e| Install::Unusable(e.to_string()))?;
    let qbox = quantization_box(&rig);
    let generation = state.registry().generation();
    let entry = match state.registry().get(&id) {
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
    state.registry().insert(entry.clone());
    take_named(state, &id, graphs);
    if let Ok(mut t) = state.topologies().lock() {
        t.purge(&id);
    }
    tracing::info!(rig = %id, generation = manifest.generation, "rig loaded from the store");
    superseded(state, &id, manifest.generation);
    if let Some(s) = state.shared_store() {
        s.set_held(manifest);
    }
    // No background LOD here: the replica that uploaded the rig runs it and commits the
    // result as the next generation, which reaches this one like any other change (every
    // replica computing it would be N times the work and N-1 conflicts); if that replica
    // dies first, its claim's heartbeat stops and one replica takes it over (`tend_lod`).
    Ok(())
}

/// The rigs among `ids` worth looking up in the shared store: distinct, valid, not held
/// here and not missed within the refresh interval, at most [`MAX_LOOKUPS`]. Without a
/// shared store, none. (Synchronous, so that the borrowed iterator of a request's heads
/// never lives inside a handler's future.)
pub fn missing<'a, S: Replicating>(
    state: &S,
    ids: impl IntoIterator<Item = &'a str>,
) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    if state.shared_store().is_none() {
        return out;
    }
    for id in ids {
        if out.len() >= MAX_LOOKUPS {
            break;
        }
        if out.iter().any(|o| o == id)
            || !valid_id(id)
            || state.registry().get(id).is_some()
            || state
                .replica()
                .misses
                .recent(id, state.config().store_refresh)
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
pub async fn after_lookups<S: Replicating, T>(
    state: &S,
    heads: &[crowdmorph_proto::Head],
    attempt: impl Fn() -> Result<T, ApiError>,
) -> Result<T, ApiError> {
    match attempt() {
        Err(e) if e.code == "unknown_rig" && state.shared_store().is_some() => {
            let ids = missing(state, heads.iter().map(|h| h.rig.as_str()));
            if ids.is_empty() {
                return Err(e);
            }
            find_missing(state, ids).await?;
            attempt()
        }
        other => other,
    }
}

/// Looks up in the shared store the rigs among `ids` ([`missing`] picks them):
/// each costs one listing, and a read of the rig when the store has it.
pub async fn find_missing<S: Replicating>(state: &S, ids: Vec<String>) -> Result<(), ApiError> {
    let Some(shared) = state.shared_store().cloned() else {
        return Ok(());
    };
    for id in ids.iter().take(MAX_LOOKUPS) {
        let started = Instant::now();
        let generations = shared.generations(id).await?;
        let found = sync_rig(state, &shared, id, &generations).await?;
        state.metrics().store_lookup(found, started.elapsed());
        if !found && state.registry().get(id).is_none() {
            state.replica().misses.insert(id);
        }
    }
    Ok(())
}

/// Takes rig `id`'s stored graphs, masks and mappings (none when the generation has none).
fn take_named<S: Replicating>(state: &S, id: &str, stored: Option<StoredGraphs>) {
    match stored {
        Some(g) if g.rig == id => {
            state.registry().maps.set(
                id,
                NamedMaps {
                    masks: Arc::new(g.masks),
                    mappings: Arc::new(g.mappings),
                },
            );
            state.graphs().load(id.to_string(), g.graphs);
        }
        _ => {
            state.registry().maps.drop_rig(id);
            state.graphs().drop_rig(id);
        }
    }
}

/// Forgets rig `id` here: its LOD job, entry, graphs, masks, mappings and render topologies.
pub(crate) fn forget_rig<S: Replicating>(state: &S, id: &str) {
    state.lod_jobs().cancel(id);
    state.registry().remove(id);
    state.graphs().drop_rig(id);
    state.registry().maps.drop_rig(id);
    if let Ok(mut t) = state.topologies().lock() {
        t.purge(id);
    }
}

/// Refreshes `state`'s rigs from its shared store every `--store-refresh-ms` until the state
/// is gone (the task holds it weakly, so it ends with its owner).
pub fn spawn_refresh<S: Replicating>(state: &S) {
    let Some(shared) = state.shared_store().cloned() else {
        return;
    };
    let every = state.config().store_refresh;
    let weak = state.downgrade();
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(every);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        tick.tick().await;
        let mut failing = false;
        loop {
            tick.tick().await;
            let Some(state) = S::upgrade(&weak) else {
                return;
            };
            match refresh_shared(&state, &shared).await {
                Ok(_) if failing => {
                    failing = false;
                    tracing::info!(store = %shared.url(), "rig store reachable again");
                }
                Ok(_) => {}
                Err(e) => {
                    state.metrics().store_refresh_failed();
                    if !failing {
                        tracing::warn!(error = %e, "cannot refresh from the rig store; serving what is held");
                    }
                    failing = true;
                }
            }
        }
    });
}
