"""Bytes per head: HTTP crowd frames and session streams, embedded head and ICT driven by the
embedded head's clips exported as ARKit-named CSV."""
import tempfile, json, os, socket, subprocess, sys, time, urllib.request, glob
# Usage: bytes_per_head.py CROWDMORPH_BIN [CLIPS_DIR]: CLIPS_DIR holds the embedded head's clips as
# ARKit-named CSV (idle, talk, smile, surprise), see docs/perf/2026-12-02-bytes-per-head.md.
import websockets.sync.client as wsc
BIN = sys.argv[1]
CLIPS = sys.argv[2] if len(sys.argv) > 2 else "/tmp/export"
def free_port():
    s = socket.socket(); s.bind(("127.0.0.1", 0)); p = s.getsockname()[1]; s.close(); return p
port = free_port()
srv = subprocess.Popen([BIN, "serve", "--addr", f"127.0.0.1:{port}", "--data-dir", tempfile.mkdtemp()],
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
base = f"http://127.0.0.1:{port}"
for _ in range(200):
    try:
        urllib.request.urlopen(base + "/readyz"); break
    except Exception: time.sleep(0.1)
def req(method, path, body=None, ctype="application/json", headers=None):
    r = urllib.request.Request(base + path, data=body, method=method, headers={"Content-Type": ctype, **(headers or {})})
    with urllib.request.urlopen(r) as resp:
        return resp.read(), resp.headers
clips = ["idle", "talk", "smile", "surprise"]
rigs = ["default-head"]
ict = os.path.join(os.path.dirname(__file__), "../../../../shared/data/ict-facekit/ict_facekit_53.glb")
if os.path.exists(ict):
    req("POST", "/v1/rigs?name=ict", open(ict, "rb").read(), "model/gltf-binary")
    for c in clips:
        b, _ = req("POST", f"/v1/rigs/ict/clips?name={c}&fps=30&ignore_unknown=true", open(f"{CLIPS}/{c}.csv", "rb").read(), "text/csv")
        info = json.loads(b)
    rigs.append("ict")
    print("ict clips:", [ (c["name"], c["frames"]) for c in json.loads(req("GET", "/v1/rigs/ict/clips")[0])["clips"]], "ignored:", info.get("ignored"))
N = 24
out = {}
for rig in rigs:
    # HTTP: crowd frames of N unique heads, per format and encoding.
    heads = [{"head": i, "rig": rig, "clip": clips[i % 4], "frame": (i * 7) % 75} for i in range(N)]
    for fmt in ["f32", "q16", "q16r"]:
        for enc in [None, "gzip", "zstd"]:
            body = json.dumps({"heads": heads, "output": {"format": fmt}}).encode()
            h = {"Accept": "application/x-bincode"}
            if enc: h["Accept-Encoding"] = enc
            r = urllib.request.Request(base + "/v1/crowd/frame", data=body, method="POST", headers={"Content-Type": "application/json", **h})
            with urllib.request.urlopen(r) as resp:
                n = len(resp.read())
            out[(rig, "http", fmt, enc)] = n / N
    # Sessions: N heads at 30 ticks/s, one viewer per mode, 60 messages each.
    sess = json.loads(req("POST", "/v1/sessions", json.dumps({"fps": 30, "heads": [
        {"head": i, "rig": rig, "clip": clips[i % 4], "offset": i * 7} for i in range(N)]}).encode())[0])
    modes = {"f32": {"format": "f32"}, "q16": {"format": "q16"},
             "q16+zstd": {"format": "q16", "compression": "zstd"},
             "temporal": {"format": "q16", "temporal": True},
             "temporal+zstd": {"format": "q16", "temporal": True, "compression": "zstd"},
             "temporal+deflate": {"format": "q16", "temporal": True, "compression": "deflate"}}
    for name, hello in modes.items():
        ws = wsc.connect(f"ws://127.0.0.1:{port}/v1/sessions/{sess['id']}/stream", max_size=None)  # noqa
        ws.send(json.dumps(hello))
        total = 0; ticks = []
        for k in range(70):
            m = ws.recv()
            if k >= 10:  # past the join keyframes
                total += len(m)
        ws.close()
        out[(rig, "session", name, None)] = total / 60 / N
    req("DELETE", f"/v1/sessions/{sess['id']}")
srv.terminate()
for rig in rigs:
    q = out[(rig, "http", "q16", None)]
    print(f"\n{rig} HTTP bytes/head (x fewer than q16):")
    for fmt in ["f32", "q16", "q16r"]:
        print("  ", fmt, "  ".join(f"{enc or 'plain'} {out[(rig,'http',fmt,enc)]:,.0f} ({q/out[(rig,'http',fmt,enc)]:.2f}x)" for enc in [None, "gzip", "zstd"]))
    q = out[(rig, "session", "q16", None)]
    print(f"{rig} session bytes/head/tick (x fewer than q16):")
    for name in ["f32", "q16", "q16+zstd", "temporal", "temporal+zstd", "temporal+deflate"]:
        v = out[(rig, "session", name, None)]
        print(f"   {name:18} {v:,.0f} ({q/v:.2f}x)")
