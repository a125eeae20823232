//! The deployment files of `deploy/` other than the nginx replicas of `balancer.rs`: the
//! Kubernetes manifests (`deploy/kubernetes`) validate against the API's schemas and request
//! the memory their own budgets allow, the image (`deploy/docker/Dockerfile`) is multi-stage,
//! runs as a non-root user with lavapipe and sets only settings `serve` has, and HAProxy with
//! the shipped `deploy/haproxy/haproxy.cfg` sends every request about one rig to one replica —
//! live, in front of three stub backends that answer with their index (the request kinds whose
//! key is in the query, an upload's `?name=` and a frame's `?rig=`, once fell back to round
//! robin there).
//!
//! Everything here is std and blocking; every wait is bounded.

use std::io::{Read, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::temp_dir;

/// The longest any wait here may take.
const WAIT: Duration = Duration::from_secs(10);

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("read {}: {e}", path.display()))
}

/// The text of every `.rs` file under `src/` and `crates/`, for checking that a flag or an environment
/// variable the deployment files use is one `serve` has.
fn sources() -> String {
    fn walk(dir: &Path, into: &mut String) {
        let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
            .unwrap_or_else(|e| panic!("list {}: {e}", dir.display()))
            .map(|e| e.expect("a directory entry").path())
            .collect();
        entries.sort();
        for p in entries {
            if p.is_dir() {
                walk(&p, into);
            } else if p.extension().is_some_and(|x| x == "rs") {
                into.push_str(&read(&p));
                into.push('\n');
            }
        }
    }
    let mut all = String::new();
    walk(&repo("src"), &mut all);
    walk(&repo("crates"), &mut all);
    all
}

/// `serve` reads the environment variable `name` (a clap `env = "NAME"` in the sources).
fn has_env(sources: &str, name: &str) -> bool {
    sources.contains(&format!("env = \"{name}\""))
}

/// `serve` has the flag `--flag` (clap's `long` from a field name, or an explicit `long =` or
/// alias).
fn has_flag(sources: &str, flag: &str) -> bool {
    let field = flag.replace('-', "_");
    sources.contains(&format!("long = \"{flag}\""))
        || sources.contains(&format!("alias = \"{flag}\""))
        || sources.contains(&format!("pub {field}:"))
        || sources.contains(&format!("    {field}:"))
}

/// The `--flags` among `args`.
fn flags(args: &[String]) -> Vec<String> {
    args.iter()
        .filter_map(|a| a.strip_prefix("--"))
        .map(|f| f.split('=').next().unwrap_or(f).to_string())
        .collect()
}

/// A line less its `#` comment (none of these files has a `#` inside a value).
fn uncommented(line: &str) -> &str {
    line.split('#').next().unwrap_or("")
}

/// The `CROWDMORPH_*` names in `text` outside comments.
fn crowdmorph_names(text: &str) -> Vec<String> {
    let mut names = Vec::new();
    for line in text.lines() {
        let line = uncommented(line);
        let mut rest = line;
        while let Some(at) = rest.find("CROWDMORPH_") {
            let tail = &rest[at..];
            let end = tail
                .find(|c: char| !(c.is_ascii_uppercase() || c.is_ascii_digit() || c == '_'))
                .unwrap_or(tail.len());
            names.push(tail[..end].to_string());
            rest = &tail[end..];
        }
    }
    names.sort();
    names.dedup();
    names
}

// ---------------------------------------------------------------------------------------------
// Kubernetes

/// A Kubernetes quantity of bytes (`11Gi`, `512Mi`, `2G`, `1073741824`).
fn quantity(q: &str) -> u64 {
    let q = q.trim().trim_matches('"');
    let split = q.find(|c: char| !c.is_ascii_digit()).unwrap_or(q.len());
    let (n, unit) = q.split_at(split);
    let n: u64 = n.parse().unwrap_or_else(|_| panic!("a quantity: {q:?}"));
    let scale: u64 = match unit {
        "" => 1,
        "Ki" => 1 << 10,
        "Mi" => 1 << 20,
        "Gi" => 1 << 30,
        "Ti" => 1 << 40,
        "k" => 1_000,
        "M" => 1_000_000,
        "G" => 1_000_000_000,
        "T" => 1_000_000_000_000,
        _ => panic!("a quantity's unit: {q:?}"),
    };
    n * scale
}

/// The documents of a multi-document YAML file.
fn documents(text: &str) -> Vec<String> {
    let mut docs = vec![String::new()];
    for line in text.lines() {
        if line.trim_end() == "---" {
            docs.push(String::new());
        } else {
            let doc = docs.last_mut().expect("one");
            doc.push_str(line);
            doc.push('\n');
        }
    }
    docs.retain(|d| d.lines().any(|l| l.starts_with("kind:")));
    docs
}

/// The top-level value of `key` in a document (`kind`).
fn top(doc: &str, key: &str) -> Option<String> {
    doc.lines()
        .find_map(|l| l.strip_prefix(&format!("{key}:")))
        .map(|v| uncommented(v).trim().to_string())
}

/// The value on the first line after line `from` that is `key: value` (indentation ignored).
fn value_after(lines: &[&str], from: usize, key: &str) -> Option<(usize, String)> {
    lines.iter().enumerate().skip(from).find_map(|(i, l)| {
        let l = uncommented(l).trim().trim_start_matches("- ");
        l.strip_prefix(&format!("{key}:"))
            .map(|v| (i, v.trim().trim_matches('"').to_string()))
    })
}

/// The line index of `text` (trimmed, comments aside) in `lines`.
fn line_of(lines: &[&str], text: &str) -> Option<usize> {
    lines.iter().position(|l| uncommented(l).trim() == text)
}

/// The value of the container environment variable `name` (`- name: NAME` then `value:`).
fn env_value(lines: &[&str], name: &str) -> Option<String> {
    let at = line_of(lines, &format!("- name: {name}"))?;
    let (i, v) = value_after(lines, at + 1, "value")?;
    (i == at + 1).then_some(v)
}

/// Checks one Deployment: probes, memory, flags and environment variables.
fn check_deployment(file: &str, doc: &str, sources: &str) {
    let lines: Vec<&str> = doc.lines().collect();
    let name = value_after(&lines, 0, "name")
        .map(|(_, n)| n)
        .unwrap_or_default();
    let what = format!("{file}: Deployment {name}");

    let probe = |kind: &str| {
        let at =
            line_of(&lines, &format!("{kind}:")).unwrap_or_else(|| panic!("{what} has a {kind}"));
        value_after(&lines, at + 1, "path")
            .unwrap_or_else(|| panic!("{what}: the {kind}'s path"))
            .1
    };
    assert_eq!(probe("readinessProbe"), "/readyz", "{what}: readiness");
    assert_eq!(probe("livenessProbe"), "/healthz", "{what}: liveness");

    // The memory request covers the two budgets the server is given in the same file.
    let rig = env_value(&lines, "CROWDMORPH_MAX_RIG_MEMORY")
        .unwrap_or_else(|| panic!("{what} sets CROWDMORPH_MAX_RIG_MEMORY"));
    let queue = env_value(&lines, "CROWDMORPH_QUEUE_MEMORY_BYTES")
        .unwrap_or_else(|| panic!("{what} sets CROWDMORPH_QUEUE_MEMORY_BYTES"));
    let budgets = quantity(&rig) + quantity(&queue);
    let requests = line_of(&lines, "requests:").unwrap_or_else(|| panic!("{what}: requests"));
    let limits = line_of(&lines, "limits:").unwrap_or_else(|| panic!("{what}: limits"));
    let (at, request) = value_after(&lines, requests + 1, "memory")
        .unwrap_or_else(|| panic!("{what}: a memory request"));
    assert!(
        at < limits || requests > limits,
        "{what}: the memory request is under requests:"
    );
    let (_, limit) =
        value_after(&lines, limits + 1, "memory").unwrap_or_else(|| panic!("{what}: a limit"));
    let (request, limit) = (quantity(&request), quantity(&limit));
    assert!(
        request >= budgets,
        "{what}: a memory request of {request} bytes is less than \
         CROWDMORPH_MAX_RIG_MEMORY {rig} + CROWDMORPH_QUEUE_MEMORY_BYTES {queue}"
    );
    assert!(
        limit >= request,
        "{what}: the memory limit is below the request"
    );

    // Non-root, with the image's uid, and a writable /data on a read-only root.
    for needed in [
        "runAsNonRoot: true",
        "runAsUser: 10001",
        "readOnlyRootFilesystem: true",
        "mountPath: /data",
    ] {
        assert!(line_of(&lines, needed).is_some(), "{what}: {needed}");
    }

    // The container's arguments: `serve` and flags it has.
    let (_, args) = value_after(&lines, 0, "args").unwrap_or_else(|| panic!("{what}: args"));
    let args: Vec<String> = args
        .trim_matches(|c| c == '[' || c == ']')
        .split(',')
        .map(|a| a.trim().trim_matches('"').to_string())
        .collect();
    assert_eq!(args[0], "serve", "{what}: runs `serve`");
    for f in flags(&args) {
        assert!(has_flag(sources, &f), "{what}: `serve` has no --{f}");
    }
}

#[test]
#[cfg_attr(
    not(crowdmorph_kubernetes_validate),
    ignore = "needs kubernetes-validate: pip install --break-system-packages \
              kubernetes-validate (then touch build.rs)"
)]
fn kubernetes_manifests_validate() {
    let dir = repo("deploy/kubernetes");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("deploy/kubernetes")
        .map(|e| e.expect("an entry").path())
        .filter(|p| p.extension().is_some_and(|x| x == "yaml" || x == "yml"))
        .collect();
    files.sort();
    assert!(files.len() >= 3, "the manifests: {files:?}");

    // Against the schemas of the API server, unknown fields rejected.
    let tool = option_env!("CROWDMORPH_KUBERNETES_VALIDATE_PATH").unwrap_or("kubernetes-validate");
    let out = Command::new(tool)
        .args(["--strict", "--kubernetes-version", "1.30.0"])
        .args(&files)
        .output()
        .expect("run kubernetes-validate");
    assert!(
        out.status.success(),
        "kubernetes-validate --strict: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );

    let sources = sources();
    let mut deployments = Vec::new();
    let mut scaled = Vec::new();
    let mut adapter_rule = false;
    for path in &files {
        let file = path
            .file_name()
            .expect("a name")
            .to_string_lossy()
            .into_owned();
        let text = read(path);
        // Every CROWDMORPH_ setting the manifests give is one `serve` reads.
        for name in crowdmorph_names(&text) {
            assert!(
                has_env(&sources, &name),
                "{file}: `serve` reads no environment variable {name}"
            );
        }
        for doc in documents(&text) {
            let lines: Vec<&str> = doc.lines().collect();
            match top(&doc, "kind").as_deref() {
                Some("Deployment") => {
                    check_deployment(&file, &doc, &sources);
                    let (_, name) = value_after(&lines, 0, "name").expect("a name");
                    deployments.push(name);
                }
                Some("HorizontalPodAutoscaler") => {
                    let metric = line_of(&lines, "metric:").expect("an HPA metric");
                    let (_, name) = value_after(&lines, metric + 1, "name").expect("its name");
                    assert_eq!(name, "crowdmorph_queue_depth", "{file}: the HPA's metric");
                    assert!(
                        line_of(&lines, "- type: Pods").is_some()
                            && line_of(&lines, "type: AverageValue").is_some(),
                        "{file}: a Pods metric with an averageValue"
                    );
                    let target = line_of(&lines, "scaleTargetRef:").expect("a target");
                    let (_, name) = value_after(&lines, target + 1, "name").expect("its name");
                    scaled.push(name);
                }
                Some("ConfigMap") if doc.contains("seriesQuery:") => {
                    adapter_rule = doc.contains("seriesQuery: 'crowdmorph_queue_depth{")
                        && doc.contains("as: \"crowdmorph_queue_depth\"");
                }
                _ => {}
            }
        }
    }
    assert!(!deployments.is_empty(), "a Deployment");
    for name in &scaled {
        assert!(
            deployments.contains(name),
            "the HPA scales {name}, not shipped"
        );
    }
    assert!(!scaled.is_empty(), "an HPA");
    assert!(
        adapter_rule,
        "prometheus-adapter serves crowdmorph_queue_depth as the HPAs' metric"
    );
    // The gauge the HPAs scale on is one the server exports.
    assert!(
        sources.contains("\"crowdmorph_queue_depth\""),
        "the server exports crowdmorph_queue_depth"
    );
}

// ---------------------------------------------------------------------------------------------
// The image

/// A Dockerfile's instructions: continuation lines joined, comments and blank lines dropped,
/// as (INSTRUCTION, arguments).
fn instructions(text: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut current = String::new();
    for line in text.lines() {
        let t = line.trim();
        if t.starts_with('#') || (t.is_empty() && current.is_empty()) {
            continue;
        }
        match t.strip_suffix('\\') {
            Some(part) => {
                current.push_str(part);
                current.push(' ');
            }
            None => {
                current.push_str(t);
                let (op, args) = current
                    .split_once(char::is_whitespace)
                    .unwrap_or((&current, ""));
                out.push((op.to_ascii_uppercase(), args.trim().to_string()));
                current.clear();
            }
        }
    }
    out
}

/// The words of an exec-form (`["a", "b"]`) or shell-form instruction.
fn words(args: &str) -> Vec<String> {
    let a = args.trim();
    if let Some(inner) = a.strip_prefix('[').and_then(|a| a.strip_suffix(']')) {
        inner
            .split(',')
            .map(|w| w.trim().trim_matches('"').to_string())
            .collect()
    } else {
        a.split_whitespace().map(str::to_string).collect()
    }
}

#[test]
fn dockerfile_is_multi_stage_and_non_root() {
    let text = read(&repo("deploy/docker/Dockerfile"));
    let all = instructions(&text);
    let froms: Vec<usize> = (0..all.len()).filter(|&i| all[i].0 == "FROM").collect();
    assert!(
        froms.len() >= 2,
        "a build stage and a runtime stage: {froms:?}"
    );
    let build = &all[froms[0]..froms[1]];
    assert!(
        build
            .iter()
            .any(|(op, a)| op == "RUN" && a.contains("cargo build --release --locked")),
        "the builder builds the release binary with the lock file"
    );
    let last = &all[*froms.last().expect("a FROM")..];

    // A numeric, non-zero uid (Kubernetes' runAsNonRoot checks it without /etc/passwd).
    let users: Vec<&String> = last
        .iter()
        .filter(|(op, _)| op == "USER")
        .map(|(_, a)| a)
        .collect();
    let user = users
        .last()
        .unwrap_or_else(|| panic!("a USER in the last stage"));
    let uid: u32 = user
        .split(':')
        .next()
        .and_then(|u| u.parse().ok())
        .unwrap_or_else(|| panic!("USER {user}: a numeric uid"));
    assert_ne!(uid, 0, "the server does not run as root");

    // lavapipe in the image that runs.
    assert!(
        last.iter().any(|(op, a)| op == "RUN"
            && a.contains("apt-get install")
            && a.contains("mesa-vulkan-drivers")
            && a.contains("libvulkan1")),
        "the runtime stage installs mesa-vulkan-drivers and libvulkan1"
    );
    assert!(
        last.iter()
            .any(|(op, a)| op == "COPY" && a.contains("--from=") && a.contains("crowdmorph")),
        "the runtime stage takes the binary from the builder"
    );

    // What it runs: `crowdmorph serve`, with flags and settings `serve` has.
    let sources = sources();
    let entry = last
        .iter()
        .rev()
        .find(|(op, _)| op == "ENTRYPOINT")
        .map(|(_, a)| words(a))
        .expect("an ENTRYPOINT");
    let cmd = last
        .iter()
        .rev()
        .find(|(op, _)| op == "CMD")
        .map(|(_, a)| words(a))
        .expect("a CMD");
    assert_eq!(entry, ["crowdmorph"], "ENTRYPOINT");
    assert_eq!(cmd.first().map(String::as_str), Some("serve"), "CMD");
    for f in flags(&entry).into_iter().chain(flags(&cmd)) {
        assert!(has_flag(&sources, &f), "`serve` has no --{f}");
    }
    let env: String = last
        .iter()
        .filter(|(op, _)| op == "ENV")
        .map(|(_, a)| format!("{a}\n"))
        .collect();
    let names = crowdmorph_names(&env);
    for needed in ["CROWDMORPH_ADDR", "CROWDMORPH_DATA_DIR"] {
        assert!(names.iter().any(|n| n == needed), "the image sets {needed}");
    }
    for name in &names {
        assert!(
            has_env(&sources, name),
            "`serve` reads no environment variable {name}"
        );
    }
    assert!(
        env.contains("CROWDMORPH_ADDR=0.0.0.0:"),
        "the server listens on every interface of the container"
    );
    assert!(
        last.iter()
            .any(|(op, a)| op == "EXPOSE" && a.split_whitespace().any(|p| p == "8080")),
        "EXPOSE 8080"
    );
}

// ---------------------------------------------------------------------------------------------
// HAProxy, live

/// Three stub replicas on 127.0.0.1:0: each answers any request with `200` and its index, and
/// records the request lines it got. Stopped when dropped.
struct Backends {
    ports: Vec<u16>,
    seen: Arc<Mutex<Vec<(usize, String)>>>,
    stop: Arc<AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl Drop for Backends {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

/// Reads one HTTP/1.x message head (through the blank line) and then `Content-Length` bytes
/// of body from `s`; returns the head and the body. `None` on end of stream before a head.
fn read_message(s: &mut TcpStream) -> Option<(String, Vec<u8>)> {
    let mut buf = Vec::new();
    let mut byte = [0u8; 1];
    while !buf.ends_with(b"\r\n\r\n") {
        match s.read(&mut byte) {
            Ok(1) => buf.push(byte[0]),
            _ => return None,
        }
        assert!(buf.len() < 64 << 10, "a message head under 64 KiB");
    }
    let head = String::from_utf8_lossy(&buf).into_owned();
    let length = head
        .lines()
        .find_map(|l| {
            let (k, v) = l.split_once(':')?;
            k.trim()
                .eq_ignore_ascii_case("content-length")
                .then(|| v.trim().parse::<usize>().ok())?
        })
        .unwrap_or(0);
    let mut body = vec![0u8; length];
    s.read_exact(&mut body).ok()?;
    Some((head, body))
}

fn backends() -> Backends {
    let seen = Arc::new(Mutex::new(Vec::new()));
    let stop = Arc::new(AtomicBool::new(false));
    let mut ports = Vec::new();
    let mut threads = Vec::new();
    for index in 0..3 {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind a backend");
        listener.set_nonblocking(true).expect("nonblocking");
        ports.push(listener.local_addr().expect("its address").port());
        let (seen, stop) = (seen.clone(), stop.clone());
        threads.push(std::thread::spawn(move || {
            while !stop.load(Ordering::SeqCst) {
                let mut s = match listener.accept() {
                    Ok((s, _)) => s,
                    Err(_) => {
                        std::thread::sleep(Duration::from_millis(5));
                        continue;
                    }
                };
                // One request per connection (Connection: close), at most WAIT to arrive.
                let _ = s.set_nonblocking(false);
                let _ = s.set_read_timeout(Some(WAIT));
                let _ = s.set_write_timeout(Some(WAIT));
                let Some((head, _body)) = read_message(&mut s) else {
                    continue;
                };
                let line = head.lines().next().unwrap_or("").to_string();
                seen.lock().expect("the log").push((index, line));
                let body = index.to_string();
                let _ = write!(
                    s,
                    "HTTP/1.1 200 OK\r\nContent-Type: text/plain\r\nContent-Length: {}\r\n\
                     Connection: close\r\n\r\n{body}",
                    body.len()
                );
                let _ = s.flush();
                let _ = s.shutdown(Shutdown::Both);
            }
        }));
    }
    Backends {
        ports,
        seen,
        stop,
        threads,
    }
}

/// HAProxy in the foreground with the shipped configuration, its bind and its three server
/// lines pointed at this test's ports; killed when dropped.
struct Haproxy {
    child: Child,
    port: u16,
    log: PathBuf,
}

impl Drop for Haproxy {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Haproxy {
    fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

fn haproxy(backends: &[u16]) -> Haproxy {
    let dir = temp_dir("haproxy");
    let port = TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free port");
    let shipped = read(&repo("deploy/haproxy/haproxy.cfg"));
    assert!(
        shipped.contains("    bind :8080\n"),
        "the shipped bind line"
    );
    let mut servers = 0;
    let conf: String = shipped
        .lines()
        .map(|line| {
            let words: Vec<&str> = line.split_whitespace().collect();
            if line.trim_start().starts_with("bind ") {
                format!("    bind 127.0.0.1:{port}\n")
            } else if words.first() == Some(&"server") && words.len() >= 3 {
                let at = backends[servers.min(backends.len() - 1)];
                servers += 1;
                let mut w: Vec<String> = words.iter().map(|w| w.to_string()).collect();
                w[2] = format!("127.0.0.1:{at}");
                format!("    {}\n", w.join(" "))
            } else {
                format!("{line}\n")
            }
        })
        .collect();
    assert_eq!(
        servers,
        backends.len(),
        "the shipped file lists three replicas"
    );
    let path = dir.join("haproxy.cfg");
    std::fs::write(&path, conf).expect("write");
    let tool = option_env!("CROWDMORPH_HAPROXY_PATH").unwrap_or("haproxy");
    let log = dir.join("haproxy.log");
    // -db: the foreground, no daemon; -n: a connection limit this test's open-file limit
    // allows (the shipped maxconn wants about 40,000 descriptors).
    let child = Command::new(tool)
        .args(["-db", "-n", "256", "-f"])
        .arg(&path)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&log).expect("a log"))
        .stderr(std::fs::File::create(dir.join("haproxy.err")).expect("a log"))
        .spawn()
        .expect("start haproxy");
    let mut h = Haproxy {
        child,
        port,
        log: dir.join("haproxy.err"),
    };
    let started = Instant::now();
    while TcpStream::connect(("127.0.0.1", port)).is_err() {
        if let Ok(Some(status)) = h.child.try_wait() {
            panic!("haproxy exited ({status}): {}", h.log());
        }
        assert!(
            started.elapsed() < WAIT,
            "haproxy did not listen: {}",
            h.log()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    h
}

/// Writes one request for `target` on `s` (no body but `body`) and reads its answer: the
/// backend's index.
fn ask(s: &mut TcpStream, method: &str, target: &str, body: &[u8], close: bool) -> usize {
    let connection = if close { "close" } else { "keep-alive" };
    write!(
        s,
        "{method} {target} HTTP/1.1\r\nHost: crowdmorph.test\r\n\
         Content-Type: application/octet-stream\r\nContent-Length: {}\r\n\
         Connection: {connection}\r\n\r\n",
        body.len()
    )
    .expect("send a request");
    s.write_all(body).expect("send its body");
    let (head, body) = read_message(s).unwrap_or_else(|| panic!("an answer to {method} {target}"));
    assert!(
        head.starts_with("HTTP/1.1 200"),
        "{method} {target} through haproxy: {head}"
    );
    String::from_utf8_lossy(&body)
        .trim()
        .parse()
        .unwrap_or_else(|_| panic!("{method} {target}: a backend's index, not {body:?}"))
}

fn connect(port: u16) -> TcpStream {
    let s = TcpStream::connect_timeout(&([127, 0, 0, 1], port).into(), WAIT).expect("connect");
    s.set_read_timeout(Some(WAIT)).expect("timeout");
    s.set_write_timeout(Some(WAIT)).expect("timeout");
    s
}

/// One request on a connection of its own.
fn once(port: u16, method: &str, target: &str, body: &[u8]) -> usize {
    ask(&mut connect(port), method, target, body, true)
}

#[test]
#[cfg_attr(
    not(crowdmorph_haproxy),
    ignore = "needs HAProxy: apt-get install haproxy (then touch build.rs)"
)]
fn haproxy_hashes_a_rig_to_one_replica_live() {
    let stubs = backends();
    let lb = haproxy(&stubs.ports);

    // The health checks ask each replica for /readyz, and every replica is up (rise 2): wait
    // until each has answered two of them.
    let started = Instant::now();
    loop {
        let checks: Vec<usize> = (0..3)
            .map(|i| {
                let seen = stubs.seen.lock().expect("the log");
                seen.iter()
                    .filter(|(at, line)| *at == i && line.starts_with("GET /readyz "))
                    .count()
            })
            .collect();
        if checks.iter().all(|&n| n >= 2) {
            break;
        }
        assert!(
            started.elapsed() < WAIT,
            "health checks on /readyz per replica: {checks:?}; {}",
            lb.log()
        );
        std::thread::sleep(Duration::from_millis(50));
    }

    let glb = b"glTF\x02\x00\x00\x00";
    let frame = br#"{"heads":[]}"#;
    let mut owner = Vec::new();
    for k in 0..8 {
        let rig = format!("rig{k}");
        // An upload (the key in the query), a crowd frame and a render (the clients' ?rig=),
        // and requests with the key in the path: all about one rig, all on one replica.
        let at = [
            once(lb.port, "POST", &format!("/v1/rigs?name={rig}"), glb),
            once(
                lb.port,
                "POST",
                &format!("/v1/crowd/frame?rig={rig}"),
                frame,
            ),
            once(
                lb.port,
                "POST",
                &format!("/v1/crowd/render?rig={rig}"),
                frame,
            ),
            once(lb.port, "GET", &format!("/v1/rigs/{rig}"), b""),
            once(lb.port, "POST", &format!("/v1/rigs/{rig}/lod"), b"{}"),
            once(
                lb.port,
                "POST",
                &format!("/v1/crowd/frame?rig={rig}"),
                frame,
            ),
        ];
        assert!(
            at.iter().all(|&b| b == at[0]),
            "the requests about {rig} reached replicas {at:?} (upload, frame, render, \
             GET, LOD, frame)"
        );
        owner.push(at[0]);

        // A session: its creation and its stream on one replica.
        let session = format!("lobby-{k}");
        let put = once(lb.port, "PUT", &format!("/v1/sessions/{session}"), b"{}");
        let stream = once(
            lb.port,
            "GET",
            &format!("/v1/sessions/{session}/stream"),
            b"",
        );
        assert_eq!(put, stream, "session {session}: PUT and stream");
    }
    let mut used = owner.clone();
    used.sort();
    used.dedup();
    assert!(used.len() >= 2, "eight rigs spread over replicas {owner:?}");

    // The clients keep connections alive: on one connection, each request is routed by its
    // own key, not by the connection's first.
    let mut kept = connect(lb.port);
    for (k, &expected) in owner.iter().enumerate() {
        let b = ask(
            &mut kept,
            "POST",
            &format!("/v1/crowd/frame?rig=rig{k}"),
            frame,
            false,
        );
        assert_eq!(b, expected, "rig{k} on a kept-alive connection");
    }
    drop(kept);
    drop(lb);
    drop(stubs);
}
