//! The Python client's pytest suite (`clients/python/tests`), run as part of `cargo test`, so
//! that the README's one test command also checks the client against this build's server.
//!
//! It runs `/usr/bin/python3 -m pytest` with the package's `src/` on `PYTHONPATH` (nothing is
//! installed) and `CROWDMORPH_BIN` set to the server binary cargo built for these tests; the
//! suite starts its own `crowdmorph serve` processes on free loopback ports. The suite's output
//! is echoed line by line as it comes (shown with `--nocapture`, and on failure). Without
//! pytest (`build.rs` sets `crowdmorph_python` when `/usr/bin/python3` imports it) the test is
//! listed as ignored with the reason.
//!
//! The suite runs beside the other integration tests (libtest's threads). So that it does not
//! take CPU from the Rust tests that have timeouts of their own (header timeouts, deadlines),
//! pytest and the servers it starts run at a lower priority (nice 10); and the suite is written
//! to be slower, not wrong, when it gets little CPU: its shared server has a one-minute crowd
//! deadline and its session tests read ticks until what they check has happened, never within
//! a time.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex, mpsc};
use std::time::{Duration, Instant};

/// The suite takes 30–60 s on the 2-core dev VM; a hung server or test must not hang CI.
const LIMIT: Duration = Duration::from_secs(15 * 60);

#[test]
#[cfg_attr(
    not(crowdmorph_python),
    ignore = "needs python3 with pytest: apt-get install python3-pytest python3-numpy"
)]
fn the_python_clients_pytest_suite_passes_against_this_server() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let src = root.join("clients/python/src");
    let python_path = match std::env::var_os("PYTHONPATH").filter(|p| !p.is_empty()) {
        Some(rest) => {
            let mut paths = vec![src.clone()];
            paths.extend(std::env::split_paths(&rest));
            std::env::join_paths(paths).expect("PYTHONPATH entries without separators")
        }
        None => src.clone().into_os_string(),
    };
    // One pipe for stdout and stderr, so that the lines keep their order.
    let (reader, writer) = std::io::pipe().expect("a pipe");
    let mut command = Command::new("/usr/bin/python3");
    command
        .args([
            "-m",
            "pytest",
            "-p",
            "no:cacheprovider",
            "-q",
            "-rs",
            "clients/python/tests",
        ])
        .current_dir(root)
        .env("PYTHONPATH", python_path)
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .env("CROWDMORPH_BIN", env!("CARGO_BIN_EXE_crowdmorph"))
        .stdin(Stdio::null())
        .stdout(writer.try_clone().expect("a second pipe writer"))
        .stderr(writer);
    lower_priority(&mut command);
    let mut child = command
        .spawn()
        .expect("/usr/bin/python3 starts (build.rs found it)");
    // The command holds this side's pipe writers: dropped, the reader ends when pytest (the
    // only other holder) exits. Lines are printed from a spawned thread, which inherits
    // libtest's output capture.
    drop(command);
    let tail = Arc::new(Mutex::new(VecDeque::new()));
    let (done, echoed) = mpsc::channel::<()>();
    let lines = Arc::clone(&tail);
    std::thread::spawn(move || {
        for line in BufReader::new(reader).lines() {
            let Ok(line) = line else { break };
            println!("{line}");
            if let Ok(mut t) = lines.lock() {
                t.push_back(line);
                if t.len() > 40 {
                    t.pop_front();
                }
            }
        }
        let _ = done.send(());
    });
    let started = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().expect("wait for pytest") {
            break status;
        }
        if started.elapsed() > LIMIT {
            stop(&mut child);
            panic!("pytest ran over {} s and was stopped", LIMIT.as_secs());
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    // The last lines, unless something pytest started still holds the pipe open.
    let _ = echoed.recv_timeout(Duration::from_secs(30));
    let tail: Vec<String> = tail
        .lock()
        .map(|t| t.iter().cloned().collect())
        .unwrap_or_default();
    assert!(
        status.success(),
        "pytest failed ({status}); its last lines:\n{}",
        tail.join("\n")
    );
}

/// Makes the command run at nice 10 (its children inherit it): on a busy machine the Rust tests
/// beside it get the CPU first.
fn lower_priority(command: &mut Command) {
    #[cfg(unix)]
    {
        use std::os::unix::process::CommandExt;
        // SAFETY: the closure runs in the forked child before exec and only makes one system
        // call, setpriority(2), which is async-signal-safe; it touches no memory of the parent.
        unsafe {
            command.pre_exec(|| {
                // Best effort: a failure (a sandbox that forbids it) leaves the priority as is.
                let _ = libc::setpriority(libc::PRIO_PROCESS, 0, 10);
                Ok(())
            });
        }
    }
    #[cfg(not(unix))]
    let _ = command;
}

/// Stops a pytest that ran too long: first an interrupt, which pytest turns into
/// `KeyboardInterrupt` so that its fixtures stop the servers they started, then a kill.
fn stop(child: &mut Child) {
    #[cfg(unix)]
    {
        if let Ok(pid) = libc::pid_t::try_from(child.id()) {
            // SAFETY: kill(2) has no memory effects; `pid` is our child, not yet reaped (we
            // hold its `Child` and have not waited for it), so it names no other process.
            unsafe {
                libc::kill(pid, libc::SIGINT);
            }
        }
        let asked = Instant::now();
        while asked.elapsed() < Duration::from_secs(30) {
            if let Ok(Some(_)) = child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }
    let _ = child.kill();
    let _ = child.wait();
}
