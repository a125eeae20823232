"""Fixtures: a real ``crowdmorph serve`` on a loopback port, the golden files, the test rigs.

The server binary is ``$CROWDMORPH_BIN``, else the newest of ``target/release/crowdmorph`` and
``target/debug/crowdmorph`` in the repository (``cargo build --bin crowdmorph`` makes the
latter; ``cargo test`` does too). Each server listens on port 0 and the test reads the port
from its ``listening`` log line, so runs never collide on a port. The shared test rigs are
``$CROWDMORPH_TEST_DATA``, else ``../shared/data`` beside the checkout, as for the Rust tests.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterator, List, Optional

import pytest

HERE = Path(__file__).resolve().parent
PACKAGE = HERE.parent
REPO = PACKAGE.parent.parent

# The tests run against the package in src/ when it is not installed, so that
# `pytest clients/python/tests` works from a plain checkout too.
try:
    import crowdmorph  # noqa: F401
except ImportError:  # pragma: no cover - depends on how the tests are run
    sys.path.insert(0, str(PACKAGE / "src"))
    import crowdmorph  # noqa: F401

#: The admin token the shared server runs with.
TOKEN = "py-test-token"

# Session streams need the optional websockets package (`pip install 'crowdmorph[sessions]'`);
# without it the tests that open one are skipped, saying so, and the others still run.
try:
    import websockets.sync.client  # noqa: F401

    HAVE_WEBSOCKETS = True
except ImportError:  # pragma: no cover - depends on the machine
    HAVE_WEBSOCKETS = False

#: Marks a test that opens a session stream.
needs_websockets = pytest.mark.skipif(
    not HAVE_WEBSOCKETS,
    reason="websockets (>= 11) is not installed, so session streams cannot be opened: "
    "pip install 'crowdmorph[sessions]' (or /usr/bin/python3 -m pip install "
    "--break-system-packages 'websockets>=11')",
)

PROTO_GOLDEN = REPO / "proto" / "tests" / "golden"
ALIGNED_GOLDEN = REPO / "tests" / "golden" / "crowd_frame_aligned.bin"

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_LISTENING = re.compile(r"listening\s+addr=(\S+)")


def server_binary() -> Path:
    env = os.environ.get("CROWDMORPH_BIN")
    if env:
        path = Path(env)
        if not path.is_file():
            pytest.fail(f"CROWDMORPH_BIN={env} is not a file")
        return path
    found = [
        p
        for p in (
            REPO / "target" / "release" / "crowdmorph",
            REPO / "target" / "debug" / "crowdmorph",
        )
        if p.is_file()
    ]
    if not found:
        pytest.fail(
            "no crowdmorph binary: run `cargo build --bin crowdmorph` (or --release) in "
            f"{REPO}, or set CROWDMORPH_BIN"
        )
    return max(found, key=lambda p: p.stat().st_mtime)


def data_dir() -> Path:
    env = os.environ.get("CROWDMORPH_TEST_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


class Server:
    """A running ``crowdmorph serve``: its ``url``, ``log`` file and process."""

    def __init__(self, proc: subprocess.Popen, url: str, log: Path):
        self.proc = proc
        self.url = url
        self.log = log

    def log_tail(self, lines: int = 40) -> str:
        try:
            text = _ANSI.sub("", self.log.read_text(errors="replace"))
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])


@contextlib.contextmanager
def run_server(*args: str, token: Optional[str] = TOKEN) -> Iterator[Server]:
    """Starts ``crowdmorph serve`` with ``args`` on 127.0.0.1:0 and a fresh data directory,
    waits until it is ready, and stops it afterwards."""
    binary = server_binary()
    with tempfile.TemporaryDirectory(prefix="crowdmorph-py-") as tmp:
        log = Path(tmp) / "server.log"
        cmd: List[str] = [
            str(binary),
            "serve",
            "--addr",
            "127.0.0.1:0",
            "--data-dir",
            str(Path(tmp) / "data"),
            *args,
        ]
        if token is not None:
            cmd += ["--admin-token", token]
        env = dict(os.environ, NO_COLOR="1", RUST_LOG="info", NODEVICE_SELECT="1")
        env.pop("CROWDMORPH_ADMIN_TOKEN", None)
        env.pop("CROWDMORPH_ADDR", None)
        with open(log, "wb") as logf:
            proc = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, env=env)
        try:
            url = _wait_listening(proc, log)
            server = Server(proc, url, log)
            with crowdmorph.Client(url) as c:
                c.wait_ready(timeout=120)
            yield server
        finally:
            _stop(proc)


def _wait_listening(proc: subprocess.Popen, log: Path, timeout: float = 120.0) -> str:
    deadline = time.monotonic() + timeout
    text = ""
    while time.monotonic() < deadline:
        text = _ANSI.sub("", log.read_text(errors="replace"))
        m = _LISTENING.search(text)
        if m:
            return f"http://{m.group(1)}"
        if proc.poll() is not None:
            raise RuntimeError(f"crowdmorph serve exited with {proc.returncode}:\n{text[-3000:]}")
        time.sleep(0.05)
    raise RuntimeError(f"crowdmorph serve did not listen within {timeout} s:\n{text[-3000:]}")


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


# The shared server: an admin token (to test 401s), no background LOD computation (so that
# uploads leave the CPU to the other tests and LOD states are the ones the tests set), and a
# crowd-request deadline of a minute instead of 10 s: `cargo test` runs this suite beside the
# Rust tests, and a busy machine must make the tests slower, not fail them with 504s.
@pytest.fixture(scope="session")
def server() -> Iterator[Server]:
    with run_server("--no-auto-lod", "--request-timeout-ms", "60000") as s:
        yield s


@pytest.fixture
def client(server: Server, request: pytest.FixtureRequest) -> Iterator["crowdmorph.Client"]:
    """An admin client of the shared server; its log is attached to failing tests."""
    request.node._crowdmorph_server = server
    with crowdmorph.Client(server.url, token=TOKEN) as c:
        yield c


@pytest.fixture
def anonymous(server: Server) -> Iterator["crowdmorph.Client"]:
    """A client of the shared server without the admin token."""
    with crowdmorph.Client(server.url) as c:
        yield c


@pytest.fixture(params=["python", "numpy"])
def backend(request: pytest.FixtureRequest) -> str:
    """Both array backends; numpy is skipped (with the reason) where it is not installed."""
    if request.param == "numpy" and not crowdmorph.HAVE_NUMPY:
        pytest.skip("numpy is not installed: only the pure-Python arrays are checked")
    return request.param


@pytest.fixture(scope="session")
def shared_data() -> Path:
    d = data_dir()
    if not d.is_dir():
        pytest.skip(
            f"{d} not found: the shared test rigs are absent (set CROWDMORPH_TEST_DATA to run "
            "the real-rig tests)"
        )
    return d


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> Iterator[None]:
    outcome = yield
    report = outcome.get_result()
    server = getattr(item, "_crowdmorph_server", None)
    if report.failed and server is not None:
        report.sections.append(("crowdmorph serve log (tail)", server.log_tail()))
