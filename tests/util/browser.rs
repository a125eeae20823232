//! Headless Chromium driven over the DevTools protocol, for the tests that need a real browser:
//! the viewer's end to end test (`tests/server/viewer.rs`) and the three.js reference render
//! (`tests/server/threejs.rs`). Tests that use it carry
//! `#[cfg_attr(not(crowdmorph_chromium), ignore = "...")]`: `build.rs` found the binary and
//! passes its path as `CROWDMORPH_CHROMIUM_PATH`.
//!
//! WebGL2 runs in software (SwiftShader through ANGLE; see the shared note on WebGL in headless
//! Chromium), so every deadline here is generous: it only decides when to give up.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use futures_util::{SinkExt, StreamExt};
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

use crate::server::temp_dir;

/// Chromium in the background, killed and its profile removed when dropped.
pub struct Browser {
    child: Child,
    profile: PathBuf,
}

impl Browser {
    pub fn launch() -> Browser {
        let binary = option_env!("CROWDMORPH_CHROMIUM_PATH").unwrap_or("chromium");
        let profile = temp_dir("chromium");
        let log = std::fs::File::create(profile.join("stderr.log")).unwrap();
        let mut command = Command::new(binary);
        // Software WebGL keeps Chromium's processes busy the whole time the page streams (and
        // Chromium sets its own priorities, so `nice` does not hold): on Linux it runs on one of
        // this process's CPUs only, inherited by every process it starts, so that tests running
        // beside this one keep the others for their own deadlines.
        #[cfg(target_os = "linux")]
        if let Some(one_cpu) = last_cpu_of_several() {
            use std::os::unix::process::CommandExt;
            // SAFETY: the closure runs in the forked child before exec and makes one
            // async-signal-safe system call about that child, with a set built beforehand.
            unsafe {
                command.pre_exec(move || {
                    libc::sched_setaffinity(0, size_of::<libc::cpu_set_t>(), &one_cpu);
                    Ok(())
                });
            }
        }
        let child = command
            .args([
                "--headless",
                "--no-sandbox",
                // WebGL2 without a GPU: SwiftShader through ANGLE, which recent Chromium
                // refuses without the "unsafe" flag.
                "--use-gl=angle",
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-default-apps",
                "--disable-extensions",
                "--disable-sync",
                "--no-first-run",
                "--no-default-browser-check",
                "--mute-audio",
                "--window-size=960,640",
                "--remote-debugging-port=0",
                "about:blank",
            ])
            .arg(format!("--user-data-dir={}", profile.display()))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {binary}: {e}"));
        Browser { child, profile }
    }

    /// The browser's DevTools WebSocket URL, from the file Chromium writes once it listens.
    pub async fn devtools_url(&mut self) -> String {
        let file = self.profile.join("DevToolsActivePort");
        let deadline = Instant::now() + Duration::from_secs(90);
        loop {
            if let Ok(text) = std::fs::read_to_string(&file) {
                let mut lines = text.lines();
                if let (Some(port), Some(path)) = (lines.next(), lines.next()) {
                    return format!("ws://127.0.0.1:{port}{path}");
                }
            }
            if let Ok(Some(status)) = self.child.try_wait() {
                panic!("chromium exited with {status}: {}", self.stderr());
            }
            assert!(
                Instant::now() < deadline,
                "chromium did not open its DevTools port in 60 s: {}",
                self.stderr()
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// A new blank tab, attached (flat mode), with console, log and page events enabled: they
    /// are only reported after these calls, so they come before anything is loaded.
    pub async fn page(&mut self) -> Cdp {
        self.page_with(&[]).await
    }

    /// [`Browser::page`] with the `extra` domains enabled too (`Network.enable`, ...).
    pub async fn page_with(&mut self, extra: &[&str]) -> Cdp {
        let url = self.devtools_url().await;
        let mut cdp = Cdp::connect(&url).await;
        let target = cdp
            .call("Target.createTarget", json!({"url": "about:blank"}))
            .await;
        let attached = cdp
            .call(
                "Target.attachToTarget",
                json!({"targetId": target["targetId"], "flatten": true}),
            )
            .await;
        cdp.session = Some(attached["sessionId"].as_str().unwrap().to_string());
        for domain in ["Runtime.enable", "Log.enable", "Page.enable"]
            .iter()
            .chain(extra)
        {
            cdp.call(domain, json!({})).await;
        }
        cdp
    }

    pub fn stderr(&self) -> String {
        std::fs::read_to_string(self.profile.join("stderr.log")).unwrap_or_default()
    }
}

/// The highest-numbered CPU this process may run on, as a set, when it may run on more than one.
#[cfg(target_os = "linux")]
fn last_cpu_of_several() -> Option<libc::cpu_set_t> {
    // SAFETY: a zeroed cpu_set_t is the empty set; sched_getaffinity writes at most its size,
    // and CPU_ISSET/CPU_SET index within it.
    unsafe {
        let mut mine: libc::cpu_set_t = std::mem::zeroed();
        if libc::sched_getaffinity(0, size_of::<libc::cpu_set_t>(), &mut mine) != 0 {
            return None;
        }
        let allowed: Vec<usize> = (0..libc::CPU_SETSIZE as usize)
            .filter(|&c| libc::CPU_ISSET(c, &mine))
            .collect();
        let &last = allowed.last()?;
        if allowed.len() < 2 {
            return None;
        }
        let mut one: libc::cpu_set_t = std::mem::zeroed();
        libc::CPU_SET(last, &mut one);
        Some(one)
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.profile);
    }
}

type Socket =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

/// A DevTools protocol client: JSON-RPC over one WebSocket, one page session (flat mode), and
/// every event kept so that console errors can be read at the end.
pub struct Cdp {
    socket: Socket,
    next_id: u64,
    session: Option<String>,
    events: Vec<Value>,
    /// An expression giving the text of an error the page itself shows (empty when none),
    /// checked while [`Cdp::wait_for`] polls; `None` for pages that show none.
    pub shown_error: Option<&'static str>,
}

impl Cdp {
    pub async fn connect(url: &str) -> Cdp {
        let (socket, _) = tokio_tungstenite::connect_async(url)
            .await
            .expect("DevTools WebSocket");
        Cdp {
            socket,
            next_id: 0,
            session: None,
            events: Vec::new(),
            shown_error: None,
        }
    }

    /// Sends a command (to the page session once attached) and waits for its result.
    pub async fn call(&mut self, method: &str, params: Value) -> Value {
        self.next_id += 1;
        let id = self.next_id;
        let mut msg = json!({"id": id, "method": method, "params": params});
        if let Some(s) = &self.session {
            msg["sessionId"] = json!(s);
        }
        self.socket
            .send(Message::text(msg.to_string()))
            .await
            .expect("DevTools send");
        let deadline = Instant::now() + Duration::from_secs(90);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let next = tokio::time::timeout(left, self.socket.next())
                .await
                .unwrap_or_else(|_| panic!("{method}: no answer in 60 s"));
            let text = match next {
                Some(Ok(Message::Text(t))) => t.to_string(),
                Some(Ok(_)) => continue,
                other => panic!("DevTools connection ended during {method}: {other:?}"),
            };
            let v: Value = serde_json::from_str(&text).expect("DevTools JSON");
            if v["id"] == json!(id) {
                if let Some(err) = v.get("error") {
                    panic!("{method}: {err}");
                }
                return v["result"].clone();
            }
            // Every stream message is a WebSocket frame event once Network is on, its bytes in
            // base64: not kept, as no test reads them.
            if v.get("method")
                .and_then(Value::as_str)
                .is_some_and(|m| !m.starts_with("Network.webSocketFrame"))
            {
                self.events.push(v);
            }
        }
    }

    /// Evaluates an expression in the page and returns its value.
    pub async fn eval(&mut self, expression: &str) -> Value {
        let r = self
            .call(
                "Runtime.evaluate",
                json!({"expression": expression, "returnByValue": true, "awaitPromise": true}),
            )
            .await;
        if let Some(e) = r.get("exceptionDetails") {
            panic!("evaluating {expression}: {e}");
        }
        r["result"]["value"].clone()
    }

    /// Console errors, uncaught exceptions and error log entries (failed loads included).
    pub fn errors(&self) -> Vec<String> {
        self.events
            .iter()
            .filter_map(|e| {
                let p = &e["params"];
                match e["method"].as_str()? {
                    "Runtime.consoleAPICalled"
                        if matches!(p["type"].as_str(), Some("error" | "assert")) =>
                    {
                        Some(format!("console.error: {}", p["args"]))
                    }
                    "Runtime.exceptionThrown" => Some(format!(
                        "exception: {}",
                        p["exceptionDetails"]["exception"]["description"]
                            .as_str()
                            .unwrap_or(&p["exceptionDetails"]["text"].to_string())
                    )),
                    "Log.entryAdded" if p["entry"]["level"] == "error" => {
                        Some(format!("log: {} {}", p["entry"]["text"], p["entry"]["url"]))
                    }
                    _ => None,
                }
            })
            .collect()
    }

    /// The page's HTTP requests so far, in the order they were sent (from `Network` events;
    /// a WebSocket is not one).
    pub fn requests(&self) -> Vec<Request> {
        let mut out: Vec<Request> = Vec::new();
        let mut at: BTreeMap<String, usize> = BTreeMap::new();
        for e in &self.events {
            let p = &e["params"];
            let id = p["requestId"].as_str().unwrap_or_default().to_string();
            match e["method"].as_str().unwrap_or_default() {
                "Network.requestWillBeSent" => {
                    at.insert(id, out.len());
                    out.push(Request {
                        url: p["request"]["url"].as_str().unwrap_or_default().to_string(),
                        status: None,
                        body_bytes: None,
                        wire_bytes: None,
                    });
                }
                "Network.responseReceived" => {
                    if let Some(&i) = at.get(&id) {
                        let r = &p["response"];
                        out[i].status = r["status"].as_u64();
                        out[i].body_bytes = r["headers"]
                            .as_object()
                            .and_then(|h| {
                                h.iter()
                                    .find(|(k, _)| k.eq_ignore_ascii_case("content-length"))
                            })
                            .and_then(|(_, v)| v.as_str()?.parse().ok());
                    }
                }
                "Network.loadingFinished" => {
                    if let Some(&i) = at.get(&id) {
                        out[i].wire_bytes = p["encodedDataLength"].as_f64().map(|b| b as u64);
                    }
                }
                _ => {}
            }
        }
        out
    }

    /// Polls `expression` every 250 ms until `done` accepts its value (then returns it), or
    /// fails after `within`, or as soon as the page shows an error or logs one.
    pub async fn wait_for(
        &mut self,
        what: &str,
        expression: &str,
        within: Duration,
        mut done: impl FnMut(&Value) -> bool,
    ) -> Value {
        let start = Instant::now();
        let deadline = start + within;
        loop {
            let v = self.eval(expression).await;
            if done(&v) {
                // Where the time goes, for `--nocapture` readers of a slow run.
                println!("{what}: {:.1} s", start.elapsed().as_secs_f64());
                return v;
            }
            let shown = match self.shown_error {
                Some(expression) => self.eval(expression).await,
                None => json!(""),
            };
            let errors = self.errors();
            assert!(
                shown.as_str().unwrap_or("").is_empty() && errors.is_empty(),
                "waiting for {what}: the page shows {shown} and logged {errors:#?}"
            );
            assert!(
                Instant::now() < deadline,
                "waiting for {what}: still {v} after {within:?}"
            );
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
    }
}

/// One HTTP request of a page: its URL, the response's status and `Content-Length`, and the
/// bytes it took on the wire (headers included) once loaded.
#[derive(Clone, Debug)]
pub struct Request {
    pub url: String,
    pub status: Option<u64>,
    pub body_bytes: Option<u64>,
    pub wire_bytes: Option<u64>,
}

/// The bytes of standard base64 text (a screenshot, a canvas's data URL).
pub fn base64_decode(s: &str) -> Vec<u8> {
    use base64::Engine as _;
    base64::engine::general_purpose::STANDARD
        .decode(s)
        .expect("base64 image")
}
