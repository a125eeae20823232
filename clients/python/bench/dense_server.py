#!/usr/bin/env python3
"""The best plain Python server a crowdmorph user could write instead: aiohttp + numpy, dense.

This is the peer that ``crowdmorph bench http --python-peer`` measures crowdmorph against
(issue 12: "at least 3x a Python server, aiohttp + numpy dense, same request"), so it is written
to be fast, not to lose:

- the rig is loaded once from the ``.npy`` export the bench writes (``manifest.json``, the
  neutral ``V x 3`` positions, the deltas as one dense ``T x 3V`` float32 matrix, each clip's
  weight table as ``frames x T`` rows, and a ``levels x T`` mask of the shapes each LOD keeps);
- ``POST /v1/crowd/frame`` takes and returns the same bincode bytes as crowdmorph (the request
  is decoded and the response framed with the ``crowdmorph`` client package's wire module), so
  the bench drives it with the same client, request bodies and connections;
- identical heads (rig, clip, frame after wrapping, LOD) are computed once;
- the blend is one ``np.matmul(W, D, out=OUT[:u])`` and ``OUT[:u] += neutral`` into a warm
  buffer taken from a pool (one per request in flight, reused, never freed), by OpenBLAS on
  every core, off the event loop (``--compute thread``, the default, measured faster here than
  ``--compute inline``), with OpenBLAS's kernels chosen from the CPU's flags (``blas_env.py``:
  Debian's OpenBLAS 0.3.21 takes the dev VM's Xeon for a Prescott and runs SSE3 kernels);
- the payloads are written to the socket straight from that buffer (asyncio copies only what
  the kernel does not take at once), with the bincode framing around them; f16 is converted
  into a second warm buffer.

Not supported (400 ``unsupported``): normals, q16, and LOD levels on simplified meshes. The
process prints ``port N`` on stdout once it listens (``--port 0`` picks a free port).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from blas_env import blas_library, pin_openblas_core  # noqa: E402  (this script's folder)

pin_openblas_core()

try:
    import numpy as np
except ImportError:
    print(
        "error: the Python peer needs numpy: apt-get install python3-numpy (or pip install numpy)",
        file=sys.stderr,
    )
    sys.exit(3)
try:
    from aiohttp import web
except ImportError:
    print(
        "error: the Python peer needs aiohttp: apt-get install python3-aiohttp "
        "(or pip install aiohttp)",
        file=sys.stderr,
    )
    sys.exit(3)

# The client package sits beside this folder (clients/python/src), in a checkout and in the
# copy the bench writes to a temporary directory.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from crowdmorph.messages import CrowdFrameRequest  # noqa: E402
from crowdmorph.wire import DecodeError, Writer, decode  # noqa: E402

FORMATS = ("f32", "f16", "q16")


def error(status: int, code: str, message: str) -> web.Response:
    """crowdmorph's error body, so that the bench's client reads it the same way."""
    return web.json_response({"error": {"code": code, "message": message}}, status=status)


class Rig:
    """The exported rig: dense deltas, neutral, clip tables, LOD masks."""

    def __init__(self, folder: Path):
        manifest = json.loads((folder / "manifest.json").read_text())
        self.id = manifest["rig"]
        self.vertices = int(manifest["vertices"])
        self.targets = int(manifest["targets"])
        self.neutral = np.load(folder / manifest["neutral"]).reshape(-1)
        self.deltas = np.ascontiguousarray(np.load(folder / manifest["deltas"]))
        self.clips = {}
        for c in manifest["clips"]:
            table = np.ascontiguousarray(np.load(folder / c["file"]), dtype=np.float32)
            self.clips[c["name"]] = table
        masks = np.load(folder / manifest["lod_masks"])
        # LOD levels on simplified meshes are not served (None); a level whose mask keeps every
        # shape needs no multiply (None as the mask).
        self.lods = []
        for level, mesh in enumerate(manifest["lod_mesh"]):
            if mesh:
                self.lods.append(("mesh", None))
            elif bool(np.all(masks[level] == 1.0)):
                self.lods.append(("full", None))
            else:
                self.lods.append(("shapes", masks[level].astype(np.float32)))
        n3 = 3 * self.vertices
        if self.neutral.shape != (n3,) or self.deltas.shape != (self.targets, n3):
            raise ValueError(
                f"export shapes differ: neutral {self.neutral.shape}, deltas {self.deltas.shape}"
            )


class Pool:
    """Warm output buffers, one per request in flight, reused and never freed."""

    def __init__(self, n3: int):
        self.n3 = n3
        self.free: list = []

    def take(self, rows: int):
        while self.free:
            f32, f16 = self.free.pop()
            if f32.shape[0] >= rows:
                return f32, f16
        # Rows rounded up so that the pool does not grow a buffer for every size it meets.
        rows = max(rows, 128)
        f32 = np.zeros((rows, self.n3), dtype=np.float32)
        f16 = np.zeros((rows, self.n3), dtype=np.float16)
        return f32, f16

    def give(self, bufs) -> None:
        self.free.append(bufs)


def blend(rig: Rig, w, out) -> None:
    """``out = W · D + neutral``, in place (the numpy a user would write, warm)."""
    np.matmul(w, rig.deltas, out=out)
    out += rig.neutral


def make_app(rig: Rig, compute: str) -> web.Application:
    pool = Pool(3 * rig.vertices)
    executor = ThreadPoolExecutor(max_workers=os.cpu_count() or 2)
    rig_str = Writer()
    rig_str.string(rig.id)
    rig_bytes = bytes(rig_str.out)
    clip_bytes = {}
    for name in rig.clips:
        w = Writer()
        w.string(name)
        clip_bytes[name] = bytes(w.out)

    async def crowd_frame(request: web.Request) -> web.StreamResponse:
        t0 = time.perf_counter()
        if request.content_type != "application/x-bincode":
            return error(415, "unsupported_media_type", "this peer reads bincode only")
        body = await request.read()
        try:
            req = decode(CrowdFrameRequest, body)
        except (DecodeError, ValueError) as e:
            return error(400, "malformed_bincode", str(e))
        fmt = req.output.format
        if req.output.normals or fmt == "q16":
            return error(400, "unsupported", "this peer serves f32 and f16 positions only")
        # Dedupe: one job per (rig, clip, frame after wrapping, LOD), in first-seen order.
        jobs: dict = {}
        order = []
        head_buffer = []
        for h in req.heads:
            if h.rig != rig.id:
                return error(404, "unknown_rig", f"no rig {h.rig!r} (rigs: {rig.id})")
            table = rig.clips.get(h.clip)
            if table is None:
                return error(404, "unknown_clip", f"no clip {h.clip!r}")
            frames = table.shape[0]
            if req.wrap:
                frame = h.frame % frames
            elif 0 <= h.frame < frames:
                frame = h.frame
            else:
                return error(400, "frame_out_of_range", f"frame {h.frame} of {frames}")
            if not 0 <= h.lod < len(rig.lods) or rig.lods[h.lod][0] == "mesh":
                return error(400, "lod_out_of_range", f"LOD {h.lod} is not served here")
            key = (h.clip, frame, h.lod)
            j = jobs.get(key)
            if j is None:
                j = jobs[key] = len(order)
                order.append(key)
            head_buffer.append((h.head, j))
        u = len(order)
        f32, f16 = pool.take(u)
        try:
            w = np.empty((u, rig.targets), dtype=np.float32)
            for i, (clip, frame, lod) in enumerate(order):
                w[i] = rig.clips[clip][frame]
                mask = rig.lods[lod][1]
                if mask is not None:
                    w[i] *= mask
            out = f32[:u]
            t1 = time.perf_counter()
            if compute == "thread":
                await asyncio.get_running_loop().run_in_executor(executor, blend, rig, w, out)
            else:
                blend(rig, w, out)
            if fmt == "f16":
                out16 = f16[:u]
                np.copyto(out16, out, casting="same_kind")
                out = out16
            t2 = time.perf_counter()
            return await respond(request, req, fmt, order, head_buffer, out, t0, t1, t2)
        finally:
            pool.give((f32, f16))

    async def respond(request, req, fmt, order, head_buffer, out, t0, t1, t2):
        """The bincode ``CrowdFrameResponse``, each payload written from the warm buffer and
        aligned to 16 bytes from the start of the body, as crowdmorph aligns it."""
        payload = out.shape[1] * out.itemsize
        chunks = []
        head = Writer()
        head.varint(FORMATS.index(fmt))
        head.bool(False)
        head.varint(len(order))
        offset = 0
        for i, (clip, frame, lod) in enumerate(order):
            head.out += rig_bytes
            head.out += clip_bytes[clip]
            head.u32(frame)
            head.u32(lod)
            head.u32(rig.vertices)
            head.out.append(0)  # No quantization.
            # Blob: pad bytes (so that the data starts 16-aligned), then the data's length.
            length = Writer()
            length.varint(payload)
            at = offset + len(head.out) + 1 + len(length.out)
            pad = (-at) % 16
            head.out.append(pad)
            head.out += bytes(pad)
            head.out += length.out
            chunks.append(bytes(head.out))
            offset += len(head.out)
            chunks.append(memoryview(out[i]).cast("B"))
            offset += payload
            head = Writer()
            head.out.append(0)  # No normals.
        head.varint(len(head_buffer))
        for hid, j in head_buffer:
            head.varint(hid)
            head.varint(j)
        t3 = time.perf_counter()
        us = lambda s: int(s * 1e6)  # noqa: E731
        head.varint(us(t1 - t0))  # queue_us: decode and gather.
        head.varint(us(t2 - t1))  # compute_us.
        head.varint(us(t3 - t0))  # total_us.
        head.out.append(0)  # gpu_us: None.
        chunks.append(bytes(head.out))
        offset += len(head.out)
        resp = web.StreamResponse(status=200)
        resp.content_type = "application/x-bincode"
        resp.content_length = offset
        await resp.prepare(request)
        for c in chunks:
            await resp.write(c)
        await resp.write_eof()
        return resp

    async def healthz(_request: web.Request) -> web.Response:
        return web.json_response({"status": "ok"})

    app = web.Application(client_max_size=64 << 20)
    app.router.add_post("/v1/crowd/frame", crowd_frame)
    app.router.add_get("/healthz", healthz)
    return app


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rig", type=Path, help="folder of the rig's .npy export")
    parser.add_argument("--port", type=int, default=0)
    parser.add_argument("--compute", choices=("thread", "inline"), default="thread")
    args = parser.parse_args()
    rig = Rig(args.rig)
    # Warm the BLAS threads and the first pool buffer before anyone measures.
    blend(rig, np.zeros((1, rig.targets), dtype=np.float32), np.empty((1, 3 * rig.vertices), np.float32))
    runner = web.AppRunner(make_app(rig, args.compute), access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", args.port)
    await site.start()
    port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
    # The bench reads this line: the port, then what numpy computes with.
    print(f"port {port} numpy {np.__version__} blas {blas_library()}", flush=True)
    await asyncio.Event().wait()


if __name__ == "__main__":
    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        pass
