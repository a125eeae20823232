//! Persistence: rigs and clips survive restarts, deletes stick, corrupt files are reported and
//! skipped, and a process killed with SIGKILL during an upload never leaves a partial rig.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use bytes::Bytes;
use crowdmorph_client::{Client, Encoding, Method};
use crowdmorph_proto::{CrowdFrameRequest, CrowdFrameResponse, Format, Head, OutputOptions};
use tokio::io::AsyncWriteExt;

use super::{TestServer, stored_config, temp_dir, upload_bytes};

fn frames(heads: &[(&str, &str, i64)]) -> CrowdFrameRequest {
    CrowdFrameRequest {
        heads: heads
            .iter()
            .enumerate()
            .map(|(i, &(rig, clip, frame))| Head {
                head: i as u64,
                rig: rig.into(),
                clip: clip.into(),
                frame,
                lod: 0,
                ..Default::default()
            })
            .collect(),
        output: OutputOptions {
            normals: true,
            format: Format::F32,
        },
        wrap: true,
    }
}

async fn frame(c: &Client, req: &CrowdFrameRequest) -> CrowdFrameResponse {
    c.crowd_frame(req, Encoding::Bincode).await.unwrap().0
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rigs_and_clips_survive_restarts_and_corrupt_files_are_skipped() {
    let dir = temp_dir("restart");
    let tri = Bytes::from(crate::util::builder::triangle_rig().to_glb());
    let clip = r#"{"fps":24,"targets":["a","b"],"frames":[[0,0],[0.5,1],[1,0.25]]}"#;
    let csv = "jawOpen,eyeBlink_L\n0.2,0.1\n0.7,0.9\n";
    let req = frames(&[
        ("tri", "wave", 1),
        ("tri", "wave", 2),
        ("default-head", "nod", 1),
    ]);

    let s1 = TestServer::start(stored_config(&dir)).await;
    s1.client.upload_rig("tri", tri.clone()).await.unwrap();
    s1.client
        .upload_clip("tri", "name=wave", "application/json", Bytes::from(clip))
        .await
        .unwrap();
    s1.client
        .upload_clip("default-head", "name=nod", "text/csv", Bytes::from(csv))
        .await
        .unwrap();
    s1.client.upload_rig("gone", tri.clone()).await.unwrap();
    s1.client.delete_rig("gone").await.unwrap();
    let before = frame(&s1.client, &req).await;
    s1.stop().await;

    // A garbage file and a truncated copy of a real one sit beside the good records.
    let rigs_dir = dir.join("rigs");
    let good = std::fs::read(rigs_dir.join("tri.cmrig")).unwrap();
    std::fs::write(rigs_dir.join("junk.cmrig"), b"not a record at all").unwrap();
    std::fs::write(rigs_dir.join("torn.cmrig"), &good[..good.len() * 2 / 3]).unwrap();

    let s2 = TestServer::start(stored_config(&dir)).await;
    let list = s2.client.rigs().await.unwrap();
    let ids: Vec<&str> = list.rigs.iter().map(|r| r.id.as_str()).collect();
    assert_eq!(ids, vec!["default-head", "tri"]);
    let tri_info = s2.client.rig("tri").await.unwrap();
    assert_eq!(tri_info.clips.len(), 1);
    assert_eq!(tri_info.clips[0].fps, 24.0);
    let head = s2.client.clips("default-head").await.unwrap();
    assert_eq!(head.clips.last().unwrap().name, "nod");
    let after = frame(&s2.client, &req).await;
    assert_eq!(
        before.buffers, after.buffers,
        "the same frames after a restart"
    );
    let ready = s2
        .client
        .send(Method::GET, "/readyz", None, None, Bytes::new())
        .await
        .unwrap();
    let ready: crowdmorph_proto::Readiness = serde_json::from_slice(&ready.body).unwrap();
    assert_eq!(ready.status, "ready");
    assert_eq!(ready.skipped_files.len(), 2, "{:?}", ready.skipped_files);
    assert!(ready.skipped_files.iter().any(|s| s.contains("junk.cmrig")));
    assert!(ready.skipped_files.iter().any(|s| s.contains("torn.cmrig")));
    // Deleting the clip and the rig sticks too.
    let r = s2
        .client
        .send(
            Method::DELETE,
            "/v1/rigs/default-head/clips/nod",
            None,
            None,
            Bytes::new(),
        )
        .await
        .unwrap();
    assert_eq!(r.status, 204);
    s2.client.delete_rig("tri").await.unwrap();
    s2.stop().await;

    let s3 = TestServer::start(stored_config(&dir)).await;
    let list = s3.client.rigs().await.unwrap();
    assert_eq!(list.rigs.len(), 1);
    assert!(
        s3.client
            .clips("default-head")
            .await
            .unwrap()
            .clips
            .iter()
            .all(|c| c.name != "nod")
    );
    s3.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// The real binary, serving on a port it chose.
pub(super) struct Proc {
    pub(super) child: Child,
    pub(super) base: String,
    /// Every line it has logged (stderr), as it arrives.
    pub(super) log: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
}

/// A failing assertion must not leave its server running (a test's 600 s render would spoil the
/// CPU measurements of the tests after it): the process is killed and reaped when dropped.
impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn spawn(dir: &Path) -> Proc {
    spawn_with(dir, &[])
}

/// [`spawn`] with extra environment variables (every serve flag has one).
pub(super) fn spawn_with(dir: &Path, env: &[(&str, &str)]) -> Proc {
    let mut child = Command::new(env!("CARGO_BIN_EXE_crowdmorph"))
        .args(["serve", "--addr", "127.0.0.1:0", "--data-dir"])
        .arg(dir)
        .envs(env.iter().copied())
        .env("RUST_LOG", "info")
        .env("NO_COLOR", "1")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn crowdmorph serve");
    let stderr = child.stderr.take().expect("stderr");
    let mut lines = BufReader::new(stderr).lines();
    let mut base = None;
    let log = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    for line in lines.by_ref() {
        let line = line.expect("log line");
        log.lock().unwrap().push(line.clone());
        if line.contains("listening")
            && let Some(at) = line.rfind("127.0.0.1:")
        {
            let port: String = line[at + 10..]
                .chars()
                .take_while(char::is_ascii_digit)
                .collect();
            base = Some(format!("http://127.0.0.1:{port}"));
            break;
        }
    }
    // Keep draining the log so the child never blocks on a full pipe.
    let kept = log.clone();
    std::thread::spawn(move || {
        for line in lines.map_while(Result::ok) {
            kept.lock().unwrap().push(line);
        }
    });
    Proc {
        child,
        base: base.expect("the server logged its address"),
        log,
    }
}

pub(super) async fn ready(c: &Client) {
    for _ in 0..500 {
        if let Ok(r) = c
            .send(Method::GET, "/readyz", None, None, Bytes::new())
            .await
            && r.status == 200
        {
            return;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    panic!("server never became ready");
}

fn no_temp_files(dir: &Path) {
    for e in std::fs::read_dir(dir.join("rigs")).unwrap() {
        let name = e.unwrap().file_name().to_string_lossy().into_owned();
        assert!(!name.contains(".tmp-"), "stray temporary file {name}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigkill_during_uploads_never_leaves_a_partial_rig() {
    let dir = temp_dir("sigkill");
    let tri = Bytes::from(crate::util::builder::triangle_rig().to_glb());

    // Killed while the body is still arriving.
    let mut p = spawn(&dir);
    let c = Client::new(p.base.clone());
    ready(&c).await;
    c.upload_rig("keep", tri.clone()).await.unwrap();
    let mut sock = tokio::net::TcpStream::connect(p.base.trim_start_matches("http://"))
        .await
        .unwrap();
    sock.write_all(
        b"POST /v1/rigs?name=partial HTTP/1.1\r\nHost: x\r\nContent-Type: model/gltf-binary\r\n\
          Content-Length: 2000000\r\n\r\n",
    )
    .await
    .unwrap();
    sock.write_all(&tri).await.unwrap();
    sock.write_all(&vec![0u8; 1_000_000]).await.unwrap();
    p.child.kill().unwrap(); // SIGKILL
    p.child.wait().unwrap();

    let (mut p, list) = restart_with_whole_rigs_only(&dir).await;
    assert!(list.iter().any(|id| id == "keep"));
    assert!(list.iter().all(|id| id != "partial"));

    // SIGTERM: a graceful exit with status 0.
    let status = Command::new("kill")
        .args(["-TERM", &p.child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    let exit = p.child.wait().unwrap();
    assert!(exit.success(), "exit status {exit:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn sigkill_while_a_big_upload_is_imported_never_leaves_a_partial_rig() {
    let dir = temp_dir("sigkill-big");
    // Killed at several moments after a whole big upload (ICT FaceKit, 18 MB) was sent: while
    // importing, preparing or writing it. Afterwards each rig is either complete or absent.
    let big = upload_bytes(&crate::util::rig_files()[0]);
    for (round, delay_ms) in [0u64, 40, 150, 400].into_iter().enumerate() {
        let mut p = spawn(&dir);
        let c = Client::new(p.base.clone());
        ready(&c).await;
        let name = format!("big{round}");
        let upload = {
            let c = c.clone();
            let big = big.clone();
            tokio::spawn(async move { c.upload_rig(&name, big).await })
        };
        tokio::time::sleep(Duration::from_millis(delay_ms)).await;
        p.child.kill().unwrap();
        p.child.wait().unwrap();
        let _ = upload.await;
    }
    let (mut p, _) = restart_with_whole_rigs_only(&dir).await;
    p.child.kill().unwrap();
    p.child.wait().unwrap();
    let _ = std::fs::remove_dir_all(&dir);
}

/// Starts the server on `dir` after it was killed: no temporary file is left, nothing stored
/// is corrupt, and every rig that came back is whole. Returns the process and the rig ids.
async fn restart_with_whole_rigs_only(dir: &Path) -> (Proc, Vec<String>) {
    let p = spawn(dir);
    let c = Client::new(p.base.clone());
    ready(&c).await;
    no_temp_files(dir);
    let r = c
        .send(Method::GET, "/readyz", None, None, Bytes::new())
        .await
        .unwrap();
    let readiness: crowdmorph_proto::Readiness = serde_json::from_slice(&r.body).unwrap();
    assert!(
        readiness.skipped_files.is_empty(),
        "{:?}",
        readiness.skipped_files
    );
    let list = c.rigs().await.unwrap();
    for r in &list.rigs {
        // Every rig that came back is whole: it frames.
        let info = c.rig(&r.id).await.unwrap();
        assert!(info.vertices > 0);
        let mesh = c.mesh(&r.id, Encoding::Bincode).await.unwrap();
        assert_eq!(mesh.positions.0.len(), info.vertices as usize * 12);
    }
    (p, list.rigs.into_iter().map(|r| r.id).collect())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_lets_requests_in_flight_complete() {
    let dir = temp_dir("sigterm");
    // A long batch delay keeps the request queued when the signal arrives.
    let mut p = spawn_with(
        &dir,
        &[
            ("CROWDMORPH_BATCH_DELAY_US", "800000"),
            ("CROWDMORPH_BATCH_HOLD_WHEN_IDLE", "true"),
            ("CROWDMORPH_BATCH_COST", "18446744073709551615"),
        ],
    );
    let c = Client::new(p.base.clone());
    ready(&c).await;
    let req = frames(&[("default-head", "talk", 3), ("default-head", "smile", 9)]);
    let inflight = {
        let c = c.clone();
        let req = req.clone();
        tokio::spawn(async move { c.crowd_frame(&req, Encoding::Bincode).await })
    };
    let mut queued = false;
    for _ in 0..250 {
        let m = c.metrics().await.unwrap();
        if crowdmorph_client::metric(&m, "crowdmorph_queue_depth") == Some(1.0) {
            queued = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(4)).await;
    }
    assert!(queued, "the request reached the batcher");
    let status = Command::new("kill")
        .args(["-TERM", &p.child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    let (resp, _) = inflight
        .await
        .unwrap()
        .expect("the request in flight is answered");
    assert_eq!(resp.heads.len(), 2);
    let frames: Vec<u32> = resp.buffers.iter().map(|b| b.frame).collect();
    assert_eq!(frames, vec![3, 9]);
    let exit = p.child.wait().unwrap();
    assert!(exit.success(), "exit status {exit:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_added_clip_writes_its_own_file_not_the_whole_rig() {
    let dir = temp_dir("clipfiles");
    let rigs_dir = dir.join("rigs");
    let csv = |w: f32| Bytes::from(format!("a,b\n0,{w}\n1,0\n"));
    let s1 = TestServer::start(stored_config(&dir)).await;
    let tri = Bytes::from(crate::util::builder::triangle_rig().to_glb());
    s1.client.upload_rig("tri", tri).await.unwrap();
    let record = std::fs::read(rigs_dir.join("tri.cmrig")).unwrap();
    for (name, w) in [("one", 0.1), ("two", 0.2), ("three", 0.3)] {
        s1.client
            .upload_clip("tri", &format!("name={name}"), "text/csv", csv(w))
            .await
            .unwrap();
    }
    // Three clip files; the rig's record is byte for byte what the upload wrote.
    assert_eq!(std::fs::read(rigs_dir.join("tri.cmrig")).unwrap(), record);
    let mut files: Vec<String> = std::fs::read_dir(&rigs_dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("tri"))
        .collect();
    files.sort();
    assert_eq!(
        files,
        [
            "tri.cmrig",
            "tri@0000000001.cmclips",
            "tri@0000000002.cmclips",
            "tri@0000000003.cmclips"
        ]
    );
    // Deleting a clip removes its file and leaves the others alone.
    let r = s1
        .client
        .send(
            Method::DELETE,
            "/v1/rigs/tri/clips/two",
            None,
            None,
            Bytes::new(),
        )
        .await
        .unwrap();
    assert_eq!(r.status, 204);
    assert!(!rigs_dir.join("tri@0000000002.cmclips").exists());
    assert_eq!(std::fs::read(rigs_dir.join("tri.cmrig")).unwrap(), record);
    let clip_names = |list: crowdmorph_proto::ClipList| -> Vec<String> {
        list.clips.into_iter().map(|c| c.name).collect()
    };
    let before = clip_names(s1.client.clips("tri").await.unwrap());
    assert_eq!(before, ["one", "three"]);
    s1.stop().await;

    // After a restart the rig has the same clips in the same order, and the next clip file
    // does not reuse a number still on disk.
    let s2 = TestServer::start(stored_config(&dir)).await;
    assert_eq!(clip_names(s2.client.clips("tri").await.unwrap()), before);
    s2.client
        .upload_clip("tri", "name=four", "text/csv", csv(0.4))
        .await
        .unwrap();
    assert!(rigs_dir.join("tri@0000000004.cmclips").exists());
    assert_eq!(
        clip_names(s2.client.clips("tri").await.unwrap()),
        ["one", "three", "four"]
    );
    // Deleting the rig removes its record and every clip file.
    s2.client.delete_rig("tri").await.unwrap();
    let left: Vec<String> = std::fs::read_dir(&rigs_dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("tri"))
        .collect();
    assert!(left.is_empty(), "{left:?}");
    s2.stop().await;
}

/// A CSV clip of `frames` smooth frames over a few of the embedded head's channels.
fn smooth_csv(frames: usize, phase: f32) -> String {
    let mut csv = String::from("jawOpen,eyeBlink_L,mouthSmile_L,browInnerUp\n");
    for f in 0..frames {
        let t = f as f32 / 24.0 + phase;
        csv += &format!(
            "{},{},{},{}\n",
            0.5 + 0.5 * (t * 2.1).sin(),
            (t * 3.7).cos().abs(),
            0.3 + 0.3 * (t * 1.3).sin(),
            0.25 * (1.0 + (t * 0.7).cos())
        );
    }
    csv
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn compressed_clips_serve_the_same_frames_across_restarts_and_a_damaged_one_is_skipped() {
    let dir = temp_dir("compressed");
    let budget = 3e-4f32;
    let config = || crowdmorph::server::ServerConfig {
        compress_clips: Some(budget),
        ..stored_config(&dir)
    };
    let req = frames(&[
        ("default-head", "talk2", 5),
        ("default-head", "talk2", 70),
        ("default-head", "hum", 33),
    ]);
    // The same clips, stored exactly, by a server without a data dir.
    let exact = TestServer::start(crowdmorph::server::ServerConfig::default()).await;
    let s1 = TestServer::start(config()).await;
    for s in [&exact, &s1] {
        for (name, phase) in [("talk2", 0.0), ("hum", 1.7)] {
            s.client
                .upload_clip(
                    "default-head",
                    &format!("name={name}"),
                    "text/csv",
                    Bytes::from(smooth_csv(96, phase)),
                )
                .await
                .unwrap();
        }
    }
    let want = frame(&exact.client, &req).await;
    let before = frame(&s1.client, &req).await;
    exact.stop().await;
    s1.stop().await;
    // Within the budget of the exact clips, in vertex space.
    let diagonal = crowdmorph::embedded::default_rig().bbox().diagonal();
    for (a, b) in want.buffers.iter().zip(&before.buffers) {
        let (a, b) = (
            crate::server::positions_f32(Format::F32, a),
            crate::server::positions_f32(Format::F32, b),
        );
        for (p, q) in a.chunks(3).zip(b.chunks(3)) {
            let d = ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt();
            assert!(d <= budget * diagonal * 1.01, "{d} > {budget} × {diagonal}");
        }
    }
    assert_ne!(want.buffers, before.buffers, "the clips were compressed");

    let s2 = TestServer::start(config()).await;
    let after = frame(&s2.client, &req).await;
    assert_eq!(
        before.buffers, after.buffers,
        "the same frames after a restart"
    );
    s2.stop().await;

    // Damage hum's first zstd segment (fixing the file's checksum, as a faulty build would
    // have written it): hum is skipped and named at start, talk2 still plays.
    let rigs_dir = dir.join("rigs");
    let mut files: Vec<_> = std::fs::read_dir(&rigs_dir)
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "cmclips"))
        .collect();
    files.sort();
    assert_eq!(files.len(), 2, "{files:?}");
    let mut b = std::fs::read(&files[1]).unwrap();
    let at = b
        .windows(4)
        .position(|w| w == [0x28, 0xb5, 0x2f, 0xfd])
        .expect("compressed");
    b[at + 12] ^= 0x41;
    let crc = crc32fast::hash(&b[24..]);
    b[20..24].copy_from_slice(&crc.to_le_bytes());
    std::fs::write(&files[1], &b).unwrap();
    let s3 = TestServer::start(config()).await;
    let ready = s3
        .client
        .send(Method::GET, "/readyz", None, None, Bytes::new())
        .await
        .unwrap();
    let ready: crowdmorph_proto::Readiness = serde_json::from_slice(&ready.body).unwrap();
    assert_eq!(ready.skipped_files.len(), 1, "{:?}", ready.skipped_files);
    assert!(
        ready.skipped_files[0].contains("\"hum\""),
        "{:?}",
        ready.skipped_files
    );
    let names: Vec<String> = s3
        .client
        .clips("default-head")
        .await
        .unwrap()
        .clips
        .into_iter()
        .map(|c| c.name)
        .collect();
    assert!(names.contains(&"talk2".to_string()) && !names.contains(&"hum".to_string()));
    let talk = frame(&s3.client, &frames(&[("default-head", "talk2", 70)])).await;
    assert_eq!(talk.buffers[0], after.buffers[1]);
    s3.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}
