#!/usr/bin/env python3
"""The best numpy blend a crowdmorph user could write instead, timed for ``bench cpu --numpy``.

Reads ``weights.npy`` (jobs x T), ``deltas.npy`` (T x 3V, dense) and ``neutral.npy`` (V x 3)
from the folder given, then times, warm, the median of repeated runs of

- ``np.matmul(W, D, out=OUT); OUT += neutral`` into one reused output buffer (issue 13's honest
  baseline), and
- ``W @ D + neutral``, allocating its output each time (what most code does),

and prints one JSON line: ``warm_ms``, ``alloc_ms``, ``blas`` (the BLAS library numpy loaded,
from /proc/self/maps) and ``numpy`` (its version).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from blas_env import blas_library, pin_openblas_core  # noqa: E402  (this script's folder)

pin_openblas_core()

try:
    import numpy as np
except ImportError:
    print(
        "error: the numpy peer needs numpy: apt-get install python3-numpy (or pip install numpy)",
        file=sys.stderr,
    )
    sys.exit(3)


def median_ms(seconds: float, f) -> float:
    f()
    f()
    times = []
    start = time.perf_counter()
    while len(times) < 5 or (time.perf_counter() - start < seconds and len(times) < 1000):
        t = time.perf_counter()
        f()
        times.append((time.perf_counter() - t) * 1e3)
    times.sort()
    return times[len(times) // 2]


def main() -> None:
    folder = Path(sys.argv[1])
    seconds = float(sys.argv[2]) if len(sys.argv) > 2 else 1.0
    w = np.ascontiguousarray(np.load(folder / "weights.npy"), dtype=np.float32)
    d = np.ascontiguousarray(np.load(folder / "deltas.npy"), dtype=np.float32)
    neutral = np.load(folder / "neutral.npy").reshape(-1).astype(np.float32)
    out = np.zeros((w.shape[0], d.shape[1]), dtype=np.float32)

    def warm() -> None:
        np.matmul(w, d, out=out)
        out.__iadd__(neutral)

    def alloc() -> None:
        r = w @ d + neutral
        del r

    warm_ms = median_ms(seconds, warm)
    alloc_ms = median_ms(seconds, alloc)
    print(
        json.dumps(
            {
                "warm_ms": warm_ms,
                "alloc_ms": alloc_ms,
                "blas": blas_library(),
                "numpy": np.__version__,
            }
        )
    )


if __name__ == "__main__":
    main()
