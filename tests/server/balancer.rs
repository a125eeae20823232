//! Several replicas behind the shipped balancer configurations (`deploy/`): Debian's nginx in
//! front of three `crowdmorph serve` processes, each with its own data directory, routes every
//! request about a rig (its upload, its crowd frames with the clients' `?rig=` hint) and every
//! request about a session (its `PUT`, its WebSocket stream, its delete) to one replica by
//! consistent hashing; HAProxy's file is checked by `haproxy -c`.
//!
//! The replicas do not share a store here (each has its own data directory), so a rig lives
//! only where its upload landed: a routing mistake is a 404. Replicas over one shared store
//! behind nginx are `replicas.rs`.

use std::io::Write;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use bytes::Bytes;
use crowdmorph_client::{Client, Encoding, Method};
use crowdmorph_proto::{Format, LiveWeights, OutputOptions, SessionRequest};
use futures_util::{SinkExt, StreamExt};
use serde_json::json;
use tokio_tungstenite::tungstenite::Message;

/// Debian's nginx as `build.rs` found it. `option_env!`, not `env!`: where build.rs found none
/// the variable is unset, the tests that use it are ignored, and the suite must still compile.
const NGINX: &str = match option_env!("CROWDMORPH_NGINX_PATH") {
    Some(path) => path,
    None => "nginx",
};

use super::persistence::{Proc, ready, spawn_with};
use super::temp_dir;

fn deploy(file: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("deploy")
        .join(file)
}

/// A port nothing listens on now.
pub(super) fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free port")
}

/// nginx in the foreground with the shipped `crowdmorph.conf`, its listen port and its
/// upstream list swapped for this test's; killed when dropped.
pub(super) struct Nginx {
    child: Child,
    pub(super) port: u16,
}

impl Drop for Nginx {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub(super) fn nginx(replicas: &[String]) -> Nginx {
    let dir = temp_dir("nginx");
    let port = free_port();
    let shipped = std::fs::read_to_string(deploy("nginx/crowdmorph.conf")).expect("read");
    // The lines a deployment edits, as the shipped file has them.
    assert!(
        shipped.contains("    listen 8080;\n"),
        "the shipped listen line"
    );
    assert!(shipped.contains("include crowdmorph-upstream.conf;"));
    let conf = shipped.replace(
        "    listen 8080;\n",
        &format!("    listen 127.0.0.1:{port};\n"),
    );
    std::fs::write(dir.join("crowdmorph.conf"), conf).expect("write");
    let upstream: String = replicas
        .iter()
        .map(|b| {
            format!(
                "server {} max_fails=3 fail_timeout=10s;\n",
                b.trim_start_matches("http://")
            )
        })
        .collect();
    std::fs::write(dir.join("crowdmorph-upstream.conf"), upstream).expect("write");
    let mut main = std::fs::File::create(dir.join("nginx.conf")).expect("create");
    write!(
        main,
        "daemon off;\npid nginx.pid;\nerror_log error.log info;\nevents {{}}\nhttp {{\n\
         access_log access.log;\nclient_body_temp_path body;\nproxy_temp_path proxy;\n\
         fastcgi_temp_path fastcgi;\nuwsgi_temp_path uwsgi;\nscgi_temp_path scgi;\n\
         include crowdmorph.conf;\n}}\n"
    )
    .expect("write");
    let prefix = format!("{}/", dir.display());
    let conf = dir.join("nginx.conf");
    let check = Command::new(NGINX)
        .args(["-t", "-p", &prefix, "-c"])
        .arg(&conf)
        .output()
        .expect("run nginx -t");
    assert!(
        check.status.success(),
        "nginx -t: {}",
        String::from_utf8_lossy(&check.stderr)
    );
    let child = Command::new(NGINX)
        .args(["-p", &prefix, "-c"])
        .arg(&conf)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start nginx");
    let started = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(
            started.elapsed() < Duration::from_secs(10),
            "nginx did not listen"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    Nginx { child, port }
}

/// Which of `replicas` answers 200 for `path` (asked directly, not through the balancer).
async fn holders(replicas: &[Client], path: &str) -> Vec<usize> {
    let mut found = Vec::new();
    for (i, c) in replicas.iter().enumerate() {
        let reply = c
            .send(Method::GET, path, None, None, Bytes::new())
            .await
            .expect("GET");
        if reply.status == 200 {
            found.push(i);
        }
    }
    found
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_nginx),
    ignore = "needs nginx: apt-get install nginx-light (then touch build.rs)"
)]
async fn nginx_keeps_each_rig_and_session_on_one_replica() {
    let procs: Vec<Proc> = (0..3)
        .map(|i| {
            let dir = temp_dir(&format!("replica{i}"));
            spawn_with(
                &dir,
                &[
                    ("CROWDMORPH_BACKEND", "cpu"),
                    ("CROWDMORPH_NO_AUTO_LOD", "true"),
                ],
            )
        })
        .collect();
    let direct: Vec<Client> = procs.iter().map(|p| Client::new(p.base.clone())).collect();
    for c in &direct {
        ready(c).await;
    }
    let bases: Vec<String> = procs.iter().map(|p| p.base.clone()).collect();
    let lb = nginx(&bases);
    let through = Client::new(format!("http://127.0.0.1:{}", lb.port));

    // Twelve rigs uploaded through the balancer: each lands on exactly one replica, and the
    // hash spreads them (all twelve on one of three replicas would be a 1-in-177,147 chance).
    let tri = Bytes::from(crate::util::builder::triangle_rig().to_glb());
    let mut used = std::collections::BTreeSet::new();
    for r in 0..12 {
        let id = format!("rig{r}");
        through.upload_rig(&id, tri.clone()).await.expect("upload");
        let at = holders(&direct, &format!("/v1/rigs/{id}")).await;
        assert_eq!(at.len(), 1, "{id} is on replicas {at:?}");
        used.insert(at[0]);
        // A crowd frame through the balancer (the client adds ?rig=) reaches that replica;
        // a wrong one would not know the rig.
        let (resp, _) = through
            .live_frame(
                &id,
                vec![LiveWeights::Named(Vec::new())],
                0,
                OutputOptions {
                    normals: false,
                    format: Format::Q16,
                },
                Encoding::Bincode,
            )
            .await
            .expect("a frame of the rig through the balancer");
        assert_eq!(resp.buffers.len(), 1);
        assert_eq!(resp.buffers[0].rig, id);
    }
    assert!(used.len() >= 2, "the rigs spread over replicas {used:?}");

    // A session with an id of the client's: created, streamed and deleted through the
    // balancer, on one replica (the built-in head, which every replica has).
    let req: SessionRequest = serde_json::from_value(json!({
        "fps": 20,
        "heads": [{"head": 1, "rig": "default-head", "clip": "talk"}]
    }))
    .expect("request");
    let made = through
        .create_session(&req, Some("lobby-7"), Encoding::Json)
        .await
        .expect("PUT through the balancer");
    assert_eq!(made.id, "lobby-7");
    assert_eq!(
        holders(&direct, "/v1/sessions/lobby-7").await.len(),
        1,
        "one replica holds the session"
    );
    let url = format!("ws://127.0.0.1:{}/v1/sessions/lobby-7/stream", lb.port);
    let (mut ws, _) = tokio_tungstenite::connect_async(url)
        .await
        .expect("the WebSocket upgrade passes through nginx");
    ws.send(Message::text(json!({"format": "q16"}).to_string()))
        .await
        .expect("hello");
    let mut binary = 0;
    while binary < 3 {
        let msg = tokio::time::timeout(Duration::from_secs(20), ws.next())
            .await
            .expect("a tick within 20 s")
            .expect("the stream is open")
            .expect("a message");
        if msg.is_binary() {
            binary += 1;
        }
    }
    let reply = through
        .send(
            Method::DELETE,
            "/v1/sessions/lobby-7",
            None,
            None,
            Bytes::new(),
        )
        .await
        .expect("DELETE");
    assert_eq!(reply.status, 204);
    assert!(holders(&direct, "/v1/sessions/lobby-7").await.is_empty());
    drop(lb);
    drop(procs);
}

#[test]
#[cfg_attr(
    not(crowdmorph_haproxy),
    ignore = "needs HAProxy: apt-get install haproxy (then touch build.rs)"
)]
fn the_haproxy_configuration_is_valid() {
    let out = Command::new(option_env!("CROWDMORPH_HAPROXY_PATH").unwrap_or("haproxy"))
        .arg("-c")
        .arg("-f")
        .arg(deploy("haproxy/haproxy.cfg"))
        .output()
        .expect("run haproxy -c");
    assert!(
        out.status.success(),
        "haproxy -c: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}
