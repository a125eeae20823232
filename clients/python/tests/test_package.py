"""The package as ``pip install ./clients/python`` would build it: every module in the wheel.

The suite itself imports the package from ``src/``, so a module that the packaging leaves out
would pass every other test; this builds the wheel through setuptools' PEP 517 hooks (what pip
calls, offline) from a copy of the package, and imports the client from the wheel alone.
"""

from __future__ import annotations

import ast
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
    # websockets is the `sessions` extra, not a dependency: the core is standard library only.
    with zipfile.ZipFile(wheel_path) as z:
        meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        fields = z.read(meta).decode("utf-8").split("\n\n", 1)[0].splitlines()
    assert "Provides-Extra: sessions" in fields
    requires = [f for f in fields if f.startswith("Requires-Dist:")]
    # (setuptools releases spell it `websockets>=11; extra == "sessions"` or
    # `websockets (>=11) ; extra == 'sessions'`.)
    ws = [r for r in requires if "websockets" in r]
    assert len(ws) == 1 and ">=11" in ws[0], requires
    assert "sessions" in ws[0].partition(";")[2], requires
    assert all("extra ==" in r for r in requires), requires
    # Imported from the wheel alone (a pure-Python wheel is importable as a zip).
    env["PYTHONPATH"] = str(wheel_path)
    probe = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys, crowdmorph; print(crowdmorph.__file__); "
            "print(crowdmorph.Client.stream.__name__, crowdmorph.StreamClosed.__name__); "
            "print('websockets' in sys.modules)",
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert probe.returncode == 0, probe.stderr[-3000:]
    where, names, websockets_imported = probe.stdout.strip().splitlines()
    assert where.startswith(str(wheel_path)) and names == "stream StreamClosed"
    # Only opening a stream imports websockets.
    assert websockets_imported == "False"


def _package_imports():
    """Module name -> the package's modules it imports (any import statement, at any depth)."""
    folder = PACKAGE / "src" / "crowdmorph"
    names = {p.stem for p in folder.glob("*.py")}
    graph = {}
    for path in folder.glob("*.py"):
        deps = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level:
                if node.module:
                    deps.add(node.module.split(".")[0])
                else:
                    deps.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("crowdmorph"):
                deps.add((node.module.split(".") + ["__init__"])[1])
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] == "crowdmorph":
                        deps.add((a.name.split(".") + ["__init__"])[1])
        graph[path.stem] = (deps & names) - {path.stem}
    return graph


def test_the_modules_import_one_way():
    # No cycle: every module can be imported (and read) without the ones above it.
    graph = _package_imports()
    done, path = set(), []

    def visit(m):
        assert m not in path, f"import cycle: {' -> '.join(path[path.index(m):] + [m])}"
        if m in done:
            return
        path.append(m)
        for d in sorted(graph[m]):
            visit(d)
        path.pop()
        done.add(m)

    for m in sorted(graph):
        visit(m)
    # The results both the HTTP client and the viewers make sit below both.
    assert "results" in graph["sessions"] and "client" not in graph["sessions"]
