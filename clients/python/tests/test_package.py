"""The package as ``pip install ./clients/python`` would build it: every module in the wheel.

The suite itself imports the package from ``src/``, so a module that the packaging leaves out
would pass every other test; this builds the wheel through setuptools' PEP 517 hooks (what pip
calls, offline) from a copy of the package, and imports the client from the wheel alone.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile

import pytest

from conftest import PACKAGE


def test_the_wheel_holds_every_module_and_imports_on_its_own(tmp_path):
    try:
        import setuptools  # noqa: F401
        import wheel  # noqa: F401
    except ImportError:
        pytest.skip("setuptools and wheel are needed to build the package (python3-setuptools)")
    src = tmp_path / "pkg"
    # A copy: setuptools writes build/ and *.egg-info next to the sources.
    shutil.copytree(PACKAGE, src, ignore=shutil.ignore_patterns("tests", "__pycache__", "build", "*.egg-info"))
    out = tmp_path / "dist"
    out.mkdir()
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
    env.pop("PYTHONPATH", None)
    built = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys; from setuptools import build_meta as b; print(b.build_wheel(sys.argv[1]))",
            str(out),
        ],
        cwd=src,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert built.returncode == 0, built.stderr[-3000:]
    name = built.stdout.strip().splitlines()[-1]
    assert name.startswith("crowdmorph-0.1.0-") and name.endswith(".whl")
    wheel_path = out / name
    modules = {p.name for p in (PACKAGE / "src" / "crowdmorph").glob("*.py")}
    with zipfile.ZipFile(wheel_path) as z:
        packaged = {n.split("/", 1)[1] for n in z.namelist() if n.startswith("crowdmorph/")}
    assert modules <= packaged, modules - packaged
    # Imported from the wheel alone (a pure-Python wheel is importable as a zip).
    env["PYTHONPATH"] = str(wheel_path)
    probe = subprocess.run(
        [
            sys.executable,
            "-c",
            "import crowdmorph; print(crowdmorph.__file__); "
            "print(crowdmorph.Client.stream.__name__, crowdmorph.StreamClosed.__name__)",
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert probe.returncode == 0, probe.stderr[-3000:]
    where, names = probe.stdout.strip().splitlines()
    assert where.startswith(str(wheel_path)) and names == "stream StreamClosed"
