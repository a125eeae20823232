"""Crowd sessions against a real ``crowdmorph serve``: the REST calls and the stream viewer.

Viewers here are :class:`crowdmorph.Viewer` objects (over the ``websockets`` package's client),
and the tests check what a viewer ends up drawing (each head's positions after "unchanged" and
layouts are applied), against the server's ``/v1/crowd/frame`` for the same frames, and how
the stream's closes, limits and timeouts reach the caller. The tests that open a stream are
skipped, with the reason, where websockets is not installed; the REST ones run everywhere.
"""

from __future__ import annotations

import json
import math
import sys
import time
from typing import Dict, Iterator, List

import pytest

import crowdmorph
from crowdmorph import HEAD_UNCHANGED, SessionHead, as_dict
from _util import flat, norm_floats
from conftest import needs_websockets

RIG = "default-head"


@pytest.fixture
def sessions(client) -> Iterator[List[str]]:
    """Ids of sessions a test made; deleted afterwards so that the shared server's session
    limit is never reached."""
    made: List[str] = []
    yield made
    for sid in made:
        try:
            client.delete_session(sid)
        except crowdmorph.NotFound:
            pass


def _create(client, made: List[str], heads, **kw) -> crowdmorph.SessionInfo:
    info = client.create_session(heads, idle_timeout_s=kw.pop("idle_timeout_s", 5), **kw)
    made.append(info.id)
    return info


def test_clip_less_alive_heads_and_the_sessions_liveliness(client, sessions):
    # An empty clip is the rig's neutral; `alive` rides on heads, the session and patches.
    info = _create(
        client,
        sessions,
        [
            {"head": 1, "rig": RIG, "alive": {"blink": True, "seed": 3}},
            crowdmorph.SessionHead(2, RIG, alive=crowdmorph.Alive(saccades=True)),
            (3, RIG, ""),
        ],
        alive={"breathing": True, "look_at": [0.0, 1.5, 4.0]},
    )
    assert [h.clip for h in info.heads] == ["", "", ""]
    assert info.heads[0].alive == crowdmorph.Alive(blink=True, seed=3)
    assert info.heads[1].alive == crowdmorph.Alive(saccades=True)
    assert info.heads[2].alive is None
    assert info.alive == crowdmorph.Alive(breathing=True, look_at=[0.0, 1.5, 4.0])
    moved = client.patch_session(info.id, alive={"look_at": [1.0, 1.5, 4.0]})
    assert moved.alive == crowdmorph.Alive(look_at=[1.0, 1.5, 4.0])
    assert moved.heads == info.heads
    with pytest.raises(crowdmorph.BadRequest) as e:
        client.patch_session(info.id, alive={"look_at": [1e30, 0.0, 0.0]})
    assert e.value.code == "invalid_alive"


def _frame_at(tick: int, offset: int, clip_fps: float, session_fps: float) -> int:
    """proto/README.md: at tick t a head plays offset + floor((t - 1) × clip_fps / fps)."""
    return offset + math.floor((tick - 1) * clip_fps / session_fps)


def test_sessions_are_created_listed_patched_and_deleted(client, anonymous, sessions):
    forms = [
        SessionHead(1, RIG, "talk"),
        {"head": 2, "rig": RIG, "clip": "smile", "offset": 7, "position": [1, 0, 0]},
        (3, RIG, "idle", -2, [2.0, 0.0, 0.5], 45.0, 1.5),
    ]
    info = _create(client, sessions, forms, fps=12.5, wrap=False, idle_timeout_s=7)
    assert (info.fps, info.wrap, info.idle_timeout_s, info.viewers) == (12.5, False, 7, 0)
    assert [h.head for h in info.heads] == [1, 2, 3]
    assert info.heads[1] == SessionHead(2, RIG, "smile", 7, [1.0, 0.0, 0.0], 0.0, 1.0)
    assert info.heads[2] == SessionHead(3, RIG, "idle", -2, [2.0, 0.0, 0.5], 45.0, 1.5)
    # Reading needs no token; the clock runs (tick) with or without viewers.
    got = anonymous.session(info.id)
    assert (got.id, got.fps, got.heads, got.viewers) == (info.id, info.fps, info.heads, 0)
    assert info.id in [s.id for s in anonymous.sessions()]

    patched = client.patch_session(
        info.id,
        remove=[1],
        change=[crowdmorph.HeadChange(2, clip="surprise"), {"head": 3, "yaw": 90}],
        add=[(9, RIG, "talk", 4)],
    )
    assert [(h.head, h.clip, h.yaw) for h in patched.heads] == [
        (2, "surprise", 0.0),
        (3, "idle", 90.0),
        (9, "talk", 0.0),
    ]

    # Refusals are the server's typed errors.
    with pytest.raises(crowdmorph.Unauthorized) as e:
        anonymous.create_session([(1, RIG, "talk")])
    assert e.value.code == "token_required"
    with pytest.raises(crowdmorph.Conflict) as e:
        client.patch_session(info.id, add=[(2, RIG, "talk")])
    assert e.value.code == "head_exists"
    with pytest.raises(crowdmorph.NotFound) as e:
        client.patch_session(info.id, remove=[77])
    assert e.value.code == "unknown_head"
    with pytest.raises(crowdmorph.BadRequest) as e:
        client.create_session([(1, RIG, "talk")], fps=500)
    assert e.value.code == "invalid_session" and "fps" in e.value.message

    client.delete_session(info.id)
    for call in (client.session, client.delete_session):
        with pytest.raises(crowdmorph.NotFound) as e:
            call(info.id)
        assert e.value.code == "unknown_session"


def test_a_session_gets_the_clients_id_once(client, sessions):
    # PUT /v1/sessions/{id}: what a load balancer hashing on the id needs.
    info = _create(client, sessions, [(1, RIG, "talk")], id="py-lobby.7")
    assert info.id == "py-lobby.7"
    assert client.session("py-lobby.7").heads[0].clip == "talk"
    with pytest.raises(crowdmorph.Conflict) as e:
        client.create_session([(1, RIG, "idle")], id="py-lobby.7")
    assert e.value.code == "session_exists" and "py-lobby.7" in e.value.message
    assert client.session("py-lobby.7").heads[0].clip == "talk", "not replaced"
    with pytest.raises(crowdmorph.BadRequest) as e:
        client.create_session([(1, RIG, "talk")], id="no spaces")
    assert e.value.code == "invalid_session"


def test_crowd_requests_carry_their_first_heads_rig_as_a_routing_hint():
    from crowdmorph.client import _rig_hint

    assert _rig_hint([]) == ""
    assert _rig_hint([(1, "ict face", "talk", 0)]) == "?rig=ict%20face"
    assert _rig_hint([{"head": 1, "rig": RIG, "clip": "talk"}]) == f"?rig={RIG}"
    assert _rig_hint([crowdmorph.Head(1, RIG, "talk", 3)]) == f"?rig={RIG}"


@needs_websockets
def test_a_stream_of_an_unknown_session_raises_the_servers_404(client, sessions):
    info = _create(client, sessions, [(1, RIG, "talk")])
    client.delete_session(info.id)
    # The refused handshake's JSON error body, as for every other call.
    with pytest.raises(crowdmorph.NotFound) as e:
        client.stream(info.id)
    assert e.value.code == "unknown_session" and info.id in e.value.message


def test_without_websockets_a_stream_says_what_to_install(monkeypatch):
    # None in sys.modules makes `import websockets` fail, as on a machine without it; the
    # error comes before any connection, and the rest of the package needs nothing.
    for name in [m for m in sys.modules if m == "websockets" or m.startswith("websockets.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "websockets", None)
    with crowdmorph.Client("http://127.0.0.1:9") as c:
        with pytest.raises(ImportError) as e:
            c.stream("s1")
    assert "pip install 'crowdmorph[sessions]'" in str(e.value)
    assert "websockets>=11" in str(e.value)


def test_session_messages_decode_to_the_servers_json(client, sessions):
    # The server's JSON of the same session is an independent encoding of every field.
    info = _create(client, sessions, [(5, RIG, "smile", -3, [0.5, -1, 2], 30.0, 0.75)], fps=7)
    patch = crowdmorph.SessionPatch(
        remove=[5], add=[SessionHead(6, RIG, "talk", 2**40, [1, 2, 3], -10.0, 2.0)]
    )
    resp = client.request(
        "PATCH",
        f"/v1/sessions/{info.id}",
        crowdmorph.encode(patch),
        crowdmorph.BINCODE,
        accept="application/json",
    )
    got = json.loads(resp.body)
    del got["tick"], got["stats"]  # they move with the clock
    mine = as_dict(client.session(info.id))
    del mine["tick"], mine["stats"]
    assert norm_floats(mine) == norm_floats(got)
    assert got["heads"] == [
        {
            "head": 6,
            "rig": RIG,
            "clip": "talk",
            "offset": 2**40,
            "position": [1.0, 2.0, 3.0],
            "yaw": -10.0,
            "scale": 2.0,
            "graph": None,
            "joints": {},
            "layers": [],
            "clamp": None,
            "live": None,
            "alive": None,
        }
    ]
    listed = json.loads(client.request("GET", "/v1/sessions", accept="application/json").body)
    assert [s["id"] for s in listed["sessions"]] == [s.id for s in client.sessions()]


@needs_websockets
def test_two_viewers_get_identical_vertices_for_clones(client, sessions):
    # Heads 1 and 2, 3 and 4 are clones (same clip and offset) at different places; two
    # viewers with different cameras draw the same vertices at every tick both received.
    heads = [
        (1, RIG, "talk", 0, [0, 0, 0]),
        (2, RIG, "talk", 0, [1, 0, 0]),
        (3, RIG, "smile", 7, [2, 0, 0]),
        (4, RIG, "smile", 7, [3, 0, 0]),
        (5, RIG, "talk", 3, [4, 0, 0]),
    ]
    info = _create(client, sessions, heads, fps=20)
    cam_a = {"position": [0, 0, 5], "target": [0, 0, 0]}
    cam_b = {"position": [8, 3, -4], "target": [2, 0, 0], "fov_y": 50}
    seen: List[Dict[int, Dict[int, List[float]]]] = [{}, {}]
    a = client.stream(info.id, format="f32", camera=cam_a)
    b = client.stream(info.id, format="f32", camera=cam_b)
    # A loaded machine skips ticks, and a slow viewer gets the newest: read until both
    # viewers have seen a few of the same ticks.
    common: List[int] = []
    with a, b:
        for _ in range(60):
            for k, viewer in enumerate((a, b)):
                t = next(viewer)
                assert t.heads == [1, 2, 3, 4, 5]
                assert set(t.positions) == {1, 2, 3, 4, 5}
                # Clones share one decoded array.
                assert t.positions[1] is t.positions[2]
                assert t.positions[3] is t.positions[4]
                seen[k][t.tick] = {h: flat(p) for h, p in t.positions.items()}
            common = sorted(set(seen[0]) & set(seen[1]))
            if len(common) >= 4:
                break
    assert len(common) >= 4, (sorted(seen[0]), sorted(seen[1]))
    for tick in common:
        assert seen[0][tick] == seen[1][tick], f"tick {tick}"
    last = seen[0][common[-1]]
    assert last[1] == last[2] and last[3] == last[4]
    assert last[1] != last[5], "offset 3 plays another frame"


@needs_websockets
@pytest.mark.parametrize("fmt, normals", [("f32", False), ("q16", True), ("f16", False)])
def test_the_decoded_vertices_equal_a_crowd_frame_of_the_same_frame(
    client, sessions, backend, fmt, normals
):
    c = crowdmorph.Client(client.url, token=client.token, arrays=backend)
    clips = {x.name: x for x in c.clips(RIG)}
    fps = 24.0
    heads = [(1, RIG, "talk", 0), (2, RIG, "smile", 11), (3, RIG, "surprise", -5)]
    info = _create(c, sessions, heads, fps=fps)
    with c.stream(info.id, format=fmt, normals=normals) as viewer:
        ticks = [next(viewer) for _ in range(3)]
    for t in ticks:
        assert t.format == fmt and t.normals_included is normals
        want = [
            (hid, RIG, clip, _frame_at(t.tick, offset, clips[clip].fps, info.fps))
            for hid, _, clip, offset in heads
        ]
        frame = c.crowd_frame(want, format=fmt, normals=normals)
        for i, (hid, _, clip, f) in enumerate(want):
            buf = t.buffers[hid]
            assert (buf.clip, buf.frame) == (clip, f % clips[clip].frames), (t.tick, hid)
            assert flat(t.positions[hid]) == flat(frame.positions(i)), (t.tick, hid)
            if normals:
                assert flat(t.normals[hid]) == flat(frame.buffer(i).normals)
            else:
                assert t.normals == {}


@needs_websockets
def test_unchanged_heads_keep_their_vertices(client, sessions):
    idle = client.clip(RIG, "idle")
    # Ticks at twice the clip's rate: every clip frame lasts two ticks, so about every other
    # message says "unchanged" for both heads, and the viewer keeps their arrays.
    heads = [(1, RIG, "idle"), (2, RIG, "idle", 0, [1, 0, 0])]
    info = _create(client, sessions, heads, fps=2 * idle.fps)
    unchanged = changed = 0
    with client.stream(info.id, format="q16") as viewer:
        prev = next(viewer)
        assert prev.layout_changed and len(prev.message.buffers) == 1
        # Read until both kinds were seen (a loaded machine skips ticks, so the count of
        # messages this takes varies).
        for _ in range(200):
            t = next(viewer)
            assert not t.layout_changed
            all_unchanged = all(b == HEAD_UNCHANGED for b in t.message.heads.buffer_indices)
            if all_unchanged:
                assert t.changed == [] and t.message.buffers == []
                assert t.positions[1] is prev.positions[1]
                assert t.buffers[2] is prev.buffers[2]
                unchanged += 1
            else:
                assert t.changed == [1, 2] and len(t.message.buffers) == 1
                changed += 1
            assert set(t.positions) == {1, 2}
            prev = t
            if unchanged >= 2 and changed >= 2:
                break
    assert unchanged >= 2 and changed >= 2, (unchanged, changed)


@needs_websockets
def test_a_patch_changes_the_layout_at_a_later_tick(client, sessions):
    info = _create(client, sessions, [(1, RIG, "talk"), (2, RIG, "smile", 0, [1, 0, 0])])
    with client.stream(info.id, format="f16") as viewer:
        first = next(viewer)
        assert first.layout_changed and first.heads == [1, 2]
        client.patch_session(
            info.id,
            remove=[1],
            change=[{"head": 2, "clip": "surprise", "yaw": 90}],
            add=[(9, RIG, "idle", 4, [0, 0, 2])],
        )
        for _ in range(30):
            t = next(viewer)
            if t.layout_changed:
                break
        else:
            pytest.fail("no message carried the new layout")
        assert t.tick > first.tick
        assert t.heads == [2, 9] and viewer.layout == t.layout
        assert (t.layout[0].clip, t.layout[0].yaw) == ("surprise", 90.0)
        assert t.layout[1].position == [0.0, 0.0, 2.0]
        assert set(t.positions) == {2, 9} and 1 not in viewer.positions
        assert t.buffers[2].clip == "surprise" and t.buffers[9].clip == "idle"


@needs_websockets
def test_a_lod_update_applies_from_a_later_tick(client, sessions):
    levels = len(client.rig(RIG).lod.levels)
    assert levels >= 2
    info = _create(client, sessions, [(1, RIG, "talk"), (2, RIG, "talk", 0, [0, 0, -30])])
    camera = {"position": [0, 0, 5], "target": [0, 0, 0]}
    with client.stream(info.id, lod=[[0, 0], [20, 1]], camera=camera) as viewer:
        t = next(viewer)
        assert (t.buffers[1].lod, t.buffers[2].lod) == (0, 1)
        viewer.update(lod=levels - 1)
        for _ in range(30):
            t = next(viewer)
            if t.buffers[1].lod == levels - 1:
                break
        assert t.buffers[1].lod == t.buffers[2].lod == levels - 1
        assert t.buffers[1].vertices == client.rig(RIG).lod.levels[-1].vertices


@needs_websockets
def test_a_bad_hello_closes_the_stream_with_1008_and_the_reason(client, sessions):
    info = _create(client, sessions, [(1, RIG, "talk")])
    viewer = client.stream(info.id, lod=[[10, 1], [5, 2]])
    with pytest.raises(crowdmorph.StreamClosed) as e:
        next(viewer)
    assert e.value.code == 1008 and not e.value.local
    assert e.value.reason == "bad lod: distances must be finite and ascending"
    assert viewer.closed is e.value
    viewer = client.stream(info.id, camera={"position": [0, 0, 1], "target": [0, 0, 1]})
    with pytest.raises(crowdmorph.StreamClosed) as e:
        next(viewer)
    assert e.value.code == 1008 and "camera" in e.value.reason


@needs_websockets
def test_deleting_the_session_closes_its_streams_with_1001(client, sessions):
    info = _create(client, sessions, [(1, RIG, "talk")])
    a = client.stream(info.id)
    b = client.stream(info.id, format="f32")
    next(a)
    next(b)
    client.delete_session(info.id)
    for viewer in (a, b):
        with pytest.raises(crowdmorph.StreamClosed) as e:
            for _ in range(100):
                next(viewer)
        assert (e.value.code, e.value.reason, e.value.local) == (1001, "session deleted", False)


@needs_websockets
def test_closing_a_viewer_ends_its_iteration_and_frees_its_place(client, sessions):
    info = _create(client, sessions, [(1, RIG, "talk")])
    viewer = client.stream(info.id)
    next(viewer)
    assert client.session(info.id).viewers == 1
    viewer.close()
    assert list(viewer) == []
    viewer.close()  # idempotent
    with pytest.raises(crowdmorph.StreamClosed):
        viewer.update(lod=1)
    deadline = time.monotonic() + 10
    while client.session(info.id).viewers and time.monotonic() < deadline:
        time.sleep(0.05)
    assert client.session(info.id).viewers == 0


@needs_websockets
def test_the_server_answers_a_viewers_close_with_1000(client, sessions):
    info = _create(client, sessions, [(1, RIG, "talk")])
    viewer = client.stream(info.id)
    next(viewer)
    viewer.close()
    assert viewer.closed.code == 1000 and not viewer.closed.local


@needs_websockets
def test_a_viewer_that_asks_for_frames_gets_images(client, sessions):
    if client.readyz().renderer is None:
        pytest.skip("the server has no adapter to render with (install mesa-vulkan-drivers)")
    info = _create(client, sessions, [(1, RIG, "talk"), (2, RIG, "smile", 0, [0.3, 0, 0])], fps=10)
    image = crowdmorph.ImageOptions(width=80, height=60, format="png")
    with client.stream(info.id, output="frames", image=image) as viewer:
        frames = [next(viewer) for _ in range(2)]
    assert frames[1].tick > frames[0].tick
    for f in frames:
        assert isinstance(f, crowdmorph.StreamFrame)
        assert (f.format, f.width, f.height) == ("png", 80, 60)
        assert f.image[:8] == b"\x89PNG\r\n\x1a\n" and f.image.content_type == "image/png"


@needs_websockets
def test_a_message_over_max_message_closes_the_stream_with_1009(client, sessions):
    # The first message carries the layout and a whole buffer: far over 1 KiB.
    info = _create(client, sessions, [(1, RIG, "talk")])
    viewer = client.stream(info.id, format="f32", max_message=1024)
    with pytest.raises(crowdmorph.StreamClosed) as e:
        next(viewer)
    assert e.value.code == 1009 and e.value.local, e.value
    assert viewer.closed is e.value
    with pytest.raises(crowdmorph.StreamClosed) as again:
        next(viewer)
    assert again.value is e.value
    viewer.close()
    assert viewer.closed is e.value


@needs_websockets
def test_a_timeout_between_ticks_leaves_the_stream_usable(client, sessions):
    info = _create(client, sessions, [(1, RIG, "talk")], fps=1)
    with client.stream(info.id, timeout=30) as viewer:
        first = next(viewer)
        # Right after a tick the next one is about a second away (but the first message may
        # have been an older tick, so a tick may still come at once).
        for _ in range(3):
            started = time.monotonic()
            try:
                first = viewer.next(timeout=0.2)
            except TimeoutError:
                break
        else:
            pytest.fail("no 0.2 s without a tick at 1 fps")
        assert time.monotonic() - started < 0.9
        later = next(viewer)
        assert later.tick > first.tick and set(later.positions) == {1}
        viewer.update(lod=1)
        assert next(viewer).tick > later.tick


def test_heads_walk_a_motion_graph_and_patches_send_them_to_a_node(client, sessions):
    graph = {
        "nodes": [{"name": "talk", "clip": "talk"}, {"name": "smile", "clip": "smile"}],
        "edges": [
            {"from": "talk", "to": "smile", "fade": 10},
            {"from": "smile", "to": "talk", "fade": 10},
        ],
    }
    stored = client.put_graph(RIG, "py-moods", graph)
    try:
        assert stored.graph.edges[0].from_ == "talk"
        assert "py-moods" in client.rig(RIG).graphs
        assert [g.name for g in client.graphs(RIG)].count("py-moods") == 1
        walk = {"name": "py-moods", "start": "talk", "seed": 3}
        info = _create(
            client,
            sessions,
            [{"head": 1, "rig": RIG, "graph": walk}, {"head": 2, "rig": RIG, "graph": walk}],
        )
        assert info.heads[0].graph == crowdmorph.GraphPlay("py-moods", "talk", 3, [])
        client.patch_session(info.id, change=[{"head": 1, "node": "smile"}])
        with pytest.raises(crowdmorph.NotFound) as e:
            client.patch_session(info.id, change=[{"head": 1, "node": "nowhere"}])
        assert e.value.code == "unknown_node"
        with client.stream(info.id, format="f32") as stream:
            ticks = [next(stream) for _ in range(3)]
        assert all(len(t.layout) == 2 and set(t.positions) == {1, 2} for t in ticks)
    finally:
        client.delete_graph(RIG, "py-moods")
    assert "py-moods" not in client.rig(RIG).graphs
    built = client.build_graph(RIG, "py-auto", window=5)
    try:
        assert len(built.costs) == len(built.info.graph.edges) > 0
        assert all(0 <= c <= 0.02 for c in built.costs)
    finally:
        client.delete_graph(RIG, "py-auto")


def _zstd_available() -> bool:
    try:
        import zstandard  # noqa: F401
    except ImportError:
        return False
    return True


@needs_websockets
@pytest.mark.parametrize(
    "mode",
    [
        {"temporal": True},
        {"temporal": True, "compression": "deflate", "keyframe_every": 2},
        pytest.param(
            {"temporal": True, "compression": "zstd"},
            marks=pytest.mark.skipif(
                not _zstd_available(), reason="zstd needs the zstandard package (crowdmorph[zstd])"
            ),
        ),
        {"compression": "deflate"},
    ],
)
def test_temporal_and_packed_streams_decode_exactly_what_a_q16_viewer_gets(
    client, sessions, mode
):
    # Clones (heads 1 and 2) and heads of their own; a plain q16 viewer is the reference.
    heads = [
        (1, RIG, "talk", 0),
        (2, RIG, "talk", 0),
        (3, RIG, "smile", 11),
        (4, RIG, "surprise", -5),
        (5, RIG, "idle", 3),
    ]
    info = _create(client, sessions, heads, fps=15)
    plain_seen: Dict[int, Dict[int, tuple]] = {}
    mode_seen: Dict[int, Dict[int, tuple]] = {}
    residual_heads = 0
    packed = 0
    plain = client.stream(info.id, format="q16", normals=True)
    other = client.stream(info.id, format="q16", normals=True, **mode)
    common: List[int] = []
    with plain, other:
        for _ in range(200):
            for viewer, seen in ((plain, plain_seen), (other, mode_seen)):
                t = next(viewer)
                seen[t.tick] = {
                    h: (flat(t.positions[h]), flat(t.normals[h])) for h in t.positions
                }
                if viewer is other:
                    residual_heads += t.from_residuals
                    packed += t.compression is not None
            common = sorted(set(plain_seen) & set(mode_seen))
            if len(common) >= 6:
                break
    assert len(common) >= 6, (sorted(plain_seen), sorted(mode_seen))
    for tick in common:
        assert mode_seen[tick] == plain_seen[tick], f"tick {tick}"
    assert (residual_heads > 0) is bool(mode.get("temporal")), residual_heads
    assert (packed > 0) is ("compression" in mode), packed


@needs_websockets
def test_a_temporal_f32_hello_is_refused_naming_q16(client, sessions):
    info = _create(client, sessions, [(1, RIG, "talk")])
    viewer = client.stream(info.id, format="f32", temporal=True)
    with pytest.raises(crowdmorph.StreamClosed) as e:
        next(viewer)
    assert e.value.code == 1008 and "q16" in e.value.reason, e.value.reason


def test_residuals_and_packed_messages_decode_by_hand():
    from crowdmorph import messages

    # Residual planes of [2, -32768] against [0, 32767]: differences 2 and 1 (wrapping).
    import struct

    prev = struct.pack("<2h", 0, 32767)
    planes = bytes([4, 2, 0, 0])
    assert bytes(crowdmorph.arrays.q16r_decode(planes, prev)) == struct.pack("<2h", 2, -32768)
    with pytest.raises(ValueError):
        crowdmorph.arrays.q16r_decode(planes[:3], prev)
    import zlib

    inner = bytes(range(40))
    good = messages.PackedMessage(encoding="deflate", length=len(inner), data=zlib.compress(inner))
    assert good.unpack() == inner
    liar = messages.PackedMessage(
        encoding="deflate", length=len(inner) + 1, data=zlib.compress(inner)
    )
    with pytest.raises(Exception):
        liar.unpack()


@needs_websockets
def test_a_weights_viewer_gets_each_heads_pose(client, sessions):
    """``output="weights"``: per head its binary16 weights (one per channel), clones one pose,
    heads that did not change kept; no vertices travel."""
    channels = client.rig_channels(RIG)
    idle = client.clip(RIG, "idle")
    heads = [(1, RIG, "idle"), (2, RIG, "idle", 0, [1, 0, 0]), (3, RIG, "talk", 5, [2, 0, 0])]
    info = _create(client, sessions, heads, fps=2 * idle.fps)
    unchanged = 0
    with client.stream(info.id, output="weights") as viewer:
        first = next(viewer)
        assert isinstance(first, crowdmorph.PoseTick) and first.layout_changed
        assert sorted(first.poses) == [1, 2, 3]
        for _ in range(40):
            t = next(viewer)
            assert not t.layout_changed
            assert t.poses[1] is t.poses[2], "clones share a pose"
            for pose in t.poses.values():
                assert len(pose.weights_f32()) == len(channels.targets)
                assert pose.joints == []
            if not t.changed:
                unchanged += 1
            if unchanged >= 2:
                break
    assert unchanged >= 2
    with pytest.raises(ValueError):
        client.stream(info.id, output="weights", temporal=True)
