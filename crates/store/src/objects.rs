//! The shared rig store of replicas (`serve --store URL`): several `crowdmorph serve`
//! processes keep their rigs in one object store through the `object_store` crate, an
//! S3-compatible bucket (`s3://bucket/prefix`; endpoint and credentials from the standard
//! `AWS_*` environment variables, so MinIO, SeaweedFS, R2 and Ceph work) or a directory they
//! all reach (`file:///dir`).
//!
//! **Layout.** A rig's history is a chain of generations. Generation `g` of rig `id` is one
//! small JSON manifest, `manifests/<id>/<g:020>.json` ([`Manifest`]), which names every object
//! the rig is made of, each with its size and CRC-32: the rig's record (`<id>.cmrig`), its clip
//! files (`<id>@<seq>.cmclips`) and its motion graphs (`graphs.json`), in the data dir's own
//! checksummed formats ([`super::Store`] writes and reads them). Objects are immutable and
//! written under a name no other writer uses (`objects/<id>/<g:020>-<writer>/<file>`) before
//! the manifest that names them; a change that keeps an object names the old one again.
//!
//! **The pointer is the manifest's conditional create.** A replica writes generation `g + 1`
//! of a rig it holds at `g` with `PutMode::Create` (S3's `If-None-Match: *`, an exclusive
//! create on a directory): of two replicas writing the same rig at once exactly one succeeds;
//! the other gets [`SharedError::Conflict`] naming the store's newest generation, uploads
//! nothing visible, and changes nothing. A delete is a tombstone generation (`deleted`).
//!
//! **Reading.** A generation is used only when its manifest parses, names only objects of its
//! rig, and every object reads back with its stated size and checksum and decodes as a record:
//! a half-written or corrupt object makes that generation unusable (reported, never served),
//! and a reader keeps or falls back to the newest generation that does read back.
//!
//! **Damage is repaired, never built on.** A writer checks the size and CRC of every object
//! it carries into its next generation ([`SharedStore::check_objects`]) and restores a damaged
//! one from what it holds before it commits; a reader that meets a damaged generation leaves a
//! marker (`damaged/<id>/<g:020>.json`, [`SharedStore::report_damage`]) so that a replica
//! holding the damaged objects restores them as the next generation ([`SharedStore::salvage`]);
//! nobody commits past a damaged generation except that repair (or a delete), so a write whose
//! objects are intact is never dropped by a fork.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path as FsPath, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use futures_util::StreamExt;
use object_store::path::Path;
use object_store::{ObjectStore, ObjectStoreExt, PutMode, PutOptions, PutPayload};
use serde::{Deserialize, Serialize};

use super::{Record, RecordRef, Store, StoreError, StoredGraphs};

/// Name of the graphs object in a manifest.
pub const GRAPHS: &str = "graphs.json";
/// Largest manifest read: a manifest names a rig's files, a few hundred bytes each.
const MAX_MANIFEST: u64 = 16 << 20;
/// Largest graphs object read (a graph is a few kilobytes; the data dir has the same bound).
const MAX_GRAPHS: u64 = 64 << 20;
/// Most manifests read looking for an earlier intact copy of a damaged object.
pub const MAX_WALK: usize = 64;
/// Objects are uploaded in parts of this size (and read back in the store's chunks), so a
/// transfer holds a few parts, never a whole record.
const PART: usize = 8 << 20;

/// One generation of a rig in the shared store.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Manifest {
    /// The rig's id.
    pub rig: String,
    /// This generation's number (1, 2, ...; its key says the same).
    pub generation: u64,
    /// The replica that wrote it.
    pub writer: String,
    /// A tombstone: the rig was deleted in this generation.
    #[serde(default)]
    pub deleted: bool,
    /// The rig's objects by file name.
    pub objects: BTreeMap<String, ObjectRef>,
}

/// An object a manifest names.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ObjectRef {
    /// Its key in the store.
    pub key: String,
    /// Its length, bytes.
    pub size: u64,
    /// CRC-32 (IEEE) of its bytes.
    pub crc32: u32,
}

/// Why the shared store failed.
#[derive(Debug, thiserror::Error)]
pub enum SharedError {
    /// The URL names no store this build can open.
    #[error("store {url:?}: {problem}")]
    Url {
        /// The URL as given.
        url: String,
        /// What is wrong with it.
        problem: String,
    },
    /// The store did not answer, or refused an operation.
    #[error("the rig store {url} is unavailable: {problem}")]
    Unavailable {
        /// The store.
        url: String,
        /// What failed.
        problem: String,
    },
    /// The memory to read or prepare a generation is short now (it is tried again later).
    #[error("not enough rig memory now: {0}")]
    Memory(String),
    /// Another replica wrote the rig since this one read it: nothing was changed.
    #[error(
        "rig {rig:?} changed in the store {url}: its newest generation is {newest}, this \
         replica holds {held}; retry once it has refreshed"
    )]
    Conflict {
        /// The store.
        url: String,
        /// The rig.
        rig: String,
        /// The generation the write was based on.
        held: u64,
        /// The store's newest generation.
        newest: u64,
    },
    /// The rig's newest generation names a damaged object that is not repaired yet (or an
    /// object this replica would carry is damaged and it holds no copy): nothing was written.
    #[error(
        "rig {rig:?} in the store {url}: generation {generation} is damaged ({why}); nothing \
         is committed on top of it until it is repaired"
    )]
    Damaged {
        /// The store.
        url: String,
        /// The rig.
        rig: String,
        /// The damaged generation.
        generation: u64,
        /// What is damaged.
        why: String,
    },
    /// A record could not be staged locally.
    #[error(transparent)]
    Local(#[from] StoreError),
}

/// A change to one rig, staged and ready to commit with [`SharedStore::commit`].
#[derive(Debug)]
pub enum Change {
    /// An object (a record or a clip file) written to a local staging file.
    File {
        /// Its file name in the manifest.
        name: String,
        /// The staged file (removed by the commit).
        path: PathBuf,
    },
    /// The rig's motion graphs; none removes the object.
    Graphs(Vec<u8>),
    /// An object dropped from the rig (a clip file emptied, or a damaged one nobody holds).
    Remove(String),
    /// An object already in the store named again (a repair by an earlier intact copy).
    Keep {
        /// Its file name in the manifest.
        name: String,
        /// The object.
        object: ObjectRef,
    },
    /// The rig deleted.
    Delete,
}

/// A generation read back: its manifest and its decoded objects.
#[derive(Debug)]
pub struct Fetched {
    /// The manifest.
    pub manifest: Manifest,
    /// The records: the rig's (or built-in rig's) first, then clip files by sequence number.
    pub records: Vec<Record>,
    /// The motion graphs, when the rig has some.
    pub graphs: Option<StoredGraphs>,
    /// Compressed clips left out of the records (as [`Store::read_reporting`] says).
    pub dropped: Vec<String>,
}

/// Whether `name` is a file name a manifest of rig `id` may hold.
fn valid_name(id: &str, name: &str) -> bool {
    if name == GRAPHS || name == format!("{id}.{}", super::EXT) {
        return true;
    }
    name.strip_prefix(id)
        .and_then(|r| r.strip_prefix('@'))
        .and_then(|r| r.strip_suffix(&format!(".{}", super::CLIPS_EXT)))
        .is_some_and(|seq| seq.len() == 10 && seq.bytes().all(|b| b.is_ascii_digit()))
}

/// The staging directories of `changes`' files (removed once they are committed or not).
fn staged_dirs(changes: &[Change]) -> Vec<PathBuf> {
    changes
        .iter()
        .filter_map(|c| match c {
            Change::File { path, .. } => path.parent().and_then(|p| p.parent()).map(PathBuf::from),
            _ => None,
        })
        .collect()
}

/// Removes the staging directories of changes that will not be committed.
fn remove_staged(changes: &[Change]) {
    for dir in staged_dirs(changes) {
        let _ = std::fs::remove_dir_all(dir);
    }
}

/// Who computes a rig's LOD: the replica that claimed it and its heartbeat, which grows at
/// each of its refreshes while the build runs (or has failed); a claim whose heartbeat stops
/// for a lease is taken over.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct LodClaim {
    /// The claiming replica's name.
    pub writer: String,
    /// Its heartbeat.
    pub beat: u64,
    /// Its build failed (the claim is kept so that no other replica retries it).
    #[serde(default)]
    pub failed: bool,
}

/// Why a generation could not be read back.
#[derive(Debug)]
pub struct Unreadable {
    /// What is wrong, for the report.
    pub why: String,
    /// Its manifest, when that read back.
    pub manifest: Option<Manifest>,
    /// Whether an object it names is damaged: missing, of another length, or failing its
    /// checksum (a generation a repair can mend), rather than wrong in what it holds.
    pub damaged: bool,
}

impl Unreadable {
    fn manifest(why: String) -> Unreadable {
        Unreadable {
            why,
            manifest: None,
            damaged: false,
        }
    }
}

/// A rig store shared by replicas.
#[derive(Debug)]
pub struct SharedStore {
    objects: Arc<dyn ObjectStore>,
    url: String,
    /// This replica's name in the objects it writes (unique per process).
    writer: String,
    /// Where records are staged before upload and objects land before they are decoded.
    work: PathBuf,
    clip_error: Option<f32>,
    counter: AtomicU64,
    /// The generation of each rig this replica holds.
    held: Mutex<HashMap<String, Manifest>>,
    /// The newest generation of each rig this replica passed over (it did not read back): a
    /// change made here is committed after it, or it would conflict with it forever.
    passed: Mutex<HashMap<String, u64>>,
    /// Per rig, the newest generation found damaged (objects missing, short or failing their
    /// checksum) and why: nothing but its repair or a delete is committed after it.
    damaged: Mutex<HashMap<String, (u64, String)>>,
    /// Rigs whose held generation is to be installed again from the store.
    stale: Mutex<HashSet<String>>,
}

/// The parts of an object store URL.
fn open_url(url: &str, timeout: Duration) -> Result<Arc<dyn ObjectStore>, SharedError> {
    let bad = |problem: String| SharedError::Url {
        url: url.to_string(),
        problem,
    };
    if let Some(rest) = url.strip_prefix("s3://") {
        return open_s3(rest, timeout).map_err(bad);
    }
    let dir = match url.strip_prefix("file://") {
        Some(path) if path.starts_with('/') => PathBuf::from(path),
        Some(_) => return Err(bad("a file:// URL has an absolute path: file:///dir".into())),
        None if url.contains("://") => {
            return Err(bad(
                "the store is a path, file:///dir or s3://bucket/prefix".into(),
            ));
        }
        None => PathBuf::from(url),
    };
    std::fs::create_dir_all(&dir)
        .map_err(|e| bad(format!("cannot create directory {}: {e}", dir.display())))?;
    let dir = dir
        .canonicalize()
        .map_err(|e| bad(format!("{}: {e}", dir.display())))?;
    // Durable like the data dir: written files and their directories are fsynced before a
    // write returns.
    let local = object_store::local::LocalFileSystem::new_with_prefix(&dir)
        .map_err(|e| bad(e.to_string()))?
        .with_fsync(true);
    Ok(Arc::new(local))
}

/// An S3-compatible bucket, `rest` being `bucket/prefix` (endpoint and credentials from the
/// standard AWS environment variables).
#[cfg(feature = "s3")]
fn open_s3(rest: &str, timeout: Duration) -> Result<Arc<dyn ObjectStore>, String> {
    let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
    if bucket.is_empty() {
        return Err("an s3:// URL names a bucket: s3://bucket/prefix".into());
    }
    let retry = object_store::RetryConfig {
        max_retries: 2,
        retry_timeout: timeout,
        ..Default::default()
    };
    // Timeouts set key by key: `with_client_options` would replace the client options
    // `from_env` read (AWS_ALLOW_HTTP among them).
    use object_store::ClientConfigKey as C;
    use object_store::aws::AmazonS3ConfigKey as K;
    let connect = timeout.min(Duration::from_secs(2));
    let s3 = object_store::aws::AmazonS3Builder::from_env()
        .with_bucket_name(bucket)
        .with_retry(retry)
        // A stall of `timeout` fails a request; a large object may take longer in all.
        .with_config(
            K::Client(C::ReadTimeout),
            format!("{}ms", timeout.as_millis()),
        )
        .with_config(K::Client(C::Timeout), "1h")
        .with_config(
            K::Client(C::ConnectTimeout),
            format!("{}ms", connect.as_millis()),
        )
        .build()
        .map_err(|e| e.to_string())?;
    let store: Arc<dyn ObjectStore> = if prefix.trim_matches('/').is_empty() {
        Arc::new(s3)
    } else {
        Arc::new(object_store::prefix::PrefixStore::new(
            s3,
            prefix.trim_matches('/'),
        ))
    };
    Ok(store)
}

/// Without feature `s3` this build keeps no AWS client: the URL is refused by name.
#[cfg(not(feature = "s3"))]
fn open_s3(_rest: &str, _timeout: Duration) -> Result<Arc<dyn ObjectStore>, String> {
    Err(
        "this build has no S3 client: build crowdmorph-store with feature `s3` \
         (the crowdmorph binary has it by default)"
            .into(),
    )
}

impl SharedStore {
    /// Opens the store at `url` (nothing is read or written yet: [`SharedStore::check`] does),
    /// staging under `work` (created), with operations that give up after `timeout`.
    pub fn open(
        url: &str,
        work: &FsPath,
        timeout: Duration,
        clip_error: Option<f32>,
    ) -> Result<SharedStore, SharedError> {
        let objects = open_url(url, timeout)?;
        let writer = format!(
            "{}-{:08x}",
            std::process::id(),
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.subsec_nanos() ^ (d.as_secs() as u32))
                .unwrap_or(0)
        );
        let work = work.join(format!("store-{writer}"));
        std::fs::create_dir_all(&work).map_err(|e| SharedError::Url {
            url: url.to_string(),
            problem: format!(
                "cannot create the staging directory {}: {e}",
                work.display()
            ),
        })?;
        Ok(SharedStore {
            objects,
            url: url.to_string(),
            writer,
            work,
            clip_error,
            counter: AtomicU64::new(0),
            held: Mutex::new(HashMap::new()),
            passed: Mutex::new(HashMap::new()),
            damaged: Mutex::new(HashMap::new()),
            stale: Mutex::new(HashSet::new()),
        })
    }

    /// The store's URL.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// The error budget clips are stored within, when they are compressed.
    pub fn clip_error(&self) -> Option<f32> {
        self.clip_error
    }

    fn unavailable(&self, e: impl std::fmt::Display) -> SharedError {
        SharedError::Unavailable {
            url: self.url.clone(),
            problem: e.to_string(),
        }
    }

    /// Checks that the store answers and takes writes: lists it and writes, then deletes, a
    /// small object of this replica's own.
    pub async fn check(&self) -> Result<(), SharedError> {
        let mut listing = self.objects.list(Some(&Path::from("manifests")));
        if let Some(Err(e)) = listing.next().await {
            return Err(self.unavailable(format!("cannot list it: {e}")));
        }
        // The probe is created twice only-if-absent: a store that lets the second create
        // succeed would let two replicas both win one generation.
        let probe = Path::from(format!("writers/{}", self.writer));
        let create = || {
            self.objects.put_opts(
                &probe,
                PutPayload::from_static(b"crowdmorph"),
                PutOptions::from(PutMode::Create),
            )
        };
        create()
            .await
            .map_err(|e| self.unavailable(format!("cannot write to it: {e}")))?;
        let second = create().await;
        let _ = self.objects.delete(&probe).await;
        match second {
            Err(
                object_store::Error::AlreadyExists { .. }
                | object_store::Error::Precondition { .. },
            ) => Ok(()),
            Ok(_) => Err(self.unavailable(
                "it ignores conditional creates (If-None-Match: *), which replicas need to \
                 agree on a rig's next generation",
            )),
            Err(e) => Err(self.unavailable(format!("a conditional create failed: {e}"))),
        }
    }

    /// Every rig in the store and its generations, ascending (one listing).
    pub async fn list(&self) -> Result<BTreeMap<String, Vec<u64>>, SharedError> {
        self.list_under("manifests").await
    }

    /// Generations of rig `id`, ascending (one listing); empty when the store has none.
    pub async fn generations(&self, id: &str) -> Result<Vec<u64>, SharedError> {
        Ok(self
            .list_under(&format!("manifests/{id}"))
            .await?
            .remove(id)
            .unwrap_or_default())
    }

    async fn list_under(&self, prefix: &str) -> Result<BTreeMap<String, Vec<u64>>, SharedError> {
        let mut rigs: BTreeMap<String, Vec<u64>> = BTreeMap::new();
        let mut listing = self.objects.list(Some(&Path::from(prefix)));
        while let Some(meta) = listing.next().await {
            let meta = meta.map_err(|e| self.unavailable(format!("cannot list it: {e}")))?;
            let mut parts = meta.location.parts();
            let (Some(_), Some(id), Some(file), None) =
                (parts.next(), parts.next(), parts.next(), parts.next())
            else {
                continue;
            };
            let Some(generation) = file
                .as_ref()
                .strip_suffix(".json")
                .and_then(|g| g.parse::<u64>().ok())
            else {
                continue;
            };
            rigs.entry(id.as_ref().to_string())
                .or_default()
                .push(generation);
        }
        for g in rigs.values_mut() {
            g.sort_unstable();
        }
        Ok(rigs)
    }

    /// The generation of rig `id` this replica holds (0: none).
    pub fn held(&self, id: &str) -> u64 {
        self.held
            .lock()
            .ok()
            .and_then(|h| h.get(id).map(|m| m.generation))
            .unwrap_or(0)
    }

    /// Remembers that generation `g` of rig `id` was passed over: the next change of the rig
    /// made here is committed as a later one (on the content this replica holds).
    pub fn pass_over(&self, id: &str, g: u64) {
        if let Ok(mut p) = self.passed.lock() {
            let e = p.entry(id.to_string()).or_insert(g);
            *e = (*e).max(g);
        }
    }

    /// Records that this replica now holds `manifest`'s generation of its rig, as it is in
    /// the store: a damaged generation it supersedes no longer holds changes up.
    pub fn set_held(&self, manifest: Manifest) {
        if let Ok(mut d) = self.damaged.lock()
            && d.get(&manifest.rig)
                .is_some_and(|(g, _)| *g <= manifest.generation)
        {
            d.remove(&manifest.rig);
        }
        if let Ok(mut s) = self.stale.lock() {
            s.remove(&manifest.rig);
        }
        if let Ok(mut h) = self.held.lock() {
            h.insert(manifest.rig.clone(), manifest);
        }
    }

    fn scratch(&self, what: &str) -> PathBuf {
        let n = self.counter.fetch_add(1, Ordering::Relaxed);
        self.work.join(format!("{what}-{n}"))
    }

    /// Writes `record` to a staging file in the data dir's format (blocking: call it off the
    /// runtime), ready to commit.
    pub fn stage(&self, record: RecordRef<'_>) -> Result<Change, SharedError> {
        let dir = self.scratch("stage");
        let store = Store::open(&dir)?.compress_clips(self.clip_error);
        store.put(record)?;
        let path = match record {
            RecordRef::Rig { id, .. } | RecordRef::Builtin { id, .. } => store.path_of(id),
            RecordRef::Clips { id, seq, .. } => store.clips_path(id, seq),
        };
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        Ok(Change::File { name, path })
    }

    /// The change that removes clip file `seq` of rig `id`.
    pub fn clips_removed(id: &str, seq: u64) -> Change {
        Change::Remove(format!("{id}@{seq:010}.{}", super::CLIPS_EXT))
    }

    /// The change that stores rig `stored.rig`'s motion graphs, masks and mappings (or removes
    /// them when there are none).
    pub fn graphs_change(stored: &StoredGraphs) -> Result<Change, SharedError> {
        if stored.is_empty() {
            return Ok(Change::Remove(GRAPHS.to_string()));
        }
        serde_json::to_vec(stored)
            .map(Change::Graphs)
            .map_err(|e| SharedError::Local(StoreError::Encode(e.to_string())))
    }

    /// Writes the next generation of rig `id` with `changes` on top of the generation this
    /// replica holds: new objects first, then the manifest, created only if no other replica
    /// has written that generation. Returns the generation written; on
    /// [`SharedError::Conflict`] nothing is visible. While the rig's newest generation is
    /// damaged and not yet repaired ([`SharedStore::mark_damaged`]), every change but a delete
    /// is refused with [`SharedError::Damaged`]: committing past it on an older generation
    /// would drop its intact objects, the writes of another replica.
    pub async fn commit(&self, id: &str, changes: Vec<Change>) -> Result<u64, SharedError> {
        let base = self.held.lock().ok().and_then(|h| h.get(id).cloned());
        let held = base.as_ref().map_or(0, |m| m.generation);
        let passed = self
            .passed
            .lock()
            .ok()
            .and_then(|p| p.get(id).copied())
            .unwrap_or(0);
        let deleting = changes.iter().any(|c| matches!(c, Change::Delete));
        if !deleting && let Some((generation, why)) = self.damaged_after(id, held) {
            remove_staged(&changes);
            return Err(SharedError::Damaged {
                url: self.url.clone(),
                rig: id.to_string(),
                generation,
                why,
            });
        }
        let manifest = self
            .write_generation(id, base, held.max(passed) + 1, changes, held)
            .await?;
        let generation = manifest.generation;
        self.set_held(manifest);
        Ok(generation)
    }

    /// Writes generation `g + 1` of `damaged`'s rig (generation `g`) with `repairs` in place
    /// of its damaged objects, created only if absent; this replica's held generation is not
    /// changed (it installs the repair like any other generation, from the store).
    pub async fn salvage(
        &self,
        damaged: Manifest,
        repairs: Vec<Change>,
    ) -> Result<u64, SharedError> {
        let (id, g) = (damaged.rig.clone(), damaged.generation);
        self.write_generation(&id, Some(damaged), g + 1, repairs, g)
            .await
            .map(|m| m.generation)
    }

    /// Writes `generation` of rig `id`: `base`'s objects with `changes` applied. `held` is the
    /// generation a conflict names as the one the write was based on.
    async fn write_generation(
        &self,
        id: &str,
        base: Option<Manifest>,
        generation: u64,
        changes: Vec<Change>,
        held: u64,
    ) -> Result<Manifest, SharedError> {
        let mut objects = base
            .filter(|m| !m.deleted)
            .map(|m| m.objects)
            .unwrap_or_default();
        let dir = format!("objects/{id}/{generation:020}-{}", self.writer);
        let mut deleted = false;
        let mut uploaded = Vec::new();
        let staged = staged_dirs(&changes);
        let result = async {
            for change in changes {
                match change {
                    Change::File { name, path } => {
                        let key = format!("{dir}/{name}");
                        let object = self.upload_file(&path, &key).await?;
                        uploaded.push(key);
                        objects.insert(name, object);
                    }
                    Change::Graphs(bytes) => {
                        let key = format!("{dir}/{GRAPHS}");
                        let object = self.upload_bytes(Bytes::from(bytes), &key).await?;
                        uploaded.push(key);
                        objects.insert(GRAPHS.to_string(), object);
                    }
                    Change::Keep { name, object } => {
                        objects.insert(name, object);
                    }
                    Change::Remove(name) => {
                        objects.remove(&name);
                    }
                    Change::Delete => {
                        objects.clear();
                        deleted = true;
                    }
                }
            }
            let manifest = Manifest {
                rig: id.to_string(),
                generation,
                writer: self.writer.clone(),
                deleted,
                objects,
            };
            let json = serde_json::to_vec_pretty(&manifest)
                .map_err(|e| SharedError::Local(StoreError::Encode(e.to_string())))?;
            let key = Path::from(format!("manifests/{id}/{generation:020}.json"));
            let put = self
                .objects
                .put_opts(
                    &key,
                    PutPayload::from(json),
                    PutOptions::from(PutMode::Create),
                )
                .await;
            match put {
                Ok(_) => {}
                Err(
                    object_store::Error::AlreadyExists { .. }
                    | object_store::Error::Precondition { .. },
                ) => {
                    let newest = self
                        .generations(id)
                        .await
                        .ok()
                        .and_then(|g| g.last().copied())
                        .unwrap_or(generation);
                    return Err(SharedError::Conflict {
                        url: self.url.clone(),
                        rig: id.to_string(),
                        held,
                        newest,
                    });
                }
                Err(e) => return Err(self.unavailable(format!("cannot write {key}: {e}"))),
            }
            Ok(manifest)
        }
        .await;
        for dir in staged {
            let _ = std::fs::remove_dir_all(dir);
        }
        if result.is_err() {
            // The objects nobody will name: removed, best effort (a leftover is harmless).
            for key in uploaded {
                let _ = self.objects.delete(&Path::from(key)).await;
            }
        }
        result
    }

    /// The objects of the generation this replica holds of rig `id` that a commit of
    /// `changes` would name again (those the changes replace or remove left out): what a
    /// writer checks before it builds on them.
    pub fn carried(&self, id: &str, changes: &[Change]) -> Vec<(String, ObjectRef)> {
        if changes.iter().any(|c| matches!(c, Change::Delete)) {
            return Vec::new();
        }
        let touched: HashSet<&str> = changes
            .iter()
            .filter_map(|c| match c {
                Change::File { name, .. } | Change::Keep { name, .. } | Change::Remove(name) => {
                    Some(name.as_str())
                }
                Change::Graphs(_) => Some(GRAPHS),
                Change::Delete => None,
            })
            .collect();
        self.held
            .lock()
            .ok()
            .and_then(|h| h.get(id).cloned())
            .filter(|m| !m.deleted)
            .map(|m| {
                m.objects
                    .into_iter()
                    .filter(|(name, _)| !touched.contains(name.as_str()))
                    .collect()
            })
            .unwrap_or_default()
    }

    /// The key under which the generation this replica holds names object `name` of rig `id`:
    /// when it is the key of a damaged object, this replica has that object's content.
    pub fn held_key(&self, id: &str, name: &str) -> Option<String> {
        self.held.lock().ok().and_then(|h| {
            h.get(id)
                .filter(|m| !m.deleted)
                .and_then(|m| m.objects.get(name).map(|o| o.key.clone()))
        })
    }

    /// Reads every one of `objects` back (streamed, nothing kept) and returns those whose
    /// bytes are missing, of another length or fail their checksum, each with why. A store
    /// that does not answer is an `Err`.
    pub async fn check_objects(
        &self,
        objects: &[(String, ObjectRef)],
    ) -> Result<Vec<(String, ObjectRef, String)>, SharedError> {
        let mut damaged = Vec::new();
        for (name, object) in objects {
            if let Err(why) = self.read_checked(object, None).await? {
                damaged.push((name.clone(), object.clone(), why));
            }
        }
        Ok(damaged)
    }

    /// The newest intact copy of object `name` of rig `id` in a generation before `below`
    /// under a key other than `not_keys` (the damaged one), if the rig named `name` in every
    /// generation from there on: a copy from before a generation that removed the object, or
    /// before a delete, would bring back what was removed, so the walk stops there. At most
    /// [`MAX_WALK`] manifests are read, each charged to `charge` first.
    pub async fn earlier_copy(
        &self,
        id: &str,
        below: u64,
        name: &str,
        not_key: &str,
        charge: &(dyn Fn(u64, &str) -> Result<(), String> + Sync),
    ) -> Result<Option<(u64, ObjectRef)>, SharedError> {
        let generations = self.generations(id).await?;
        let mut bad: HashSet<String> = HashSet::from([not_key.to_string()]);
        for &g in generations
            .iter()
            .rev()
            .filter(|&&g| g < below)
            .take(MAX_WALK)
        {
            let Ok(manifest) = self.manifest(id, g, charge).await? else {
                // A manifest that does not read says nothing about the object: look further.
                continue;
            };
            let Some(object) = manifest.objects.get(name).filter(|_| !manifest.deleted) else {
                return Ok(None);
            };
            if bad.contains(&object.key) {
                continue;
            }
            match self.read_checked(object, None).await? {
                Ok(()) => return Ok(Some((g, object.clone()))),
                Err(_) => {
                    bad.insert(object.key.clone());
                }
            }
        }
        Ok(None)
    }

    /// Leaves a marker saying that generation `g` of rig `id` is damaged
    /// (`damaged/<id>/<g:020>.json`), so that a replica holding the damaged objects, which
    /// never reads back a generation it holds, restores them.
    pub async fn report_damage(&self, id: &str, g: u64, why: &str) -> Result<(), SharedError> {
        let body = serde_json::json!({
            "rig": id,
            "generation": g,
            "reporter": self.writer,
            "why": why,
        });
        let key = format!("damaged/{id}/{g:020}.json");
        self.objects
            .put(
                &Path::from(key.as_str()),
                PutPayload::from(body.to_string()),
            )
            .await
            .map(drop)
            .map_err(|e| self.unavailable(format!("cannot write {key}: {e}")))
    }

    /// Every damage marker in the store: (rig, generation), one listing.
    pub async fn damage_reports(&self) -> Result<Vec<(String, u64)>, SharedError> {
        Ok(self
            .list_under("damaged")
            .await?
            .into_iter()
            .flat_map(|(id, gs)| gs.into_iter().map(move |g| (id.clone(), g)))
            .collect())
    }

    /// Removes the damage marker of generation `g` of rig `id` (repaired or superseded).
    pub async fn clear_damage(&self, id: &str, g: u64) {
        let key = format!("damaged/{id}/{g:020}.json");
        if let Err(e) = self.objects.delete(&Path::from(key.as_str())).await
            && !matches!(e, object_store::Error::NotFound { .. })
        {
            tracing::warn!(error = %e, key, "cannot remove a damage marker");
        }
    }

    /// Remembers that generation `g` of rig `id`, its newest, is damaged (`why`): changes
    /// other than a delete wait for its repair.
    pub fn mark_damaged(&self, id: &str, g: u64, why: &str) {
        if let Ok(mut d) = self.damaged.lock() {
            let e = d.entry(id.to_string()).or_insert((g, why.to_string()));
            if g >= e.0 {
                *e = (g, why.to_string());
            }
        }
    }

    /// The damaged generation of rig `id` newer than `held`, with why, if there is one.
    fn damaged_after(&self, id: &str, held: u64) -> Option<(u64, String)> {
        self.damaged
            .lock()
            .ok()
            .and_then(|d| d.get(id).cloned())
            .filter(|(g, _)| *g > held)
    }

    /// Remembers that the generation held of rig `id` is not what this replica serves (a
    /// commit restored a damaged object from an earlier copy, or dropped it): the next
    /// refresh installs it from the store.
    pub fn mark_stale(&self, id: &str) {
        if let Ok(mut s) = self.stale.lock() {
            s.insert(id.to_string());
        }
    }

    /// Whether the generation held of rig `id` is to be installed again ([`Self::mark_stale`]).
    pub fn is_stale(&self, id: &str) -> bool {
        self.stale.lock().is_ok_and(|s| s.contains(id))
    }

    /// Uploads a staged file in parts, checksumming it as it goes.
    async fn upload_file(&self, path: &FsPath, key: &str) -> Result<ObjectRef, SharedError> {
        use tokio::io::AsyncReadExt;
        let local = |e: std::io::Error| {
            SharedError::Local(StoreError::Io {
                op: "read",
                path: path.display().to_string(),
                source: e,
            })
        };
        let mut file = tokio::fs::File::open(path).await.map_err(local)?;
        let size = file.metadata().await.map_err(local)?.len();
        if size <= PART as u64 {
            let mut bytes = Vec::with_capacity(size as usize);
            file.read_to_end(&mut bytes).await.map_err(local)?;
            return self.upload_bytes(Bytes::from(bytes), key).await;
        }
        let location = Path::from(key);
        let upload = self
            .objects
            .put_multipart(&location)
            .await
            .map_err(|e| self.unavailable(format!("cannot write {key}: {e}")))?;
        let mut writer = object_store::WriteMultipart::new_with_chunk_size(upload, PART);
        let mut crc = crc32fast::Hasher::new();
        let mut buf = vec![0u8; PART];
        loop {
            let n = file.read(&mut buf).await.map_err(local)?;
            if n == 0 {
                break;
            }
            crc.update(&buf[..n]);
            writer
                .wait_for_capacity(2)
                .await
                .map_err(|e| self.unavailable(format!("cannot write {key}: {e}")))?;
            writer.write(&buf[..n]);
        }
        writer
            .finish()
            .await
            .map_err(|e| self.unavailable(format!("cannot write {key}: {e}")))?;
        Ok(ObjectRef {
            key: key.to_string(),
            size,
            crc32: crc.finalize(),
        })
    }

    async fn upload_bytes(&self, bytes: Bytes, key: &str) -> Result<ObjectRef, SharedError> {
        let object = ObjectRef {
            key: key.to_string(),
            size: bytes.len() as u64,
            crc32: crc32fast::hash(&bytes),
        };
        self.objects
            .put(&Path::from(key), PutPayload::from(bytes))
            .await
            .map_err(|e| self.unavailable(format!("cannot write {key}: {e}")))?;
        Ok(object)
    }

    /// Manifest `generation` of rig `id`, parsed and checked (its rig, its number, names and
    /// keys that are the rig's own); `Ok(Err)` says why it cannot be used.
    pub async fn manifest(
        &self,
        id: &str,
        generation: u64,
        charge: &(dyn Fn(u64, &str) -> Result<(), String> + Sync),
    ) -> Result<Result<Manifest, String>, SharedError> {
        let key = format!("manifests/{id}/{generation:020}.json");
        let bytes = match self.read_manifest(&key, charge).await? {
            Ok(b) => b,
            Err(why) => return Ok(Err(why)),
        };
        let manifest: Manifest = match serde_json::from_slice(&bytes) {
            Ok(m) => m,
            Err(e) => return Ok(Err(format!("{}: {key}: not a manifest: {e}", self.url))),
        };
        if manifest.rig != id || manifest.generation != generation {
            return Ok(Err(format!(
                "{}: {key} is for rig {:?} generation {}",
                self.url, manifest.rig, manifest.generation
            )));
        }
        let prefix = format!("objects/{id}/");
        if let Some((name, o)) = manifest
            .objects
            .iter()
            .find(|(name, o)| !valid_name(id, name) || !o.key.starts_with(&prefix))
        {
            return Ok(Err(format!(
                "{}: {key} names an object that is not rig {id:?}'s: {name:?} at {:?}",
                self.url, o.key
            )));
        }
        Ok(Ok(manifest))
    }

    /// Reads generation `generation` of rig `id` back: its manifest, then each object, whose
    /// memory `charge` is asked for first (twice its size: its bytes and what they decode
    /// to). `Err` says why the generation cannot be used; a store that does not answer is
    /// [`SharedError::Unavailable`], anything wrong with what it holds an [`Unreadable`].
    pub async fn fetch(
        &self,
        id: &str,
        generation: u64,
        charge: &(dyn Fn(u64, &str) -> Result<(), String> + Sync),
    ) -> Result<Result<Fetched, Unreadable>, SharedError> {
        let manifest = match self.manifest(id, generation, charge).await? {
            Ok(m) => m,
            Err(why) => return Ok(Err(Unreadable::manifest(why))),
        };
        let unreadable = |why: String, damaged: bool| Unreadable {
            why,
            manifest: Some(manifest.clone()),
            damaged,
        };
        let mut fetched = Fetched {
            manifest: manifest.clone(),
            records: Vec::new(),
            graphs: None,
            dropped: Vec::new(),
        };
        for (name, object) in &manifest.objects {
            let limit = if name == GRAPHS { MAX_GRAPHS } else { u64::MAX };
            if object.size > limit {
                return Ok(Err(unreadable(
                    format!(
                        "{}: {} is {} bytes, more than a graphs object may be",
                        self.url, object.key, object.size
                    ),
                    false,
                )));
            }
            if let Err(why) = charge(object.size.saturating_mul(2), &object.key) {
                return Ok(Err(unreadable(why, false)));
            }
            let dir = self.scratch("fetch");
            let path = dir.join("rigs").join(name);
            let got = self.read_checked(object, Some(&path)).await;
            let outcome = match got {
                Ok(Ok(())) if name == GRAPHS => std::fs::read(&path)
                    .map_err(|e| e.to_string())
                    .and_then(|b| {
                        serde_json::from_slice::<StoredGraphs>(&b).map_err(|e| e.to_string())
                    })
                    .map(|g| fetched.graphs = Some(g))
                    .map_err(|e| (format!("{}: {}: {e}", self.url, object.key), false)),
                Ok(Ok(())) => {
                    let path = path.clone();
                    match tokio::task::spawn_blocking(move || Store::read_reporting(&path)).await {
                        Ok(Ok((record, dropped))) => {
                            fetched.records.push(record);
                            fetched.dropped.extend(dropped);
                            Ok(())
                        }
                        Ok(Err(e)) => Err((format!("{}: {}: {e}", self.url, object.key), false)),
                        Err(e) => Err((e.to_string(), false)),
                    }
                }
                Ok(Err(why)) => Err((why, true)),
                Err(e) => {
                    let _ = std::fs::remove_dir_all(&dir);
                    return Err(e);
                }
            };
            let _ = std::fs::remove_dir_all(&dir);
            if let Err((why, damaged)) = outcome {
                return Ok(Err(unreadable(why, damaged)));
            }
        }
        Ok(Ok(fetched))
    }

    /// Manifest `key`'s bytes, charged to `charge` before they are read; `Ok(Err)` when it is
    /// missing or larger than [`MAX_MANIFEST`] (a generation that cannot be used, not a store
    /// that does not answer).
    async fn read_manifest(
        &self,
        key: &str,
        charge: &(dyn Fn(u64, &str) -> Result<(), String> + Sync),
    ) -> Result<Result<Bytes, String>, SharedError> {
        let got = match self.objects.get(&Path::from(key)).await {
            Ok(g) => g,
            Err(object_store::Error::NotFound { .. }) => {
                return Ok(Err(format!("{}: {key} is missing", self.url)));
            }
            Err(e) => return Err(self.unavailable(format!("cannot read {key}: {e}"))),
        };
        if got.meta.size > MAX_MANIFEST {
            return Ok(Err(format!(
                "{}: {key} is {} bytes, more than a manifest may be ({MAX_MANIFEST})",
                self.url, got.meta.size
            )));
        }
        if let Err(why) = charge(got.meta.size, key) {
            return Ok(Err(why));
        }
        got.bytes()
            .await
            .map(Ok)
            .map_err(|e| self.unavailable(format!("cannot read {key}: {e}")))
    }

    /// Streams `object` into `path` (or only through the checksum, without a path), checking
    /// its length and checksum against the manifest; `Ok(Err)` for an object that is
    /// missing, longer or shorter, or damaged.
    async fn read_checked(
        &self,
        object: &ObjectRef,
        path: Option<&FsPath>,
    ) -> Result<Result<(), String>, SharedError> {
        use tokio::io::AsyncWriteExt;
        let key = &object.key;
        let got = match self.objects.get(&Path::from(key.as_str())).await {
            Ok(g) => g,
            Err(object_store::Error::NotFound { .. }) => {
                return Ok(Err(format!("{}: {key} is missing", self.url)));
            }
            Err(e) => return Err(self.unavailable(format!("cannot read {key}: {e}"))),
        };
        if got.meta.size != object.size {
            return Ok(Err(format!(
                "{}: {key} is {} bytes, its manifest says {} (half-written or replaced)",
                self.url, got.meta.size, object.size
            )));
        }
        let local = |e: std::io::Error| {
            SharedError::Local(StoreError::Io {
                op: "write",
                path: path.map(|p| p.display().to_string()).unwrap_or_default(),
                source: e,
            })
        };
        let mut file = match path {
            Some(path) => {
                if let Some(dir) = path.parent() {
                    tokio::fs::create_dir_all(dir).await.map_err(local)?;
                }
                Some(tokio::fs::File::create(path).await.map_err(local)?)
            }
            None => None,
        };
        let mut crc = crc32fast::Hasher::new();
        let mut len = 0u64;
        let mut stream = got.into_stream();
        while let Some(chunk) = stream.next().await {
            let chunk = chunk.map_err(|e| self.unavailable(format!("cannot read {key}: {e}")))?;
            len += chunk.len() as u64;
            if len > object.size {
                return Ok(Err(format!(
                    "{}: {key} is longer than its manifest says",
                    self.url
                )));
            }
            crc.update(&chunk);
            if let Some(file) = &mut file {
                file.write_all(&chunk).await.map_err(local)?;
            }
        }
        if let Some(file) = &mut file {
            file.flush().await.map_err(local)?;
        }
        if len != object.size {
            return Ok(Err(format!(
                "{}: {key} ended after {len} of {} bytes",
                self.url, object.size
            )));
        }
        if crc.finalize() != object.crc32 {
            return Ok(Err(format!(
                "{}: {key} does not match its checksum (damaged)",
                self.url
            )));
        }
        Ok(Ok(()))
    }

    /// The LOD claim of rig `id` (`lod/<id>.json`): which replica computes the rig's LOD
    /// and its heartbeat; `None` when nobody claims it. A claim that does not parse is one of
    /// nobody's (its writer is empty).
    pub async fn lod_claim(&self, id: &str) -> Result<Option<LodClaim>, SharedError> {
        let key = Path::from(format!("lod/{id}.json"));
        let got = match self.objects.get(&key).await {
            Ok(g) => g,
            Err(object_store::Error::NotFound { .. }) => return Ok(None),
            Err(e) => return Err(self.unavailable(format!("cannot read {key}: {e}"))),
        };
        if got.meta.size > 4096 {
            return Ok(Some(LodClaim::default()));
        }
        let bytes = got
            .bytes()
            .await
            .map_err(|e| self.unavailable(format!("cannot read {key}: {e}")))?;
        Ok(Some(serde_json::from_slice(&bytes).unwrap_or_default()))
    }

    /// Claims (or keeps claiming: `beat` grows with each heartbeat) the LOD build of rig
    /// `id` for this replica; `failed` says its build failed (it is not retried elsewhere).
    pub async fn claim_lod(&self, id: &str, beat: u64, failed: bool) -> Result<(), SharedError> {
        let claim = LodClaim {
            writer: self.writer.clone(),
            beat,
            failed,
        };
        let key = Path::from(format!("lod/{id}.json"));
        let json = serde_json::to_vec(&claim)
            .map_err(|e| SharedError::Local(StoreError::Encode(e.to_string())))?;
        self.objects
            .put(&key, PutPayload::from(json))
            .await
            .map(drop)
            .map_err(|e| self.unavailable(format!("cannot write {key}: {e}")))
    }

    /// Removes rig `id`'s LOD claim (its LOD is in the store, or the rig is gone).
    pub async fn release_lod(&self, id: &str) {
        let key = Path::from(format!("lod/{id}.json"));
        if let Err(e) = self.objects.delete(&key).await
            && !matches!(e, object_store::Error::NotFound { .. })
        {
            tracing::warn!(error = %e, %key, "cannot remove a LOD claim");
        }
    }

    /// This replica's name in what it writes.
    pub fn writer(&self) -> &str {
        &self.writer
    }

    /// Deletes this replica's staging directory (at exit; leftovers of a killed process are
    /// under the data dir, named by their process).
    pub fn clean_up(&self) {
        let _ = std::fs::remove_dir_all(&self.work);
    }
}

/// Generations the replica could not use, each reported once, and when it first knew of
/// damage to a generation (unusable here, or marked by another replica): a repair from
/// whatever copy is left waits a grace period from then for a replica holding the exact
/// objects.
#[derive(Debug, Default)]
pub struct Unusable(Mutex<UnusableSets>);

#[derive(Debug, Default)]
struct UnusableSets {
    unusable: HashSet<(String, u64)>,
    damage_seen: HashMap<(String, u64), Instant>,
    repair_tried: HashMap<(String, u64), Instant>,
}

impl Unusable {
    /// Whether generation `g` of `id` is known to be unusable.
    pub fn contains(&self, id: &str, g: u64) -> bool {
        self.0
            .lock()
            .map(|s| s.unusable.contains(&(id.to_string(), g)))
            .unwrap_or(false)
    }

    /// Remembers that generation `g` of `id` is unusable; `true` the first time.
    pub fn insert(&self, id: &str, g: u64) -> bool {
        self.0
            .lock()
            .map(|mut s| s.unusable.insert((id.to_string(), g)))
            .unwrap_or(false)
    }

    /// When generation `g` of `id` was first known to be damaged here (now, the first time).
    pub fn damage_seen(&self, id: &str, g: u64) -> Instant {
        self.0
            .lock()
            .map(|mut s| {
                *s.damage_seen
                    .entry((id.to_string(), g))
                    .or_insert_with(Instant::now)
            })
            .unwrap_or_else(|_| Instant::now())
    }

    /// Whether a repair of generation `g` of `id` may be tried now: not tried within
    /// `every` (a repair reads the whole generation back). Counts this try.
    pub fn may_try_repair(&self, id: &str, g: u64, every: Duration) -> bool {
        self.0
            .lock()
            .map(|mut s| {
                let key = (id.to_string(), g);
                if s.repair_tried
                    .get(&key)
                    .is_some_and(|t| t.elapsed() < every)
                {
                    return false;
                }
                s.repair_tried.insert(key, Instant::now());
                true
            })
            .unwrap_or(false)
    }

    /// Forgets the generations of `id` before `g` (superseded: never read again).
    pub fn forget_below(&self, id: &str, g: u64) {
        if let Ok(mut s) = self.0.lock() {
            s.unusable
                .retain(|(rig, generation)| rig != id || *generation >= g);
            s.damage_seen
                .retain(|(rig, generation), _| rig != id || *generation >= g);
            s.repair_tried
                .retain(|(rig, generation), _| rig != id || *generation >= g);
        }
    }
}

/// Most remembered misses (rig ids the store did not have, until the next refresh).
const MAX_MISSES: usize = 4096;

/// Rig ids the store did not have when last asked, with when.
#[derive(Debug, Default)]
pub struct Misses(Mutex<HashMap<String, Instant>>);

impl Misses {
    /// Whether `id` was a miss less than `within` ago.
    pub fn recent(&self, id: &str, within: Duration) -> bool {
        self.0
            .lock()
            .map(|m| m.get(id).is_some_and(|t| t.elapsed() < within))
            .unwrap_or(false)
    }

    /// Remembers that the store has no rig `id` now.
    pub fn insert(&self, id: &str) {
        if let Ok(mut m) = self.0.lock() {
            if m.len() >= MAX_MISSES {
                m.clear();
            }
            m.insert(id.to_string(), Instant::now());
        }
    }

    /// Forgets a miss (the rig was written or found).
    pub fn forget(&self, id: &str) {
        if let Ok(mut m) = self.0.lock() {
            m.remove(id);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_a_manifest_may_hold() {
        assert!(valid_name("a", "a.cmrig"));
        assert!(valid_name("a", "a@0000000003.cmclips"));
        assert!(valid_name("a", GRAPHS));
        for bad in [
            "b.cmrig",
            "a@3.cmclips",
            "a@000000000x.cmclips",
            "../a.cmrig",
            "a.cmrig/..",
            "ab@0000000003.cmclips",
        ] {
            assert!(!valid_name("a", bad), "{bad}");
        }
    }

    fn temp(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!(
            "crowdmorph-objects-{tag}-{}-{:?}",
            std::process::id(),
            std::time::SystemTime::now()
        ));
        std::fs::create_dir_all(&d).expect("temp dir");
        d
    }

    /// Two replicas writing the next generation of one rig: one commit wins, the other is a
    /// conflict that names the newest generation; once the loser has passed over a
    /// generation it could not use, its next change goes after it.
    #[tokio::test]
    async fn one_of_two_writers_wins_and_a_passed_generation_is_skipped() {
        let (root, work) = (temp("root"), temp("work"));
        let url = root.display().to_string();
        let open = || SharedStore::open(&url, &work, Duration::from_secs(5), None).expect("open");
        let (a, b) = (open(), open());
        a.check().await.expect("the store answers");
        let graphs = |n: u8| {
            Change::Graphs(format!("{{\"rig\":\"r\",\"graphs\":[],\"n\":{n}}}").into_bytes())
        };
        let (ra, rb) = tokio::join!(
            a.commit("r", vec![graphs(1)]),
            b.commit("r", vec![graphs(2)])
        );
        let won = [ra.is_ok(), rb.is_ok()];
        assert_eq!(won.iter().filter(|&&w| w).count(), 1, "{ra:?} {rb:?}");
        let (winner, loser, lost) = if ra.is_ok() {
            (&a, &b, rb)
        } else {
            (&b, &a, ra)
        };
        match lost {
            Err(SharedError::Conflict {
                held: 0, newest: 1, ..
            }) => {}
            other => panic!("not a conflict at generation 1: {other:?}"),
        }
        assert_eq!(a.generations("r").await.expect("list"), vec![1]);
        assert_eq!(winner.held("r"), 1);
        assert_eq!(loser.held("r"), 0, "the loser changed nothing");

        // The winner writes 2; the loser cannot use 1 or 2 (say): it passes them over and
        // commits 3, on what it holds.
        winner
            .commit("r", vec![graphs(3)])
            .await
            .expect("generation 2");
        loser.pass_over("r", 2);
        assert_eq!(
            loser
                .commit("r", vec![Change::Delete])
                .await
                .expect("after"),
            3
        );
        assert_eq!(winner.list().await.expect("list")["r"], vec![1, 2, 3]);
        let _ = std::fs::remove_dir_all(&root);
        let _ = std::fs::remove_dir_all(&work);
    }

    #[test]
    fn urls_that_open_nothing_say_why() {
        let work = std::env::temp_dir();
        for url in ["s3://", "file://relative/dir", "gs://bucket"] {
            let e = SharedStore::open(url, &work, Duration::from_secs(1), None)
                .expect_err(url)
                .to_string();
            assert!(e.contains(url), "{e}");
        }
    }
}
