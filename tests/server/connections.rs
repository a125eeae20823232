//! Connections: idle and half-open sockets are bounded and closed, a request in progress is
//! never evicted, and a storm of shed requests logs a few summary lines instead of one ERROR
//! line each.
//!
//! These need real sockets and real time: the timeouts are short (1–2 s) and the assertions
//! about time are only the generous bounds that prove a socket was closed, or still open.

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::process::{Command, Stdio};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use crowdmorph::server::ServerConfig;
use crowdmorph_client::{Client, Encoding, Method, metric};
use crowdmorph_proto::{CrowdFrameRequest, Format, Head, OutputOptions};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use super::{TestServer, temp_dir};

/// Polls `f` every 20 ms for up to 10 s.
async fn eventually(mut f: impl FnMut() -> bool) -> bool {
    for _ in 0..500 {
        if f() {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    false
}

/// A response read off a raw socket.
struct Raw {
    status: u16,
    head: String,
    body: Vec<u8>,
}

/// Reads one response (headers, then `content-length` bytes of body).
async fn read_response(s: &mut TcpStream) -> Raw {
    let mut buf = Vec::new();
    let end = loop {
        if let Some(at) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            break at + 4;
        }
        let mut chunk = [0u8; 4096];
        let n = s.read(&mut chunk).await.expect("read response");
        assert!(n > 0, "connection closed before a response");
        buf.extend_from_slice(&chunk[..n]);
    };
    let head = String::from_utf8_lossy(&buf[..end]).into_owned();
    let status = head[9..12].parse().expect("status");
    let len: usize = head
        .lines()
        .find_map(|l| {
            let (k, v) = l.split_once(':')?;
            k.eq_ignore_ascii_case("content-length")
                .then(|| v.trim().parse().ok())?
        })
        .unwrap_or(0);
    let mut body = buf[end..].to_vec();
    while body.len() < len {
        let mut chunk = vec![0u8; len - body.len()];
        let n = s.read(&mut chunk).await.expect("read body");
        assert!(n > 0, "connection closed mid-body");
        body.extend_from_slice(&chunk[..n]);
    }
    Raw { status, head, body }
}

/// `GET path` on a fresh connection that asks to be closed afterwards.
async fn get_once(addr: SocketAddr, path: &str) -> Raw {
    let mut s = TcpStream::connect(addr).await.unwrap();
    s.write_all(format!("GET {path} HTTP/1.1\r\nhost: t\r\nconnection: close\r\n\r\n").as_bytes())
        .await
        .unwrap();
    read_response(&mut s).await
}

/// Waits up to `within` for the server to close `s` (EOF, or a reset); how long it took.
async fn closed_within(s: &mut TcpStream, within: Duration) -> Option<Duration> {
    let start = Instant::now();
    let mut chunk = [0u8; 1024];
    loop {
        match tokio::time::timeout(within.saturating_sub(start.elapsed()), s.read(&mut chunk)).await
        {
            Err(_) => return None,
            Ok(Ok(0) | Err(_)) => return Some(start.elapsed()),
            // Leftovers of a response are not a close.
            Ok(Ok(_)) => {}
        }
    }
}

fn crowd_json(frame: i64) -> String {
    let req = CrowdFrameRequest {
        heads: vec![Head {
            head: 0,
            rig: "default-head".into(),
            clip: "talk".into(),
            frame,
            lod: 0,
            ..Default::default()
        }],
        output: OutputOptions {
            normals: false,
            format: Format::F32,
        },
        wrap: true,
    };
    serde_json::to_string(&req).unwrap()
}

fn crowd_post(frame: i64) -> Vec<u8> {
    let body = crowd_json(frame);
    format!(
        "POST /v1/crowd/frame HTTP/1.1\r\nhost: t\r\ncontent-type: application/json\r\n\
         accept: application/json\r\ncontent-length: {}\r\n\r\n{body}",
        body.len()
    )
    .into_bytes()
}

/// The reproducer of the descriptor exhaustion: far more idle and half-open connections than
/// the cap. The server holds at most the cap, answers `/readyz` on a fresh connection at once,
/// and closes every one of them (evicting the longest-idle, then by the timeouts).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_and_half_open_connections_are_capped_and_closed() {
    const CAP: usize = 64;
    const FLOOD: usize = 300;
    let server = TestServer::start(ServerConfig {
        max_connections: Some(CAP),
        header_timeout: Duration::from_secs(1),
        idle_timeout: Duration::from_secs(2),
        ..ServerConfig::default()
    })
    .await;
    let m = server.state.metrics.clone();
    let start = Instant::now();
    let mut socks = Vec::new();
    let mut most_open = 0;
    for i in 0..FLOOD {
        let mut s = TcpStream::connect(server.addr).await.unwrap();
        match i % 4 {
            // Sends nothing.
            0 => {}
            // Stops mid request line.
            1 => s.write_all(b"GET /heal").await.unwrap(),
            // Stops mid-headers.
            2 => s
                .write_all(b"GET /healthz HTTP/1.1\r\nhost: t\r\n")
                .await
                .unwrap(),
            // One whole request, kept alive, then idle.
            _ => {
                s.write_all(b"GET /healthz HTTP/1.1\r\nhost: t\r\n\r\n")
                    .await
                    .unwrap();
                assert_eq!(read_response(&mut s).await.status, 200);
            }
        }
        most_open = most_open.max(m.connections_open.get());
        socks.push(s);
    }
    let flood = start.elapsed();
    // An evicted connection counts until its task has closed the socket, a moment after the
    // connection that replaced it was admitted.
    assert!(most_open <= CAP as u64 + 4, "{most_open} open, cap {CAP}");

    // While they are held: a fresh connection is admitted (evicting the longest-idle one).
    let asked = Instant::now();
    let ready = tokio::time::timeout(Duration::from_secs(5), get_once(server.addr, "/readyz"))
        .await
        .expect("/readyz answered under the idle flood");
    let readyz = asked.elapsed();
    assert_eq!(ready.status, 200, "{}", ready.head);

    // Every flood connection is closed by the server: evicted already, or by its timeout.
    let waits: Vec<_> = socks
        .into_iter()
        .map(|mut s| {
            tokio::spawn(async move { closed_within(&mut s, Duration::from_secs(8)).await })
        })
        .collect();
    let mut last_close = Duration::ZERO;
    for (i, w) in waits.into_iter().enumerate() {
        let took = w.await.unwrap();
        assert!(took.is_some(), "flood connection {i} still open");
        last_close = last_close.max(start.elapsed());
    }
    let closed = |r: &str| m.connections_closed_with(r);
    let counted = || closed("evicted") + closed("header_timeout") + closed("idle_timeout");
    // The client sees the socket close a moment before the server's task counts it.
    eventually(|| counted() >= FLOOD as u64).await;
    let (evicted, header, idle) = (
        closed("evicted"),
        closed("header_timeout"),
        closed("idle_timeout"),
    );
    assert!(
        evicted > 0 && header > 0 && idle > 0,
        "{evicted} {header} {idle}"
    );
    assert!(
        evicted + header + idle >= FLOOD as u64,
        "{evicted} evicted + {header} header timeouts + {idle} idle timeouts < {FLOOD}"
    );
    assert!(eventually(|| m.connections_open.get() == 0).await);
    let page = get_once(server.addr, "/metrics").await;
    let page = String::from_utf8(page.body).unwrap();
    assert_eq!(
        metric(
            &page,
            "crowdmorph_connections_closed_total{reason=\"evicted\"}"
        ),
        Some(evicted as f64)
    );
    assert_eq!(
        metric(&page, "crowdmorph_connections_limit"),
        Some(CAP as f64)
    );
    eprintln!(
        "idle flood: {FLOOD} connections in {flood:.2?}, at most {most_open} open (cap {CAP}); \
         /readyz answered in {readyz:.2?}; all closed {last_close:.2?} after the flood began; \
         {evicted} evicted, {header} header timeouts, {idle} idle timeouts"
    );
    server.stop().await;
}

/// Header timeout: bytes trickling in do not extend it. Idle timeout: a kept-alive connection
/// waits longer than the header timeout, then is closed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_header_timeout_is_not_extended_by_trickling_and_differs_from_idle() {
    let server = TestServer::start(ServerConfig {
        header_timeout: Duration::from_millis(500),
        idle_timeout: Duration::from_secs(2),
        ..ServerConfig::default()
    })
    .await;
    let addr = server.addr;
    // One byte of headers every 100 ms, for up to 5 s.
    let trickle = tokio::spawn(async move {
        let mut s = TcpStream::connect(addr).await.unwrap();
        s.write_all(b"GET /healthz HTTP/1.1\r\n").await.unwrap();
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(5) {
            if s.write_all(b"x").await.is_err() {
                return Some(start.elapsed());
            }
            if let Some(t) = closed_within(&mut s, Duration::from_millis(100)).await {
                return Some(start.elapsed() - Duration::from_millis(100) + t);
            }
        }
        None
    });
    let mut k = TcpStream::connect(addr).await.unwrap();
    k.write_all(b"GET /healthz HTTP/1.1\r\nhost: t\r\n\r\n")
        .await
        .unwrap();
    assert_eq!(read_response(&mut k).await.status, 200);
    // Twice the header timeout later, the kept-alive connection is still open...
    assert_eq!(closed_within(&mut k, Duration::from_secs(1)).await, None);
    // ...and it is closed by the idle timeout.
    let idle = closed_within(&mut k, Duration::from_secs(4)).await;
    assert!(idle.is_some(), "idle connection never closed");
    let trickled = trickle.await.unwrap();
    assert!(trickled.is_some(), "trickling connection never closed");
    let m = &server.state.metrics;
    assert_eq!(m.connections_closed_with("header_timeout"), 1);
    assert_eq!(m.connections_closed_with("idle_timeout"), 1);
    eprintln!(
        "header timeout 0.5 s: trickling connection closed after {:.2?}; \
         idle timeout 2 s: closed {:.2?} after the 1 s check",
        trickled.unwrap_or_default(),
        idle.unwrap_or_default()
    );
    server.stop().await;
}

/// At the cap, the idle connection is evicted, never the one with a request in progress; with
/// every connection busy, the new one is refused with a 503 and both requests complete.
///
/// A request is held in progress by its unfinished body, which the test sends when it chooses:
/// a hold by time (a long batch delay) raced the test's own steps on a loaded CI machine.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_in_progress_is_never_evicted() {
    let server = TestServer::start(ServerConfig {
        max_connections: Some(2),
        // The bodies may take this long to arrive: far longer than the test.
        request_timeout: Duration::from_secs(120),
        ..ServerConfig::default()
    })
    .await;
    let m = server.state.metrics.clone();
    let state = server.state.clone();
    let open = |n: u64| {
        let m = m.clone();
        move || m.connections_open.get() == n
    };
    // A request whose head and half of whose body have been sent: the server has begun it
    // once it has reserved the memory to read the body.
    let queued = |s: &crowdmorph::server::AppState| s.queue_memory.used();
    let (a_head, a_tail) = split_body(crowd_post(3));
    let mut a = TcpStream::connect(server.addr).await.unwrap();
    a.write_all(&a_head).await.unwrap();
    assert!(eventually(|| queued(&state) > 0).await);
    let one_request = queued(&state);
    let mut b = TcpStream::connect(server.addr).await.unwrap();
    assert!(eventually(open(2)).await);
    // Past the cap: B (idle) makes room, not A.
    let mut c = TcpStream::connect(server.addr).await.unwrap();
    assert!(
        closed_within(&mut b, Duration::from_secs(5))
            .await
            .is_some(),
        "the idle connection was evicted"
    );
    // Counted when the connection's task ends, which may be just after its socket closed.
    assert!(
        eventually(|| m.connections_closed_with("evicted") == 1).await,
        "the eviction is counted once: {}",
        m.connections_closed_with("evicted")
    );
    let (c_head, c_tail) = split_body(crowd_post(4));
    c.write_all(&c_head).await.unwrap();
    assert!(eventually(|| queued(&state) >= 2 * one_request).await);
    // Both busy: D is refused, and told why.
    let mut d = TcpStream::connect(server.addr).await.unwrap();
    d.write_all(b"GET /healthz HTTP/1.1\r\nhost: t\r\n\r\n")
        .await
        .unwrap();
    let refused = read_response(&mut d).await;
    assert_eq!(refused.status, 503, "{}", refused.head);
    assert!(
        refused
            .head
            .to_ascii_lowercase()
            .contains("connection: close"),
        "{}",
        refused.head
    );
    let err: crowdmorph_proto::ErrorBody = serde_json::from_slice(&refused.body).unwrap();
    assert_eq!(err.error.code, "too_many_connections");
    assert!(
        closed_within(&mut d, Duration::from_secs(3))
            .await
            .is_some()
    );
    // The requests in progress complete once their bodies do.
    for (s, tail) in [(&mut a, a_tail), (&mut c, c_tail)] {
        s.write_all(&tail).await.unwrap();
        let r = read_response(s).await;
        assert_eq!(r.status, 200, "{}", r.head);
        let resp: crowdmorph_proto::CrowdFrameResponse = serde_json::from_slice(&r.body).unwrap();
        assert_eq!(resp.buffers.len(), 1);
    }
    assert_eq!(m.connections_closed_with("evicted"), 1);
    assert_eq!(m.connections_closed_with("refused"), 1);
    drop((a, c));
    assert!(eventually(open(0)).await);
    server.stop().await;
}

/// A request cut in two inside its body: the head and half the body, then the rest.
fn split_body(mut request: Vec<u8>) -> (Vec<u8>, Vec<u8>) {
    let body_at = request
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("a request has a head")
        + 4;
    let cut = body_at + (request.len() - body_at) / 2;
    let tail = request.split_off(cut);
    (request, tail)
}

/// Kills the server if the test fails before stopping it.
struct KillOnDrop(std::process::Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        if let Ok(None) = self.0.try_wait() {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
}

/// The reproducer of the log flood: the real binary with one request at a time, under a storm of
/// concurrent crowd requests until thousands are shed. Its log (the default filter, `info`) gets
/// a few WARN summaries whose counts add up to the shed requests, and no ERROR.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_storm_of_shed_requests_logs_a_few_summary_lines() {
    const SHED_AT_LEAST: f64 = 3000.0;
    let dir = temp_dir("storm");
    let child = Command::new(env!("CARGO_BIN_EXE_crowdmorph"))
        .args(["serve", "--addr", "127.0.0.1:0", "--data-dir"])
        .arg(&dir)
        .env_remove("RUST_LOG")
        .env("NO_COLOR", "1")
        .env("CROWDMORPH_MAX_CONCURRENCY", "1")
        // The one admitted crowd request holds the only slot for ≥ 20 ms.
        .env("CROWDMORPH_BATCH_DELAY_US", "20000")
        .env("CROWDMORPH_BATCH_HOLD_WHEN_IDLE", "true")
        .env("CROWDMORPH_BATCH_COST", "18446744073709551615")
        .env("CROWDMORPH_NO_AUTO_LOD", "true")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn crowdmorph serve");
    let mut child = KillOnDrop(child);
    let stderr = child.0.stderr.take().expect("stderr");
    let lines = Arc::new(Mutex::new(Vec::<(Instant, String)>::new()));
    {
        let lines = lines.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines() {
                let Ok(line) = line else { break };
                lines.lock().unwrap().push((Instant::now(), line));
            }
        });
    }
    let mut base = None;
    for _ in 0..1000 {
        base = lines.lock().unwrap().iter().find_map(|(_, l)| {
            let at = l.find("listening addr=")? + "listening addr=".len();
            Some(format!("http://{}", l[at..].split_whitespace().next()?))
        });
        if base.is_some() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let Some(base) = base else {
        let log: Vec<String> = lines
            .lock()
            .unwrap()
            .iter()
            .map(|(_, l)| l.clone())
            .collect();
        panic!("the server never logged its address:\n{}", log.join("\n"));
    };
    let c = Client::new(base);
    let mut ready = false;
    for _ in 0..500 {
        if let Ok(r) = c
            .send(Method::GET, "/readyz", None, None, Bytes::new())
            .await
            && r.status == 200
        {
            ready = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(ready, "server ready");

    let body = Bytes::from(crowd_json(1));
    let start = Instant::now();
    let shed_so_far = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let mut storm = Vec::new();
    for _ in 0..32 {
        let (c, body, shed_so_far) = (c.clone(), body.clone(), shed_so_far.clone());
        storm.push(tokio::spawn(async move {
            let (mut ok, mut shed) = (0u64, 0u64);
            // For 2 s, and on until enough are shed (for at most 20 s).
            while start.elapsed() < Duration::from_secs(2)
                || ((shed_so_far.load(Ordering::Relaxed) as f64) < SHED_AT_LEAST
                    && start.elapsed() < Duration::from_secs(20))
            {
                let r = c
                    .crowd_frame_raw(body.clone(), Encoding::Json)
                    .await
                    .unwrap();
                match r.status {
                    200 => ok += 1,
                    503 => {
                        shed += 1;
                        shed_so_far.fetch_add(1, Ordering::Relaxed);
                    }
                    s => panic!("unexpected status {s}"),
                }
            }
            (ok, shed)
        }));
    }
    let (mut ok, mut shed) = (0, 0);
    for t in storm {
        let (o, s) = t.await.unwrap();
        ok += o;
        shed += s;
    }
    let storm_time = start.elapsed();
    let page = c.metrics().await.unwrap();
    let overloaded = metric(&page, "crowdmorph_rejected_total{reason=\"overloaded\"}").unwrap();
    assert_eq!(overloaded, shed as f64, "every shed request is counted");
    assert!(overloaded >= SHED_AT_LEAST, "{overloaded} shed");

    // The summaries add up to the shed requests once the last one is written (within 2 s).
    let reported = || -> u64 {
        lines
            .lock()
            .unwrap()
            .iter()
            .filter(|(t, _)| *t >= start)
            .filter_map(|(_, l)| {
                let at = l.find("unavailable_503=")? + "unavailable_503=".len();
                l[at..].split_whitespace().next()?.parse::<u64>().ok()
            })
            .sum()
    };
    let mut summed = 0;
    for _ in 0..250 {
        summed = reported();
        if summed >= shed {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(summed, shed, "the WARN summaries count every shed request");
    let log: Vec<String> = lines
        .lock()
        .unwrap()
        .iter()
        .filter(|(t, _)| *t >= start)
        .map(|(_, l)| l.clone())
        .collect();
    assert!(
        log.iter().all(|l| !l.contains("ERROR")),
        "{}",
        log.join("\n")
    );
    // At most one summary per second, plus a few other lines.
    let bound = 2 * storm_time.as_secs() as usize + 6;
    assert!(
        log.len() <= bound,
        "{} lines:\n{}",
        log.len(),
        log.join("\n")
    );
    eprintln!(
        "storm: {shed} shed and {ok} served in {storm_time:.2?} ({:.0} shed/s); {} log lines \
         during and after it, none at ERROR",
        shed as f64 / storm_time.as_secs_f64(),
        log.len()
    );

    let status = Command::new("kill")
        .args(["-TERM", &child.0.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    let exit = child.0.wait().unwrap();
    assert!(exit.success(), "exit status {exit:?}");
    let _ = std::fs::remove_dir_all(&dir);
}
