//! Changing a rig: preparing it within a budget ([`prepare_charged`]), and persisting the
//! change. A change of a rig (its record, a clip file, its motion graphs with its masks and
//! mappings, a delete)
//! written where this server keeps rigs — the data dir ([`crowdmorph_store::Store`]), or the
//! shared store as the rig's next generation ([`super::replicas::commit_shared`]) — before
//! the change is served. Without either, nothing is written. At start, the data dir's records
//! are loaded ([`load_blocking`]), each charged to the rig memory pool before it is read.
//!
//! Invariant: a caller holds the admin lock, and serves a change only after its function here
//! returned `Ok`: what was acknowledged is stored.

use std::sync::Arc;

use super::replicas::{Replicating, charge_preparing, commit_shared};
use crate::http::{ApiError, blocking};
use crate::registry::{ClipLayout, NewEntry, RigEntry, clips_named, quantization_box};
use axum::http::StatusCode;
use crowdmorph_core::budget::{Budget, BudgetError};
use crowdmorph_core::rig::{Rig, RigShape};
use crowdmorph_store::objects::{Change, SharedStore};
use crowdmorph_store::{
    Record, RecordRef, Store, StoreError, StoredBuiltin, StoredClips, StoredGraphs, StoredRig,
    geometry_fingerprint,
};

use crate::rig_maps::NamedMaps;

/// A rig the engine could not prepare: over the GPU memory budget, answered as the host
/// budget answers (413 `too_large`, 503 `memory_full`, naming `--max-gpu-memory`); anything
/// else the device cannot hold, 422 `cannot_prepare`.
pub fn prepare_error(e: crowdmorph_engine::EngineError, too_large: &'static str) -> ApiError {
    match e {
        crowdmorph_engine::EngineError::GpuMemory(b) => ApiError::budget(b, too_large),
        e => ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "cannot_prepare",
            e.to_string(),
        ),
    }
}

/// Prepares `rig` for the engine after charging what that adds (the CPU layout and, on a GPU,
/// the upload's staging copies, or the stored record, whichever is larger) to `budget`.
pub fn prepare_charged(
    engine: &crowdmorph_engine::Engine,
    budget: &Budget,
    rig: Arc<Rig>,
    gpu: bool,
) -> Result<Prepared, ApiError> {
    let cost = RigShape::of(&rig).cost(gpu);
    // A rig whose resident GPU copy alone exceeds the GPU memory budget is refused up front,
    // as one over the host budget is; one that does not fit next to the rigs already there is
    // refused by the engine's charges (503, or 413 for one buffer over the whole budget).
    if let Some(pool) = engine.gpu_memory().filter(|_| gpu)
        && cost.device > pool.limit()
    {
        return Err(ApiError::budget(
            BudgetError::TooLarge {
                what: format!(
                    "a rig of {} vertices and {} targets on the GPU",
                    rig.vertex_count(),
                    rig.targets.len()
                ),
                needed: cost.device,
                limit: pool.limit(),
                flag: crowdmorph_engine::gpu::GPU_MEMORY_FLAG,
            },
            "rig_too_large",
        ));
    }
    budget
        .charge(cost.layout + cost.transient, || {
            format!("preparing a rig of {} vertices", rig.vertex_count())
        })
        .map_err(|e| ApiError::budget(e, "rig_too_large"))?;
    let prepared = engine
        .prepare(rig.clone())
        .map_err(|e| prepare_error(e, "rig_too_large"))?;
    Ok((rig, prepared))
}

/// What persistence needs of the server beside replication: the data dir's store.
pub trait Persisting: Replicating {
    /// The data dir's store, when there is one (and no shared store).
    fn store(&self) -> Option<&Store>;
}

/// A rig prepared for the engine, with the rig it was prepared from.
pub type Prepared = (Arc<Rig>, crowdmorph_engine::PreparedRig);

/// The error budget clips are stored within, when the store compresses them.
pub fn clip_error<S: Persisting>(state: &S) -> Option<f32> {
    match state.shared_store() {
        Some(s) => s.clip_error(),
        None => state.store().and_then(|s| s.clip_error()),
    }
}

/// Makes `rig` (prepared as `prepared`, same geometry and clips as `entry`'s generation)
/// rig `id`'s next generation: stored first, then served; it takes over `entry`'s memory
/// charge, set to what it now holds. The caller holds the admin lock.
pub async fn next_generation<S: Persisting>(
    state: &S,
    id: &str,
    entry: &RigEntry,
    (rig, prepared): Prepared,
) -> Result<Arc<RigEntry>, ApiError> {
    persist_record(state, id, rig, entry.builtin, &entry.layout).await?;
    let next = Arc::new(entry.successor(
        prepared,
        entry.qbox,
        entry.layout.clone(),
        state.registry().generation(),
        None,
    ));
    state.registry().insert(next.clone());
    Ok(next)
}

/// Persists a rig's record: its geometry and LOD with the clips `layout` keeps in the
/// record (for the built-in rig: its extra clips and LOD).
pub async fn persist_record<S: Persisting>(
    state: &S,
    id: &str,
    rig: Arc<Rig>,
    builtin: bool,
    layout: &ClipLayout,
) -> Result<(), ApiError> {
    if state.store().is_none() && state.shared_store().is_none() {
        return Ok(());
    }
    let owned = state.clone();
    let rid = id.to_string();
    let names = layout.record.clone();
    let staged = blocking(move || {
        let id = rid;
        let clips = clips_named(&rig, &names);
        let record = if builtin {
            RecordRef::Builtin {
                id: &id,
                clips: &clips,
                rig: &rig,
            }
        } else {
            RecordRef::Rig {
                id: &id,
                rig: &rig,
                clips: &clips,
            }
        };
        match (owned.shared_store(), owned.store()) {
            (Some(shared), _) => shared.stage(record).map(Some).map_err(ApiError::internal),
            (None, Some(store)) => store.put(record).map(|()| None).map_err(ApiError::internal),
            (None, None) => Ok(None),
        }
    })
    .await?;
    if state.shared_store().is_none() {
        // The data dir's record of the rig is written anew: what was reported about the
        // one before is superseded.
        state.skips().clear(id, u64::MAX);
    }
    commit_staged(state, id, staged).await
}

/// Commits a change staged for the shared store (none for the data dir, written already).
async fn commit_staged<S: Persisting>(
    state: &S,
    id: &str,
    staged: Option<Change>,
) -> Result<(), ApiError> {
    match (state.shared_store(), staged) {
        (Some(shared), Some(change)) => commit_shared(state, shared, id, change).await,
        _ => Ok(()),
    }
}

/// Rig `id`'s motion graphs, masks and mappings as they are stored together (one file or
/// store object per rig).
pub fn stored_named(
    id: &str,
    graphs: std::collections::BTreeMap<String, crowdmorph_proto::MotionGraph>,
    maps: &NamedMaps,
) -> StoredGraphs {
    StoredGraphs {
        rig: id.to_string(),
        graphs,
        masks: (*maps.masks).clone(),
        mappings: (*maps.mappings).clone(),
    }
}

/// Takes what a stored graphs file holds beside the graphs: the rig's masks and mappings.
pub fn load_named<S: Persisting>(state: &S, stored: &StoredGraphs) {
    state.registry().maps.set(
        &stored.rig,
        NamedMaps {
            masks: Arc::new(stored.masks.clone()),
            mappings: Arc::new(stored.mappings.clone()),
        },
    );
}

/// Persists rig `id`'s motion graphs, all of them (none removes them), with its masks and
/// mappings as they are.
pub async fn persist_graphs<S: Persisting>(
    state: &S,
    id: &str,
    graphs: std::collections::BTreeMap<String, crowdmorph_proto::MotionGraph>,
) -> Result<(), ApiError> {
    let stored = stored_named(id, graphs, &state.registry().maps.of(id));
    persist_named(state, stored).await
}

/// Persists rig `id`'s masks and mappings, all of them, with its motion graphs as they are.
pub async fn persist_maps<S: Persisting>(
    state: &S,
    id: &str,
    maps: NamedMaps,
) -> Result<(), ApiError> {
    let stored = stored_named(id, state.graphs().specs(id), &maps);
    persist_named(state, stored).await
}

async fn persist_named<S: Persisting>(state: &S, stored: StoredGraphs) -> Result<(), ApiError> {
    if let Some(shared) = state.shared_store() {
        let change = SharedStore::graphs_change(&stored).map_err(ApiError::internal)?;
        return commit_shared(state, shared, &stored.rig, change).await;
    }
    on_data_dir(state, move |st| st.put_graphs(&stored)).await
}

/// Removes rig `id` from the store: its record, clip files and graphs (a tombstone
/// generation in a shared store).
pub async fn persist_delete<S: Persisting>(state: &S, id: &str) -> Result<(), ApiError> {
    if let Some(shared) = state.shared_store() {
        commit_shared(state, shared, id, Change::Delete).await?;
        shared.release_lod(id).await;
        return Ok(());
    }
    state.skips().clear(id, u64::MAX);
    let id = id.to_string();
    on_data_dir(state, move |st| st.remove(&id)).await
}

/// Runs `f` on the data dir's store on a blocking thread; nothing without one.
async fn on_data_dir<S: Persisting>(
    state: &S,
    f: impl FnOnce(&Store) -> Result<(), StoreError> + Send + 'static,
) -> Result<(), ApiError> {
    if state.store().is_none() {
        return Ok(());
    }
    let state = state.clone();
    blocking(move || state.store().map_or(Ok(()), f).map_err(ApiError::internal)).await
}

/// Persists clip file `seq` of `rig` with `clips`, or deletes it when there are none.
pub async fn persist_clips<S: Persisting>(
    state: &S,
    id: &str,
    seq: u64,
    rig: Arc<Rig>,
    clips: Vec<crowdmorph_core::rig::Clip>,
) -> Result<(), ApiError> {
    if state.store().is_none() && state.shared_store().is_none() {
        return Ok(());
    }
    let owned = state.clone();
    let rid = id.to_string();
    let staged = blocking(move || {
        let id = rid;
        let record = RecordRef::Clips {
            id: &id,
            seq,
            clips: &clips,
            rig: &rig,
        };
        match (owned.shared_store(), owned.store()) {
            (Some(_), _) if clips.is_empty() => Ok(Some(SharedStore::clips_removed(&id, seq))),
            (Some(shared), _) => shared.stage(record).map(Some).map_err(ApiError::internal),
            (None, Some(store)) if clips.is_empty() => store
                .remove_clips(&id, seq)
                .map(|()| None)
                .map_err(ApiError::internal),
            (None, Some(store)) => store.put(record).map(|()| None).map_err(ApiError::internal),
            (None, None) => Ok(None),
        }
    })
    .await?;
    commit_staged(state, id, staged).await
}

// ---------------------------------------------------------------------------------------------
// Loading the data dir at start.

/// Loads the stored records one at a time, each charged to the memory pool before it is
/// read (about twice its file: the bytes read and the rig decoded from them) and then
/// holding what its prepared rig occupies. A record that does not fit is skipped and
/// reported, never deleted.
pub fn load_blocking<S: Persisting>(state: &S) -> Result<usize, StoreError> {
    let Some(store) = state.store() else {
        return Ok(0);
    };
    let mut n = 0;
    for (path, size) in store.record_files()? {
        let budget = Arc::new(Budget::new(
            state.pool().limit(),
            "--max-rig-memory",
            Some(state.pool().clone()),
        ));
        let file = path.display().to_string();
        // Reports about a rig's record are cleared when the rig is written or deleted.
        let rig = path
            .file_stem()
            .and_then(|s| s.to_str())
            .map(|s| s.split('@').next().unwrap_or(s).to_string());
        let skip = |why: String| match &rig {
            Some(id) => state.skips().skip_rig(id, 0, why),
            None => state.skips().skip(why),
        };
        if let Err(e) = budget.reserve(2 * size, || format!("stored record {file}")) {
            tracing::error!(error = %e, "skipping a stored rig that does not fit in memory");
            skip(e.to_string());
            continue;
        }
        let record = match Store::read_reporting(&path) {
            Ok((r, dropped)) => {
                for why in dropped {
                    skip(why);
                }
                r
            }
            Err(e) => {
                tracing::error!(error = %e, "skipping a stored rig that cannot be loaded");
                skip(e.to_string());
                continue;
            }
        };
        match load_record(state, record, &budget) {
            Ok(true) => n += 1,
            Ok(false) => {}
            Err(why) => skip(why),
        }
    }
    // Motion graphs come after the rigs they belong to; a graph file that does not parse
    // is skipped and reported, and graphs of a rig that is gone are left unused.
    let budget = Arc::new(Budget::new(
        state.pool().limit(),
        "--max-rig-memory",
        Some(state.pool().clone()),
    ));
    let (graphs, skipped) = store.load_graphs(|bytes, path| {
        budget
            .charge(bytes, || format!("stored graph file {}", path.display()))
            .map(drop)
            .map_err(|e| e.to_string())
    });
    for why in skipped {
        tracing::error!(error = %why, "skipping a stored graph file that cannot be read");
        state.skips().skip(why);
    }
    for g in graphs {
        if state.registry().get(&g.rig).is_some() {
            load_named(state, &g);
            state.graphs().load(g.rig, g.graphs);
        }
    }
    Ok(n)
}

/// Registers one stored record; `Ok(true)` for an uploaded rig, `Ok(false)` for the
/// built-in rig's clips and LOD.
fn load_record<S: Persisting>(state: &S, record: Record, budget: &Budget) -> Result<bool, String> {
    match record {
        Record::Rig(r) => load_rig(state, *r, budget).map(|()| true),
        Record::Clips(c) => load_clips(state, c, budget).map(|()| false),
        Record::Builtin(c) => load_builtin(state, c, budget).map(|()| false),
    }
}

/// An uploaded rig's record: a new entry.
fn load_rig<S: Persisting>(state: &S, r: StoredRig, budget: &Budget) -> Result<(), String> {
    if state.registry().get(&r.id).is_some() {
        return Err(format!("stored rig {:?} clashes with a built-in id", r.id));
    }
    let mut rig = r.rig;
    // The store keeps images encoded: decode them (charged) before the rig is served.
    crowdmorph_import::decode_stored_images(&mut rig, budget)
        .map_err(|e| format!("stored rig {:?}: {e}", r.id))?;
    let rig = Arc::new(rig);
    charge_preparing(state, &rig, budget)?;
    let prepared = state
        .engine()
        .prepare(rig.clone())
        .map_err(|e| format!("stored rig {:?}: {e}", r.id))?;
    let charge = budget.keep(prepared.memory().host_bytes as u64);
    state.registry().insert(Arc::new(RigEntry::new(NewEntry {
        id: r.id,
        builtin: None,
        prepared,
        generation: state.registry().generation(),
        layout: ClipLayout::in_record(&rig.clips),
        charge,
        qbox: quantization_box(&rig),
    })));
    Ok(())
}

/// A clip file: a new generation of its rig with the clips appended.
fn load_clips<S: Persisting>(state: &S, c: StoredClips, budget: &Budget) -> Result<(), String> {
    let Some(entry) = state.registry().get(&c.id) else {
        // The rig's record was deleted and the process stopped before its clip
        // files were: leftovers of a delete, not data anyone can reach.
        if let Some(store) = state.store() {
            tracing::warn!(rig = %c.id, seq = c.seq, "removing clips of a deleted rig");
            let _ = store.remove_clips(&c.id, c.seq);
        }
        return Ok(());
    };
    let mut rig = entry.rig().clone();
    let names: Vec<String> = c.clips.iter().map(|c| c.name.clone()).collect();
    let mut seen = std::collections::HashSet::new();
    if let Some(dup) = names
        .iter()
        .find(|n| entry.clip_index(n).is_some() || !seen.insert(n.as_str()))
    {
        return Err(format!(
            "clip file {} of rig {:?} repeats clip {dup:?}",
            c.seq, c.id
        ));
    }
    rig.clips.extend(c.clips);
    rig.validate()
        .map_err(|e| format!("clip file {} of rig {:?}: {e}", c.seq, c.id))?;
    let rig = Arc::new(rig);
    charge_preparing(state, &rig, budget)?;
    let prepared = state
        .engine()
        .update_clips(&entry.prepared, rig.clone())
        .map_err(|e| format!("clip file {} of rig {:?}: {e}", c.seq, c.id))?;
    let mut layout = entry.layout.clone();
    layout.files.push((c.seq, names));
    publish_successor(state, &entry, prepared, &rig, layout);
    Ok(())
}

/// Registers the next generation of `entry`: `rig` prepared, with its clips in `layout`.
fn publish_successor<S: Persisting>(
    state: &S,
    entry: &RigEntry,
    prepared: crowdmorph_engine::PreparedRig,
    rig: &Rig,
    layout: ClipLayout,
) {
    state.registry().insert(Arc::new(entry.successor(
        prepared,
        quantization_box(rig),
        layout,
        state.registry().generation(),
        None,
    )));
}

/// The built-in rig's stored clips and LOD: a new generation of it.
fn load_builtin<S: Persisting>(state: &S, c: StoredBuiltin, budget: &Budget) -> Result<(), String> {
    let Some(entry) = state.registry().get(&c.id).filter(|e| e.builtin) else {
        return Err(format!("stored clips for unknown built-in rig {:?}", c.id));
    };
    let mut rig = entry.rig().clone();
    let layout = ClipLayout {
        record: c.clips.iter().map(|c| c.name.clone()).collect(),
        files: entry.layout.files.clone(),
    };
    rig.clips.extend(c.clips);
    let mut lod_changed = false;
    if let Some((lod, geometry)) = c.lod {
        if geometry == geometry_fingerprint(&rig) {
            lod_changed = lod != rig.lod;
            rig.lod = lod;
        } else {
            // This build's built-in rig is not the one the LOD was made for;
            // the clips still apply, and the background job makes a new LOD.
            tracing::warn!(rig = %c.id, "stored LOD is for another version of the built-in rig; recomputing it");
        }
    }
    rig.validate()
        .map_err(|e| format!("stored clips and LOD of {:?}: {e}", c.id))?;
    let rig = Arc::new(rig);
    charge_preparing(state, &rig, budget)?;
    let prepared = if lod_changed {
        state.engine().prepare(rig.clone())
    } else {
        state.engine().update_clips(&entry.prepared, rig.clone())
    }
    .map_err(|e| format!("stored clips and LOD of {:?}: {e}", c.id))?;
    publish_successor(state, &entry, prepared, &rig, layout);
    Ok(())
}
