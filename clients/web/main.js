// The crowdmorph browser viewer: creates a crowd session (or joins `?session=ID`), streams its
// blended vertex buffers over the session's WebSocket and draws them with WebGL2.
//
// URL parameters: `session` (join), `token` (admin token for creating and changing sessions),
// `rig` (default `default-head`), `heads` (initial crowd size, default 25), `fps` (ticks per
// second of a new session), `format` (`q16`, the default, `f16` or `f32`), `temporal` (`0`: ask
// for plain q16 buffers instead of temporal residuals) and `compression` (`deflate`, the default
// with temporal residuals, or `none`).
//
// With q16 the viewer asks for temporal residuals (TickDelta: each head's buffer coded against
// the last one it received for that head) packed with deflate (PackedMessage), inflated by the
// browser's DecompressionStream. Messages are applied strictly in arrival order, one after the
// other, whatever the time each takes to inflate: a residual needs the buffer before it.
//
// What a rig looks like is fetched once per rig, beside its mesh: `GET /v1/rigs/{id}/materials`,
// then each image the materials sample by its versioned URI with a plain fetch (so the
// browser's HTTP cache keeps it: the server marks versioned textures immutable), decoded with
// createImageBitmap and kept on the GPU. The stream carries none of it: 0 bytes per tick.
//
// For tests and for anyone inspecting the page, `window.crowdmorphViewer` tells what arrived and
// what the heads hold (the last tick applied, message counts, a checksum of the decoded q16
// values).
//
// Errors are shown on the page; console.error is kept for real faults, since the end-to-end
// test fails on any console error.

import { Api, ApiError, base64Bytes } from './api.js';
import {
  DecodeError,
  HEAD_MISSING,
  HEAD_UNCHANGED,
  decodeStreamMessage,
  q16rDecode,
  typedView,
  unpack,
} from './bincode.js';
import { OrbitCamera, multiply, placement } from './camera.js';
import { Renderer } from './render.js';

const params = new URLSearchParams(location.search);
const $ = (id) => document.getElementById(id);

const MAX_HEADS = 400;
/** The least time between two camera updates sent to the server (it limits messages/s). */
const CAMERA_UPDATE_MS = 250;

const FORMAT = ['f32', 'f16', 'q16'].includes(params.get('format')) ? params.get('format') : 'q16';
/** Temporal residuals are q16's only (f32 and f16 differences would not decode bit for bit). */
const TEMPORAL = FORMAT === 'q16' && !['0', 'false', 'no'].includes(params.get('temporal'));
/** Deflate where the browser inflates it: by default with residuals, else on `?compression=deflate`. */
const COMPRESSION =
  typeof DecompressionStream === 'function' &&
  (params.get('compression') === 'deflate' || (TEMPORAL && !['none', '0'].includes(params.get('compression'))))
    ? 'deflate'
    : null;

/** Expression layers (wrinkle maps, clip textures) drawn as the server draws them; `?layers=0`
 * draws base colours alone (a comparison, or a GPU without RGBA16F arrays). */
const LAYERS = !['0', 'false', 'no'].includes(params.get('layers'));

const state = {
  api: new Api(params.get('token')),
  format: FORMAT,
  temporal: TEMPORAL,
  compression: COMPRESSION,
  rig: params.get('rig') || 'default-head',
  sessionId: null,
  rigs: new Map(), // rig id → RigInfo (or a pending promise)
  pendingTopologies: new Map(), // topology key → promise
  appearance: new Map(), // rig id → promise of its materials, fetched once
  images: new Map(), // "URI colour spaces" → promise of the image on the GPU
  // Since the page opened: materials and image requests, images on the GPU, failures.
  appearanceStats: {
    materialFetches: 0,
    imageFetches: 0,
    imagesReady: 0,
    imageFailures: 0,
    layerFetches: 0,
    texelFetches: 0,
    layersReady: 0,
    layerFailures: 0,
  },
  layers: LAYERS,
  layerDocs: new Map(), // rig id → promise of its GET /layers, fetched once
  layerTexels: new Map(), // texels URI (with its ETag) → promise of them on the GPU
  // Per head id, its expression-layer inputs as last received (StreamMessage variant 4).
  layerInputs: new Map(),
  lastView: null, // What the last frame was drawn with, for tests.
  refetchAt: new Map(), // topology key → time of the last refetch for a vertex-count mismatch
  layout: [], // per layout head: {spec, entry, model}
  planned: [], // the heads as the server will have them at the next tick
  patching: Promise.resolve(),
  patchesInFlight: 0,
  selectedClips: null,
  sliderMoving: false, // The crowd-size slider moved and its PATCH is not sent yet.
  ws: null,
  helloSent: false,
  inbox: Promise.resolve(), // The binary messages of the socket, applied one after the other.
  // Per head id, the q16 values it holds, as decoded: {positions, normals, quantization}, the
  // reference of that head's next residuals (q16 streams only).
  decoded: new Map(),
  cameraSent: -1,
  drawnCamera: -1,
  dirty: true,
  tick: 0,
  counters: { frames: 0, ticks: 0, bytes: 0, since: performance.now() },
  lastTimings: null,
  lastBuffers: 0,
  // Since the page opened: messages by StreamMessage variant (a packed message counts as 3 and
  // again as what it held), heads given a new buffer decoded from residuals or as keyframes,
  // and bytes on the wire and once inflated.
  received: { variants: [0, 0, 0, 0, 0], fromResiduals: 0, keyframes: 0, wireBytes: 0, bytes: 0, layerBytes: 0 },
};

let renderer;
const camera = new OrbitCamera();

// ---------------------------------------------------------------------------------------------
// Messages on the page.

function showError(message, { fault = true } = {}) {
  const box = $('error');
  box.textContent = message;
  box.hidden = false;
  if (fault) console.error(message);
}

function clearError() {
  $('error').hidden = true;
  $('error').textContent = '';
}

function setStatus(text) {
  $('status').textContent = text;
}

function describe(e) {
  return e instanceof ApiError || e instanceof DecodeError ? e.message : `${e.name || 'Error'}: ${e.message}`;
}

// ---------------------------------------------------------------------------------------------
// Rigs and topology.

async function rigInfo(id) {
  let entry = state.rigs.get(id);
  if (!entry) {
    entry = state.api.rig(id).then((info) => {
      state.rigs.set(id, info);
      return info;
    });
    state.rigs.set(id, entry);
  }
  return entry;
}

function knownRig(id) {
  const r = state.rigs.get(id);
  return r && !(r instanceof Promise) ? r : null;
}

/** The topology a buffer of `rig` at LOD `lod` uses: one per (rig, mesh level). */
function topologyKey(rig, lod) {
  const info = knownRig(rig);
  const levels = info && info.lod && info.lod.levels;
  if (levels && levels.length) {
    const level = levels[Math.min(lod, levels.length - 1)];
    return { key: `${rig}\u0000mesh:${level.mesh ?? 'full'}`, lod };
  }
  return { key: `${rig}\u0000lod:${lod}`, lod };
}

function ensureTopology(key, rig, lod, vertices) {
  const have = renderer.topology(key);
  if (have && have.vertices === vertices) return;
  if (state.pendingTopologies.has(key)) return;
  if (have) {
    // The rig's mesh levels changed under us (a new LOD was computed, or the rig was uploaded
    // again): fetch it again, at most every two seconds, and meanwhile skip heads whose
    // buffers do not fit. Its materials may have changed too; images whose URI (which names
    // their checksum) did not change are not fetched again.
    const last = state.refetchAt.get(key) || 0;
    if (performance.now() - last < 2000) return;
    state.refetchAt.set(key, performance.now());
    state.rigs.delete(rig);
    state.appearance.delete(rig);
    state.layerDocs.delete(rig);
    rigInfo(rig).catch((e) => showError(`rig ${rig}: ${describe(e)}`));
  }
  ensureAppearance(rig);
  const p = state.api
    .mesh(rig, lod)
    .then((mesh) => {
      const indices = new Uint32Array(base64Bytes(mesh.indices));
      for (let i = 0; i < indices.length; i++) {
        if (indices[i] >= mesh.vertices) throw new DecodeError(`mesh of ${rig}: index ${indices[i]} past ${mesh.vertices} vertices`);
      }
      // Texture coordinates (sets 0 and 1: u, v per vertex) and colours (r, g, b, a), or
      // nothing for a rig without them (and from a server older than them).
      const column = (blob, components, what) => {
        const bytes = blob ? base64Bytes(blob) : new ArrayBuffer(0);
        if (bytes.byteLength !== 0 && bytes.byteLength !== mesh.vertices * components * 4) {
          throw new DecodeError(`mesh of ${rig}: ${bytes.byteLength} ${what} bytes for ${mesh.vertices} vertices`);
        }
        return bytes.byteLength ? new Float32Array(bytes) : null;
      };
      const uvs = column(mesh.uvs, 2, 'texture coordinate');
      const uvs1 = column(mesh.uvs1, 2, 'texture coordinate (set 1)');
      const colors = column(mesh.colors, 4, 'vertex colour');
      renderer.setTopology(key, rig, mesh, indices, uvs, uvs1, colors);
      state.dirty = true;
    })
    .catch((e) => showError(`topology of ${rig} at LOD ${lod}: ${describe(e)}`))
    .finally(() => state.pendingTopologies.delete(key));
  state.pendingTopologies.set(key, p);
}

/** Fetches a rig's materials once, then the images they sample that the GPU lacks. */
function ensureAppearance(rig) {
  if (state.appearance.has(rig)) return;
  state.appearanceStats.materialFetches++;
  const p = state.api
    .materials(rig)
    .then((doc) => {
      const wanted = renderer.setMaterials(rig, doc);
      state.dirty = true;
      for (const image of wanted) loadImage(image);
      ensureLayers(rig);
    })
    .catch((e) => showError(`materials of ${rig}: ${describe(e)}`));
  state.appearance.set(rig, p);
}

/**
 * Fetches a rig's expression layers once (`GET /v1/rigs/{id}/layers`), then each material's
 * texels by their versioned URI, once per rig generation, onto the GPU.
 */
function ensureLayers(rig) {
  if (!state.layers || state.layerDocs.has(rig)) return;
  state.appearanceStats.layerFetches++;
  const p = state.api
    .layers(rig)
    .then((doc) => {
      for (const m of doc.materials || []) loadLayerTexels(rig, m);
    })
    .catch((e) => showError(`layers of ${rig}: ${describe(e)}`));
  state.layerDocs.set(rig, p);
}

/** Fetches one material's layer texels and puts them on the GPU. */
function loadLayerTexels(rig, desc) {
  const uri = desc.texels;
  if (typeof uri !== 'string' || state.layerTexels.has(uri)) return;
  state.appearanceStats.texelFetches++;
  const p = fetch(uri)
    .then((resp) => {
      if (!resp.ok) throw new ApiError(resp.status, 'http', `GET ${uri}`);
      return resp.arrayBuffer();
    })
    .then((texels) => {
      renderer.setLayers(rig, desc.material, desc, texels);
      state.appearanceStats.layersReady++;
      state.dirty = true;
    })
    .catch((e) => {
      state.appearanceStats.layerFailures++;
      showError(`layers ${uri}: ${describe(e)}`);
    });
  state.layerTexels.set(uri, p);
}

/** The ImageBitmap option that keeps the image's rows as they are (older browsers say 'none'). */
let imageOrientation = 'from-image';

/**
 * Decodes image bytes as glTF wants them: no colour space conversion (glTF ignores embedded
 * profiles and gamma), no premultiplication (alpha is its own channel), rows top to bottom
 * as stored (glTF's v = 0 is the top row; render.js uploads row 0 at t = 0). Larger than the
 * GPU takes, it is scaled down while decoding.
 */
async function decodeImage(blob, width, height) {
  const options = { colorSpaceConversion: 'none', premultiplyAlpha: 'none', imageOrientation };
  const max = renderer.maxTextureSize;
  if (width > max || height > max) {
    const k = max / Math.max(width, height);
    Object.assign(options, {
      resizeWidth: Math.max(1, Math.floor(width * k)),
      resizeHeight: Math.max(1, Math.floor(height * k)),
      resizeQuality: 'high',
    });
  }
  try {
    return await createImageBitmap(blob, options);
  } catch (e) {
    if (!(e instanceof TypeError) || imageOrientation === 'none') throw e;
    imageOrientation = 'none';
    return createImageBitmap(blob, { ...options, imageOrientation });
  }
}

/** Fetches one image (once per URI and colour spaces) and puts it on the GPU. */
function loadImage({ uri, width, height, srgb, linear }) {
  const key = `${uri} ${srgb} ${linear}`;
  if (state.images.has(key)) return;
  state.appearanceStats.imageFetches++;
  const p = fetch(uri)
    .then((resp) => {
      if (!resp.ok) throw new ApiError(resp.status, 'http', `GET ${uri}`);
      return resp.blob();
    })
    .then((blob) => decodeImage(blob, width, height))
    .then((bitmap) => {
      renderer.setImage(uri, bitmap, { srgb, linear });
      bitmap.close();
      state.appearanceStats.imagesReady++;
      state.dirty = true;
    })
    .catch((e) => {
      state.appearanceStats.imageFailures++;
      showError(`texture ${uri}: ${describe(e)}`);
    });
  state.images.set(key, p);
}

// ---------------------------------------------------------------------------------------------
// The crowd: placements on a square spiral, so growing the crowd never moves a head.

function spiralCell(i) {
  if (i === 0) return [0, 0];
  const ring = Math.ceil((Math.sqrt(i + 1) - 1) / 2);
  const side = 2 * ring;
  const start = (2 * ring - 1) ** 2; // The first index of this ring.
  const k = i - start;
  const edge = Math.floor(k / side);
  const t = (k % side) - ring + 1;
  switch (edge) {
    case 0:
      return [ring, t];
    case 1:
      return [-t, ring];
    case 2:
      return [-ring, -t];
    default:
      return [t, -ring];
  }
}

function spacing(info) {
  const min = info.bbox.min;
  const max = info.bbox.max;
  const dx = max[0] - min[0];
  const dz = max[2] - min[2];
  return [dx * 1.35, Math.max(dx, dz) * 1.5];
}

function clipsOf(info) {
  return info.clips.map((c) => c.name);
}

/** The head a new crowd member `id` of the page's rig gets: one of `clips`, or, for a rig with
 * none (an avatar as uploaded), its neutral made alive by the server (blinks, saccades,
 * breathing; each head's seed is its id, so they do not blink together). */
function newHead(id, info, clips) {
  const [cx, cz] = spiralCell(id);
  const [sx, sz] = spacing(info);
  if (!clips.length) {
    return {
      head: id,
      rig: info.id,
      clip: '',
      position: [cx * sx, 0, cz * sz],
      yaw: ((id * 37) % 31) - 15,
      scale: 1,
      alive: { blink: true, saccades: true, breathing: true },
    };
  }
  const clip = clips[id % clips.length];
  const frames = (info.clips.find((c) => c.name === clip) || { frames: 1 }).frames;
  return {
    head: id,
    rig: info.id,
    clip,
    // Three offsets per clip: heads that share clip and offset are clones, which the server
    // blends once per tick for all of them (25 heads cost 12 blends).
    offset: (Math.floor(id / clips.length) % 3) * Math.floor(frames / 3),
    position: [cx * sx, 0, cz * sz],
    yaw: ((id * 37) % 31) - 15,
    scale: 1,
  };
}

/** Frames the camera on the crowd as planned. */
function frameCrowd(heads) {
  const info = knownRig(state.rig);
  if (!info || !heads.length) return;
  const min = [Infinity, Infinity, Infinity];
  const max = [-Infinity, -Infinity, -Infinity];
  for (const h of heads) {
    const r = knownRig(h.rig) || info;
    for (let a = 0; a < 3; a++) {
      min[a] = Math.min(min[a], h.position[a] + r.bbox.min[a] * h.scale);
      max[a] = Math.max(max[a], h.position[a] + r.bbox.max[a] * h.scale);
    }
  }
  const center = [0, 1, 2].map((a) => (min[a] + max[a]) / 2);
  const radius = Math.hypot(max[0] - min[0], max[1] - min[1], max[2] - min[2]) / 2;
  camera.elevation = 20;
  camera.frame(center, radius * 0.65);
}

// ---------------------------------------------------------------------------------------------
// The stream.

function defaultLodTable(info) {
  // The rig's largest extent, not its height: a flat rig (a floor, a card) would otherwise
  // get every level at 0 m and be drawn at its coarsest however close.
  const h = Math.max(...[0, 1, 2].map((a) => info.bbox.max[a] - info.bbox.min[a]));
  const levels = Math.max(info.lod.levels.length, 1);
  const rows = [];
  for (let l = 0; l < levels; l++) rows.push(`${Math.round(l * 8 * h)}:${l}`);
  return rows.join(', ');
}

function parseLodTable(text) {
  const rows = text
    .split(/[,;]/)
    .map((s) => s.trim())
    .filter(Boolean)
    .map((row) => {
      const m = /^(\d+(?:\.\d+)?)\s*:\s*(\d+)$/.exec(row);
      if (!m) throw new Error(`"${row}" is not metres:level`);
      return [Number(m[1]), Number(m[2])];
    });
  for (let i = 1; i < rows.length; i++) {
    if (rows[i][0] < rows[i - 1][0]) throw new Error('distances must ascend');
  }
  if (!rows.length) throw new Error('the table is empty');
  return rows;
}

function lodChoice() {
  const mode = $('lod-mode').value;
  if (mode === 'distance') return { by_distance: parseLodTable($('lod-table').value) };
  return Number(mode);
}

function openStream() {
  const proto = location.protocol === 'https:' ? 'wss' : 'ws';
  const ws = new WebSocket(`${proto}://${location.host}/v1/sessions/${encodeURIComponent(state.sessionId)}/stream`);
  ws.binaryType = 'arraybuffer';
  state.ws = ws;
  ws.addEventListener('open', () => {
    let lod;
    try {
      lod = lodChoice();
    } catch (e) {
      showError(`LOD table: ${e.message}`, { fault: false });
      lod = 0;
    }
    const hello = { output: 'vertices', format: state.format, normals: true, camera: camera.spec(), lod };
    if (state.temporal) hello.temporal = true;
    if (state.compression) hello.compression = state.compression;
    if (state.layers) hello.layers = true;
    ws.send(JSON.stringify(hello));
    state.helloSent = true;
    state.cameraSent = camera.version;
    setStatus('streaming');
  });
  state.decoded = new Map(); // Residuals refer to what this socket delivered only.
  state.layerInputs = new Map(); // So do layer inputs.
  ws.addEventListener('message', (ev) => {
    if (typeof ev.data === 'string') return; // The server sends no text; nothing to do.
    const data = ev.data;
    state.counters.bytes += data.byteLength;
    state.received.wireBytes += data.byteLength;
    // Inflating is asynchronous: each message waits for the one before it to be applied.
    state.inbox = state.inbox
      .then(() => receive(data))
      .catch((e) => showError(`tick message: ${describe(e)}`));
  });
  ws.addEventListener('close', (ev) => {
    state.ws = null;
    state.helloSent = false;
    const why = `stream closed (${ev.code}${ev.reason ? `: ${ev.reason}` : ''})`;
    setStatus(why);
    if (ev.code === 1000 || ev.code === 1001) {
      // The session ended or was deleted: an outcome, not a fault of the page.
      showError(`${why}. Reload the page without ?session= to start a new one.`, { fault: false });
    } else {
      showError(why);
    }
  });
}

function sendUpdate(update) {
  if (state.ws && state.helloSent && state.ws.readyState === WebSocket.OPEN) {
    state.ws.send(JSON.stringify(update));
    return true;
  }
  return false;
}

function setEntry(h, entry) {
  if (h.entry === entry) return;
  if (entry) entry.refs++;
  if (h.entry && --h.entry.refs === 0) renderer.release(h.entry);
  h.entry = entry;
}

function setLayout(layout) {
  const old = new Map(state.layout.map((h) => [h.spec.head, h]));
  const next = layout.map((spec) => {
    const h = old.get(spec.head) || { spec, entry: null };
    old.delete(spec.head);
    h.spec = spec;
    h.model = placement(spec.position, spec.yaw, spec.scale);
    return h;
  });
  for (const gone of old.values()) {
    setEntry(gone, null);
    // The server forgets it too: back in a later layout, it is sent its inputs again.
    state.layerInputs.delete(gone.spec.head);
  }
  state.layout = next;
  if (state.patchesInFlight === 0 && !state.sliderMoving) {
    // Another viewer may have changed the crowd: the slider follows.
    state.planned = layout;
    $('heads').value = String(layout.length);
  }
  for (const spec of layout) {
    if (!state.rigs.has(spec.rig)) rigInfo(spec.rig).catch((e) => showError(`rig ${spec.rig}: ${describe(e)}`));
  }
  $('heads-out').textContent = $('heads').value;
}

/** Decodes one binary message of the socket (inflating a packed one) and applies it. */
async function receive(data) {
  let msg = decodeStreamMessage(data);
  let buffer = data;
  state.received.variants[msg.variant]++;
  if (msg.kind === 'packed') {
    buffer = await unpack(msg, data);
    msg = decodeStreamMessage(buffer);
    if (msg.kind === 'packed') throw new DecodeError('a packed message inside a packed message');
    state.received.variants[msg.variant]++;
  }
  state.received.bytes += buffer.byteLength;
  if (msg.kind === 'layers') {
    // Sent just before the tick's vertices: the heads draw them together.
    state.received.layerBytes += buffer.byteLength;
    for (const h of msg.heads) state.layerInputs.set(h.head, h.inputs);
    state.dirty = true;
    return;
  }
  applyTick(msg, buffer);
}

/** The q16 values of a buffer sent plain, copied out of the message (which can then go). */
function plainQ16(buffer, b) {
  return {
    positions: typedView(buffer, b.positions, 'q16').slice(),
    normals: b.normals ? typedView(buffer, b.normals, 'q16').slice() : null,
    quantization: b.quantization,
  };
}

/** The q16 values of a head whose buffer `b` holds residuals against its previous values. */
function resolveResiduals(buffer, b, prev, head) {
  const planes = (blob) => new Uint8Array(buffer, blob.offset, blob.length);
  if (prev.positions.length !== b.vertices * 3) {
    throw new DecodeError(`head ${head}: residuals for ${b.vertices} vertices against a buffer of ${prev.positions.length / 3}`);
  }
  let normals = null;
  if (b.normals) {
    if (!prev.normals) throw new DecodeError(`head ${head}: residual normals but no earlier normals`);
    normals = q16rDecode(planes(b.normals), prev.normals);
  }
  return { positions: q16rDecode(planes(b.positions), prev.positions), normals, quantization: b.quantization };
}

/**
 * Applies a vertex message, as crowdmorph_proto's StreamState does: every head's new values
 * are decoded first (a message that does not fit what came before is refused whole and changes
 * nothing), then the heads draw them.
 */
function applyTick(msg, buffer) {
  if (msg.kind !== 'vertices') throw new DecodeError(`a ${msg.kind} message on a vertices stream`);
  const layout = msg.layout || state.layout.map((h) => h.spec);
  if (msg.heads.length !== layout.length) {
    throw new DecodeError(`${msg.heads.length} heads for a layout of ${layout.length}`);
  }
  msg.heads.forEach((hb, i) => {
    const want = layout[i].head;
    if (hb.head !== want) throw new DecodeError(`head ${i} is ${hb.head}, the layout says ${want}`);
  });
  const q16 = msg.format === 'q16';
  // What each head draws: a slot per buffer sent plain, and per (residual buffer, previous
  // values) pair, each with one renderer entry: heads that share a residual buffer had the same
  // previous buffer, so they share the decoded values too.
  const plain = new Array(msg.buffers.length).fill(null);
  const resolved = msg.buffers.map(() => new Map());
  const decoded = new Map();
  const slots = new Array(msg.heads.length);
  let fromResiduals = 0;
  let keyframes = 0;
  msg.heads.forEach((hb, i) => {
    const id = hb.head;
    if (hb.buffer === HEAD_MISSING) {
      slots[i] = null;
      return;
    }
    if (hb.buffer === HEAD_UNCHANGED) {
      const had = state.decoded.get(id);
      if (had) decoded.set(id, had);
      slots[i] = undefined;
      return;
    }
    const b = msg.buffers[hb.buffer];
    let slot;
    if (msg.residual && msg.residual[hb.buffer]) {
      const prev = state.decoded.get(id);
      if (!prev) throw new DecodeError(`head ${id} has residuals but no earlier buffer`);
      slot = resolved[hb.buffer].get(prev);
      if (!slot) {
        slot = { b, values: resolveResiduals(buffer, b, prev, id), entry: null };
        resolved[hb.buffer].set(prev, slot);
      }
      fromResiduals++;
    } else {
      slot = plain[hb.buffer];
      if (!slot) {
        const values = q16
          ? plainQ16(buffer, b)
          : {
              positions: typedView(buffer, b.positions, msg.format),
              normals: b.normals ? typedView(buffer, b.normals, msg.format) : null,
              quantization: b.quantization,
            };
        slot = { b, values, entry: null };
        plain[hb.buffer] = slot;
      }
      keyframes++;
    }
    if (q16) decoded.set(id, slot.values);
    slots[i] = slot;
  });

  // Decoded: from here on nothing throws.
  if (msg.layout) setLayout(msg.layout);
  const entries = [];
  slots.forEach((slot, i) => {
    const h = state.layout[i];
    if (slot === undefined) return; // HEAD_UNCHANGED: keep what it had.
    if (slot === null) {
      setEntry(h, null);
      return;
    }
    if (!slot.entry) {
      const { b, values } = slot;
      const { key } = topologyKey(b.rig, b.lod);
      ensureTopology(key, b.rig, b.lod, b.vertices);
      const e = renderer.entry(key, b.vertices, msg.format, values.positions, values.normals, values.quantization);
      e.refs = 0;
      e.lod = b.lod;
      slot.entry = e;
      entries.push(e);
    }
    setEntry(h, slot.entry);
  });
  for (const e of entries) if (e.refs === 0) renderer.release(e);
  state.decoded = q16 ? decoded : new Map();
  state.received.fromResiduals += fromResiduals;
  state.received.keyframes += keyframes;
  state.tick = msg.tick;
  state.lastTimings = msg.timings;
  state.lastBuffers = msg.buffers.length;
  state.counters.ticks++;
  state.dirty = true;
  $('tick').textContent = String(msg.tick);
}

// ---------------------------------------------------------------------------------------------
// Controls: crowd size and clip mix are session changes (PATCH, one at a time, each based on the
// heads the last answer said the next tick will have); LOD and camera are this viewer's own.

function patch(make) {
  state.patchesInFlight++;
  state.patching = state.patching
    .then(async () => {
      const body = make(state.planned);
      if (!body) return;
      const info = await state.api.patchSession(state.sessionId, body);
      state.planned = info.heads;
    })
    .catch((e) => {
      if (e instanceof ApiError && (e.status === 401 || e.status === 403)) {
        showError(`changing the session needs the admin token (?token=): ${e.message}`, { fault: false });
      } else {
        showError(`changing the session: ${describe(e)}`);
      }
    })
    .finally(() => state.patchesInFlight--);
}

function resizeCrowd(n) {
  const info = knownRig(state.rig);
  if (!info) return;
  patch((heads) => {
    if (n === heads.length) return null;
    if (n < heads.length) {
      const ids = heads.map((h) => h.head).sort((a, b) => b - a);
      return { remove: ids.slice(0, heads.length - n) };
    }
    const used = new Set(heads.map((h) => h.head));
    const add = [];
    for (let id = 0; add.length < n - heads.length; id++) {
      if (!used.has(id)) add.push(newHead(id, info, selectedClips(info)));
    }
    return { add };
  });
}

function selectedClips(info) {
  const all = clipsOf(info);
  const picked = all.filter((c) => state.selectedClips && state.selectedClips.has(c));
  return picked.length ? picked : all;
}

function applyClipMix() {
  const info = knownRig(state.rig);
  if (!info) return;
  const clips = selectedClips(info);
  if (!clips.length) return;
  patch((heads) => {
    const change = heads
      .filter((h) => h.rig === info.id && h.clip !== clips[h.head % clips.length])
      .map((h) => ({ head: h.head, clip: clips[h.head % clips.length] }));
    return change.length ? { change } : null;
  });
}

function buildControls(info, heads) {
  const range = $('heads');
  range.max = String(MAX_HEADS);
  range.value = String(heads.length);
  $('heads-out').textContent = String(heads.length);
  let timer = null;
  range.addEventListener('input', () => {
    $('heads-out').textContent = range.value;
    state.sliderMoving = true;
    clearTimeout(timer);
    timer = setTimeout(() => {
      state.sliderMoving = false;
      resizeCrowd(Number(range.value));
    }, 300);
  });

  const used = new Set(heads.filter((h) => h.rig === info.id).map((h) => h.clip));
  state.selectedClips = new Set(clipsOf(info).filter((c) => used.has(c)));
  const box = $('clips');
  for (const name of clipsOf(info)) {
    const label = document.createElement('label');
    const check = document.createElement('input');
    check.type = 'checkbox';
    check.checked = state.selectedClips.has(name);
    check.addEventListener('change', () => {
      if (check.checked) state.selectedClips.add(name);
      else state.selectedClips.delete(name);
      applyClipMix();
    });
    label.append(check, ` ${name}`);
    box.append(label);
  }

  const mode = $('lod-mode');
  const distance = document.createElement('option');
  distance.value = 'distance';
  distance.textContent = 'by distance';
  mode.append(distance);
  info.lod.levels.forEach((level, l) => {
    const o = document.createElement('option');
    o.value = String(l);
    o.textContent = `level ${l} (${level.shapes} shapes)`;
    mode.append(o);
  });
  mode.value = 'distance';
  const table = $('lod-table');
  table.value = defaultLodTable(info);
  const sendLod = () => {
    table.disabled = mode.value !== 'distance';
    try {
      const lod = lodChoice();
      clearError();
      sendUpdate({ lod });
    } catch (e) {
      showError(`LOD table: ${e.message}`, { fault: false });
    }
  };
  mode.addEventListener('change', sendLod);
  table.addEventListener('change', sendLod);
}

// ---------------------------------------------------------------------------------------------
// Drawing and counters.

function frame() {
  if (renderer.resize()) state.dirty = true;
  if (state.dirty || camera.version !== state.drawnCamera) {
    const aspect = renderer.canvas.width / renderer.canvas.height;
    const projection = camera.projection(aspect);
    // On a wide window, the orbit centre sits in the middle of the space the panel leaves.
    const panel = $('panel').getBoundingClientRect();
    const width = renderer.canvas.clientWidth;
    if (width > 2.5 * panel.right) projection[8] -= panel.right / width;
    const viewMatrix = camera.view();
    const view = { viewProj: multiply(projection, viewMatrix), view: viewMatrix, eye: camera.eye() };
    const drawn = renderer.draw(view, state.layout, state.layerInputs);
    state.lastView = {
      viewProj: view.viewProj,
      eye: view.eye,
      camera: { ...camera.spec(), ...camera.clip() },
      // How far the picture is moved right beside the panel, in NDC (a CameraSpec cannot say).
      ndcShiftX: -projection[8],
      layout: state.layout,
    };
    // What was drawn, for tests and for anyone inspecting the page.
    const lods = new Set(state.layout.filter((h) => h.entry).map((h) => h.entry.lod));
    Object.assign(renderer.canvas.dataset, {
      heads: String(state.layout.length),
      drawn: String(drawn),
      lods: [...lods].sort((a, b) => a - b).join(','),
    });
    state.drawnCamera = camera.version;
    state.dirty = false;
    state.counters.frames++;
  }
  requestAnimationFrame(frame);
}

function formatBytes(n) {
  if (n >= 1e6) return `${(n / 1e6).toFixed(2)} MB`;
  if (n >= 1e3) return `${(n / 1e3).toFixed(1)} kB`;
  return `${Math.round(n)} B`;
}

function updateCounters() {
  const now = performance.now();
  const c = state.counters;
  const s = (now - c.since) / 1000;
  if (s <= 0) return;
  $('fps').textContent = (c.frames / s).toFixed(1);
  $('tps').textContent = (c.ticks / s).toFixed(1);
  $('bps').textContent = formatBytes(c.bytes / s);
  const t = state.lastTimings;
  const lods = renderer.canvas.dataset.lods || '-';
  const mode = [state.format, state.temporal && 'temporal', state.compression].filter(Boolean).join(' + ');
  $('detail').textContent =
    `${state.layout.length} heads · ${state.lastBuffers} buffers last tick · LOD ${lods} · ${mode}` +
    (t ? ` · compute ${(t.compute_us / 1000).toFixed(1)} ms` : '');
  state.counters = { frames: 0, ticks: 0, bytes: 0, since: now };
}

function sendCamera() {
  if (camera.version !== state.cameraSent && sendUpdate({ camera: camera.spec() })) {
    state.cameraSent = camera.version;
  }
}

// ---------------------------------------------------------------------------------------------
// What the page holds, for tests (tests/server/viewer.rs) and for inspecting it by hand.

/** FNV-1a, 32-bit, fed byte by byte. */
function fnv1a(h, bytes) {
  for (let i = 0; i < bytes.length; i++) h = Math.imul(h ^ bytes[i], 0x01000193);
  return h;
}

/**
 * A checksum of the q16 values every head holds after the last tick applied: FNV-1a 32 (basis
 * 0x811c9dc5) fed, for each layout head in order that has a buffer, its id as u64
 * little-endian, its positions' int16 values little-endian, then its normals' (if any). A plain
 * q16 reader of the same ticks computes the same number; null on an f32 or f16 stream.
 */
function q16Checksum() {
  if (state.format !== 'q16') return null;
  let h = 0x811c9dc5;
  const id = new DataView(new ArrayBuffer(8));
  for (const { spec } of state.layout) {
    const v = state.decoded.get(spec.head);
    if (!v) continue;
    id.setUint32(0, spec.head % 2 ** 32, true);
    id.setUint32(4, Math.floor(spec.head / 2 ** 32), true);
    h = fnv1a(h, new Uint8Array(id.buffer));
    // Int16Array bytes are the platform's order: little-endian everywhere WebGL runs.
    for (const a of [v.positions, v.normals]) if (a) h = fnv1a(h, new Uint8Array(a.buffer, a.byteOffset, a.byteLength));
  }
  return h >>> 0;
}

window.crowdmorphViewer = Object.freeze({
  /** The hello's modes. */
  get mode() {
    return { format: state.format, temporal: state.temporal, compression: state.compression, layers: state.layers };
  },
  /** The last tick applied (0 before the first). */
  get tick() {
    return state.tick;
  },
  /** Counters since the page opened (a copy). */
  get received() {
    return { ...state.received, variants: [...state.received.variants] };
  },
  q16Checksum,
  /** Appearance requests since the page opened, and the textures on the GPU. */
  get appearance() {
    return {
      ...state.appearanceStats,
      textures: renderer ? renderer.textureCount : 0,
      layerMaterials: renderer ? renderer.layerCount : 0,
    };
  },
  /** Each head's expression-layer inputs as last received. */
  get layerInputs() {
    return Object.fromEntries([...state.layerInputs].map(([h, v]) => [h, Array.from(v)]));
  },
  /** What the last frame was drawn with: the view-projection matrix (column-major), the
   * camera, the drawing buffer's size, the eye, and each drawn head's model matrix. */
  get view() {
    const v = state.lastView;
    if (!v) return null;
    return {
      viewProj: Array.from(v.viewProj),
      eye: v.eye.slice(),
      // The camera as the server's CameraSpec, clip planes included.
      camera: { ...v.camera },
      ndcShiftX: v.ndcShiftX,
      width: renderer.canvas.width,
      height: renderer.canvas.height,
      heads: v.layout.filter((h) => h.entry).map((h) => ({ head: h.spec.head, rig: h.spec.rig, model: Array.from(h.model) })),
    };
  },
  /** Tick, checksum and counters at one instant (messages are applied between tasks). */
  snapshot() {
    return { tick: state.tick, checksum: q16Checksum(), received: this.received };
  },
});

// ---------------------------------------------------------------------------------------------
// Start.

async function start() {
  try {
    renderer = new Renderer($('view'));
  } catch (e) {
    showError(`WebGL2: ${e.message}`);
    return;
  }
  camera.attach($('view'));
  try {
    let heads;
    const join = params.get('session');
    if (join) {
      setStatus(`joining session ${join}`);
      const info = await state.api.session(join);
      state.sessionId = info.id;
      heads = info.heads;
      if (!params.get('rig') && heads.length) state.rig = heads[0].rig;
    }
    const rig = await rigInfo(state.rig);
    if (!join) {
      const n = Math.max(1, Math.min(MAX_HEADS, Number(params.get('heads')) || 25));
      // A rig without clips still gets a session: its neutral, alive (see newHead).
      const clips = clipsOf(rig);
      heads = Array.from({ length: n }, (_, id) => newHead(id, rig, clips));
      const fps = Number(params.get('fps')) || 30;
      setStatus('creating a session');
      const info = await state.api.createSession({ fps, wrap: true, idle_timeout_s: 60, heads });
      state.sessionId = info.id;
      const url = new URL(location.href);
      url.searchParams.set('session', info.id);
      history.replaceState(null, '', url);
    }
    state.planned = heads;
    const link = $('session-link');
    link.textContent = state.sessionId;
    const share = new URL(location.href);
    share.searchParams.delete('token');
    link.href = share.href;
    buildControls(rig, heads);
    frameCrowd(heads);
    openStream();
  } catch (e) {
    if (e instanceof ApiError && e.code === 'unknown_session') {
      // Sessions end after their idle timeout: an old link is an outcome, not a fault.
      showError(`${e.message}: it has ended. Open /viewer without ?session= to start a new one.`, { fault: false });
    } else {
      showError(`starting: ${describe(e)}`);
    }
    return;
  }
  setInterval(updateCounters, 1000);
  setInterval(sendCamera, CAMERA_UPDATE_MS);
  requestAnimationFrame(frame);
}

// Faults no handler caught are shown on the page as well as in the console.
window.addEventListener('error', (e) => showError(`${e.message}`, { fault: false }));
window.addEventListener('unhandledrejection', (e) => showError(`${e.reason}`, { fault: false }));

start();
