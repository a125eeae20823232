//! Shaped links for the server benchmarks (`--link 1gbit,100mbit`): the server in this process
//! also listens inside a network namespace of its own, joined to this host by a veth pair
//! whose two ends are shaped with `tbf`, and the clients, on the host, reach it through that
//! pair. One server state serves loopback and every link, so each route sees the same rig,
//! clips and sessions.
//!
//! Only `tbf` and `htb` exist in the kernels of the project's machines (no `netem`, `cake` or
//! `fq`), so a link has a rate and no added delay or loss; its queue holds at most 50 ms.
//! Traffic stays on addresses of the namespaces made here (a free /30 of `10.213.0.0/16`
//! each, the host's end and the namespace's); each is removed
//! when its [`ShapedLink`] drops, and on Ctrl-C ([`cleanup_on_ctrl_c`]). It needs root and
//! iproute2; [`preflight`] says what is missing, and the benchmarks then skip the shaped
//! routes with that reason and measure loopback alone.

use std::net::{Ipv4Addr, SocketAddr};
use std::process::Command;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use serde::Serialize;

use crowdmorph_server::AppState;

/// A link rate asked for on the command line: `1gbit`, `100mbit`, `500kbit`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LinkSpec {
    /// As written (lowercase), also `tc`'s rate.
    pub name: String,
    /// Bits per second.
    pub bits_per_s: u64,
}

impl std::str::FromStr for LinkSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<LinkSpec, String> {
        let name = s.trim().to_ascii_lowercase();
        let (digits, unit) = name
            .find(|c: char| !c.is_ascii_digit())
            .map_or((name.as_str(), ""), |i| name.split_at(i));
        let scale = match unit {
            "kbit" => 1_000,
            "mbit" => 1_000_000,
            "gbit" => 1_000_000_000,
            _ => {
                return Err(format!(
                    "link rate {s:?}: write it as <n>kbit, <n>mbit or <n>gbit"
                ));
            }
        };
        let n: u64 = digits
            .parse()
            .map_err(|_| format!("link rate {s:?}: no number before the unit"))?;
        let bits_per_s = n
            .checked_mul(scale)
            .filter(|b| (100_000..=100_000_000_000).contains(b))
            .ok_or_else(|| format!("link rate {s:?} is not between 100kbit and 100gbit"))?;
        Ok(LinkSpec { name, bits_per_s })
    }
}

impl LinkSpec {
    /// `tbf`'s bucket: about 8 ms at the rate, at least 256 KB (the measured notes: 1 MB at
    /// 1 Gbit/s, 256 KB at 100 Mbit/s; a bucket too small for the rate caps throughput).
    fn burst_bytes(&self) -> u64 {
        (self.bits_per_s / 1000).max(256 * 1024)
    }

    /// Bytes per second of the rate.
    pub fn bytes_per_s(&self) -> f64 {
        self.bits_per_s as f64 / 8.0
    }
}

/// `Ok` when shaped links can be made here, else why not (for the benchmark's skip line).
pub fn preflight() -> Result<(), String> {
    #[cfg(unix)]
    {
        // SAFETY: geteuid has no preconditions and cannot fail.
        let uid = unsafe { libc::geteuid() };
        if uid != 0 {
            return Err(format!(
                "shaped links need root (network namespaces, veth, tc); running as uid {uid}"
            ));
        }
        for tool in ["ip", "tc"] {
            match Command::new(tool).arg("-V").output() {
                Ok(o) if o.status.success() => {}
                _ => return Err(format!("shaped links need iproute2's `{tool}`, not found")),
            }
        }
        Ok(())
    }
    #[cfg(not(unix))]
    Err("shaped links need Linux network namespaces".to_string())
}

/// Namespaces and host interfaces made by this process and not yet removed, for Ctrl-C.
static ACTIVE: Mutex<Vec<(String, String)>> = Mutex::new(Vec::new());

/// Removes namespace `ns` and host interface `host` (which takes its veth peer with it);
/// errors are ignored, as either may already be gone.
fn remove(ns: &str, host: &str) {
    let _ = Command::new("ip").args(["link", "del", host]).output();
    let _ = Command::new("ip").args(["netns", "del", ns]).output();
}

/// On Ctrl-C, removes every link this process made and exits with status 130 (a `Drop` does
/// not run when the process is interrupted). Call inside the benchmark's runtime.
pub fn cleanup_on_ctrl_c() {
    tokio::spawn(async {
        if tokio::signal::ctrl_c().await.is_ok() {
            let active = std::mem::take(&mut *ACTIVE.lock().unwrap_or_else(|e| e.into_inner()));
            for (ns, host) in &active {
                remove(ns, host);
            }
            eprintln!("interrupted: removed {} shaped link(s)", active.len());
            std::process::exit(130);
        }
    });
}

/// Runs one command, failing with its standard error.
fn sh(args: &[&str]) -> Result<()> {
    let out = Command::new(args[0])
        .args(&args[1..])
        .output()
        .with_context(|| format!("running {}", args.join(" ")))?;
    if !out.status.success() {
        bail!(
            "{} failed: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    Ok(())
}

/// One shaped link: a namespace, a veth pair shaped at both ends, the namespace's address.
#[derive(Debug)]
pub struct ShapedLink {
    /// The rate.
    pub spec: LinkSpec,
    /// The namespace's end, where the server listens.
    pub addr: Ipv4Addr,
    ns: String,
    host: String,
}

impl ShapedLink {
    /// Makes link `index` (0..64) at `spec`'s rate. Whatever was made is removed again when
    /// a step fails.
    pub fn create(index: u8, spec: &LinkSpec) -> Result<ShapedLink> {
        if index >= 64 {
            bail!("at most 64 shaped links");
        }
        // Interface names have at most 15 bytes; the pid keeps two benchmarks apart.
        let pid = std::process::id() % 100_000;
        let ns = format!("crowdmorph-bench-{pid}-{index}");
        let host = format!("cmb{pid}h{index}");
        let peer = format!("cmb{pid}n{index}");
        let (host_addr, addr) = free_subnet(pid, index)?;
        ACTIVE
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push((ns.clone(), host.clone()));
        // Dropped on failure below, which removes what was made.
        let link = ShapedLink {
            spec: spec.clone(),
            addr,
            ns,
            host,
        };
        let (ns, host) = (link.ns.as_str(), link.host.as_str());
        let rate = spec.name.as_str();
        let burst = spec.burst_bytes().to_string();
        let tbf = [
            "root", "tbf", "rate", rate, "burst", &burst, "latency", "50ms",
        ];
        sh(&["ip", "netns", "add", ns])?;
        sh(&[
            "ip", "link", "add", host, "type", "veth", "peer", "name", &peer,
        ])?;
        sh(&["ip", "link", "set", &peer, "netns", ns])?;
        sh(&["ip", "addr", "add", &format!("{host_addr}/30"), "dev", host])?;
        sh(&["ip", "link", "set", host, "up"])?;
        sh(&[
            "ip",
            "-n",
            ns,
            "addr",
            "add",
            &format!("{addr}/30"),
            "dev",
            &peer,
        ])?;
        sh(&["ip", "-n", ns, "link", "set", &peer, "up"])?;
        sh(&["ip", "-n", ns, "link", "set", "lo", "up"])?;
        // Host -> namespace (requests), then namespace -> host (responses).
        let mut host_tc = vec!["tc", "qdisc", "add", "dev", host];
        host_tc.extend(tbf);
        sh(&host_tc)?;
        let mut peer_tc = vec![
            "ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", &peer,
        ];
        peer_tc.extend(tbf);
        sh(&peer_tc)?;
        Ok(link)
    }

    /// A listener on a free port of the namespace's address: bound from a thread that joined
    /// the namespace, so that the socket belongs to it; the thread then ends, and the socket
    /// serves from any thread of this process.
    pub fn bind(&self) -> Result<tokio::net::TcpListener> {
        let path = format!("/var/run/netns/{}", self.ns);
        let addr = self.addr;
        let listener = std::thread::spawn(move || -> Result<std::net::TcpListener> {
            enter_namespace(&path)?;
            let l = std::net::TcpListener::bind((addr, 0))?;
            l.set_nonblocking(true)?;
            Ok(l)
        })
        .join()
        .map_err(|_| anyhow::anyhow!("the namespace thread panicked"))??;
        Ok(tokio::net::TcpListener::from_std(listener)?)
    }
}

/// A /30 of 10.213.0.0/16 that no interface here uses: the host's end and the namespace's.
/// The search starts at a place given by the pid and the link's index, so that two
/// benchmarks at once (tests run in parallel) pick different ones.
fn free_subnet(pid: u32, index: u8) -> Result<(Ipv4Addr, Ipv4Addr)> {
    let out = Command::new("ip")
        .args(["-o", "-4", "addr", "show"])
        .output()
        .context("listing addresses")?;
    let used = String::from_utf8_lossy(&out.stdout).into_owned();
    const SUBNETS: u32 = 1 << 14;
    let start = (pid.wrapping_mul(64) + u32::from(index)) % SUBNETS;
    for k in 0..SUBNETS {
        let n = (start + k) % SUBNETS;
        let (c, d) = ((n / 64) as u8, ((n % 64) * 4) as u8);
        let host = Ipv4Addr::new(10, 213, c, d + 1);
        let inside = Ipv4Addr::new(10, 213, c, d + 2);
        let taken = |a: Ipv4Addr| used.contains(&format!("inet {a}/"));
        if !taken(host) && !taken(inside) {
            return Ok((host, inside));
        }
    }
    bail!("no free /30 left in 10.213.0.0/16")
}

#[cfg(unix)]
fn enter_namespace(path: &str) -> Result<()> {
    use std::os::fd::AsRawFd;
    let f = std::fs::File::open(path).with_context(|| format!("opening {path}"))?;
    // SAFETY: setns on a namespace file descriptor that stays open for the call; it changes
    // only this thread's network namespace, and this thread ends after binding.
    if unsafe { libc::setns(f.as_raw_fd(), libc::CLONE_NEWNET) } != 0 {
        bail!("setns {path}: {}", std::io::Error::last_os_error());
    }
    Ok(())
}

#[cfg(not(unix))]
fn enter_namespace(_: &str) -> Result<()> {
    bail!("network namespaces need Linux")
}

impl Drop for ShapedLink {
    fn drop(&mut self) {
        remove(&self.ns, &self.host);
        ACTIVE
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .retain(|(ns, _)| ns != &self.ns);
    }
}

/// One way to reach the server: loopback, or a shaped link.
#[derive(Clone, Debug, Serialize)]
pub struct Route {
    /// `loopback` or the link's rate (`1gbit`).
    pub name: String,
    /// Where the server listens on it.
    pub addr: SocketAddr,
    /// The link's rate in bits per second (`None`: loopback, no shaping).
    pub bits_per_s: Option<u64>,
    /// The link's network namespace (`None`: loopback); gone when the benchmark ends.
    pub namespace: Option<String>,
    /// Bytes per second plain TCP carried over it in this run (as many connections as the
    /// benchmark's clients, large writes, no HTTP): the most any server can send over it.
    pub tcp_bytes_per_s: f64,
}

/// The route's line in both link reports: its name and what plain TCP carried over it.
impl std::fmt::Display for Route {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "  {:<9} plain TCP carries {:.1} MB/s",
            self.name,
            self.tcp_bytes_per_s / 1e6
        )?;
        match self.bits_per_s {
            Some(b) => write!(f, " (shaped at {:.1} MB/s)", b as f64 / 8e6),
            None => Ok(()),
        }
    }
}

/// The routes of one benchmark run and what keeps them open.
pub struct Routes {
    /// Loopback first, then each link.
    pub routes: Vec<Route>,
    /// Why the shaped links were skipped, when they were.
    pub skipped: Option<String>,
    stops: Vec<tokio::sync::oneshot::Sender<()>>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
    // Dropped last (declared last): the namespaces go after the listeners stop.
    links: Vec<ShapedLink>,
}

impl Routes {
    /// Loopback (`loopback`, where the server already listens) and a shaped link per spec,
    /// each served by `state` through [`crowdmorph_server::serve_also`], each with its plain TCP
    /// throughput measured over `connections` connections for `seconds`.
    pub async fn open(
        state: &AppState,
        loopback: SocketAddr,
        specs: &[LinkSpec],
        connections: usize,
        seconds: f64,
    ) -> Result<Routes> {
        let mut routes = Routes {
            routes: Vec::new(),
            skipped: None,
            stops: Vec::new(),
            tasks: Vec::new(),
            links: Vec::new(),
        };
        let tcp = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let connect = tcp.local_addr()?;
        routes.routes.push(Route {
            name: "loopback".to_string(),
            addr: loopback,
            bits_per_s: None,
            namespace: None,
            tcp_bytes_per_s: tcp_throughput(tcp, connect, connections, seconds).await?,
        });
        if specs.is_empty() {
            return Ok(routes);
        }
        if let Err(why) = preflight() {
            routes.skipped = Some(why);
            return Ok(routes);
        }
        cleanup_on_ctrl_c();
        for (i, spec) in specs.iter().enumerate() {
            // Root without leave to make namespaces (an unprivileged container) is a reason
            // to skip the links, not a failed benchmark.
            let link = match ShapedLink::create(i as u8, spec) {
                Ok(link) => link,
                Err(e) => {
                    routes.skipped = Some(format!("could not make the {} link: {e:#}", spec.name));
                    break;
                }
            };
            let listener = link.bind()?;
            let addr = listener.local_addr()?;
            let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
            routes
                .tasks
                .push(tokio::spawn(crowdmorph_server::serve_also(
                    listener,
                    state.clone(),
                    async {
                        let _ = stop_rx.await;
                    },
                )));
            routes.stops.push(stop_tx);
            let tcp = link.bind()?;
            let connect = tcp.local_addr()?;
            let tcp_bytes_per_s = tcp_throughput(tcp, connect, connections, seconds).await?;
            routes.routes.push(Route {
                name: spec.name.clone(),
                addr,
                bits_per_s: Some(spec.bits_per_s),
                namespace: Some(link.ns.clone()),
                tcp_bytes_per_s,
            });
            routes.links.push(link);
        }
        Ok(routes)
    }

    /// Stops serving the links, then removes them.
    pub async fn close(mut self) {
        for s in self.stops.drain(..) {
            let _ = s.send(());
        }
        for t in self.tasks.drain(..) {
            // A connection still open would hold the task: the namespaces go regardless.
            let _ = tokio::time::timeout(Duration::from_secs(5), t).await;
        }
    }
}

/// Bytes per second `connections` TCP connections to `connect` (accepted by `listener`)
/// carry together with large writes and reads for `seconds`, writers and readers in this
/// process's runtime: the most bytes per second a server here can hand to its clients over
/// that route.
pub async fn tcp_throughput(
    listener: tokio::net::TcpListener,
    connect: SocketAddr,
    connections: usize,
    seconds: f64,
) -> Result<f64> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let deadline = Instant::now() + Duration::from_secs_f64(seconds);
    let n = connections.max(1);
    let writers = tokio::spawn(async move {
        let mut tasks = Vec::new();
        for _ in 0..n {
            let (mut tcp, _) = listener.accept().await?;
            tcp.set_nodelay(true)?;
            tasks.push(tokio::spawn(async move {
                let chunk = vec![7u8; 1 << 20];
                while Instant::now() < deadline {
                    tcp.write_all(&chunk).await?;
                }
                anyhow::Ok(())
            }));
        }
        for t in tasks {
            t.await??;
        }
        anyhow::Ok(())
    });
    let start = Instant::now();
    let mut readers = Vec::new();
    for _ in 0..n {
        let mut tcp = tokio::net::TcpStream::connect(connect).await?;
        readers.push(tokio::spawn(async move {
            let mut buf = vec![0u8; 1 << 20];
            let mut total = 0usize;
            loop {
                let got = tcp.read(&mut buf).await?;
                if got == 0 {
                    break;
                }
                total += got;
            }
            anyhow::Ok(total)
        }));
    }
    let mut total = 0usize;
    for r in readers {
        total += r.await??;
    }
    let elapsed = start.elapsed().as_secs_f64();
    writers.await??;
    Ok(total as f64 / elapsed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rates_parse_with_their_units_and_bounds() {
        let l: LinkSpec = "1gbit".parse().expect("a rate");
        assert_eq!(l.bits_per_s, 1_000_000_000);
        assert_eq!(l.burst_bytes(), 1_000_000);
        let l: LinkSpec = " 100Mbit".parse().expect("a rate");
        assert_eq!((l.name.as_str(), l.bits_per_s), ("100mbit", 100_000_000));
        assert_eq!(l.burst_bytes(), 256 * 1024);
        for bad in [
            "",
            "gbit",
            "1gb",
            "10kbit",
            "1000gbit",
            "99999999999999999999gbit",
        ] {
            assert!(bad.parse::<LinkSpec>().is_err(), "{bad:?} parsed");
        }
    }
}
