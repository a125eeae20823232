// A reader for the server's bincode messages, written from proto/README.md ("bincode" and
// "Crowd sessions"): bincode 2, standard configuration (little-endian, varint integers).
//
// Only what the viewer receives is decoded: the stream's StreamMessage (proto/README.md, "The
// stream": variants 0 TickVertices, 1 TickFrame, 2 TickDelta, 3 PackedMessage, 4 TickLayers, 5 TickPoses), and
// a crowd frame's CrowdPoseResponse (decodeCrowdPoses, for "format": "weights"). Vertex payloads
// are not copied: a Blob is returned as its byte offset and length in the message's ArrayBuffer,
// and typedView() views it in place (the server pads each payload to a 16-byte offset), copying
// only when an odd offset makes a view impossible. unpack() inflates a PackedMessage into the
// bytes of the message it holds, and q16rDecode() resolves a TickDelta's residual planes.

/** HeadBuffer.buffer of a head whose job did not change: keep drawing what it had. */
export const HEAD_UNCHANGED = 0xffffffff;
/** HeadBuffer.buffer of a head with nothing to draw (its rig or clip was deleted). */
export const HEAD_MISSING = 0xfffffffe;

/** Formats by their varint variant index (vertex formats, then `weights`: no vertices, poses). */
export const FORMATS = ['f32', 'f16', 'q16', 'q16r', 'weights'];
/** Image formats of TickFrame by their variant index. */
export const IMAGE_FORMATS = ['png', 'jpeg', 'rgba'];
/** Compressions of PackedMessage by their variant index. */
export const MESSAGE_ENCODINGS = ['zstd', 'deflate'];
/** Most bytes a packed message may claim once decompressed (as the Rust decoder: 1 GiB). */
export const MAX_UNPACKED_BYTES = 2 ** 30;

/** A message that does not follow the spec; the viewer reports it and drops the message. */
export class DecodeError extends Error {
  constructor(message) {
    super(message);
    this.name = 'DecodeError';
  }
}

const utf8 = new TextDecoder('utf-8', { fatal: true });

/** A cursor over one message. */
export class Reader {
  /** @param {ArrayBuffer} buffer the whole message */
  constructor(buffer) {
    this.buffer = buffer;
    this.view = new DataView(buffer);
    this.pos = 0;
  }

  need(n) {
    if (this.pos + n > this.view.byteLength) {
      throw new DecodeError(`message ends at byte ${this.view.byteLength}, needed ${n} more at ${this.pos}`);
    }
  }

  u8() {
    this.need(1);
    return this.view.getUint8(this.pos++);
  }

  bool() {
    const b = this.u8();
    if (b > 1) throw new DecodeError(`bool byte ${b} at ${this.pos - 1}`);
    return b === 1;
  }

  /** An unsigned varint as a Number (exact up to 2^53, which ids and counters stay below). */
  varint() {
    const first = this.u8();
    if (first < 251) return first;
    if (first === 0xfb) {
      this.need(2);
      const v = this.view.getUint16(this.pos, true);
      this.pos += 2;
      return v;
    }
    if (first === 0xfc) {
      this.need(4);
      const v = this.view.getUint32(this.pos, true);
      this.pos += 4;
      return v;
    }
    if (first === 0xfd) {
      this.need(8);
      const v = this.view.getBigUint64(this.pos, true);
      this.pos += 8;
      if (v > BigInt(Number.MAX_SAFE_INTEGER)) {
        throw new DecodeError(`integer ${v} at ${this.pos - 9} is past 2^53`);
      }
      return Number(v);
    }
    throw new DecodeError(`varint tag 0x${first.toString(16)} at ${this.pos - 1} (u128 is not used)`);
  }

  /** A u64 varint that is only shown, never computed with (a graph head's seed): past 2^53
   * it is rounded rather than refused. */
  varintLossy() {
    this.need(1);
    if (this.view.getUint8(this.pos) === 0xfd) {
      this.need(9);
      const v = this.view.getBigUint64(this.pos + 1, true);
      this.pos += 9;
      return Number(v);
    }
    return this.varint();
  }

  /** A u32 varint, checked to fit. */
  u32() {
    const v = this.varint();
    if (v > 0xffffffff) throw new DecodeError(`u32 ${v} out of range at ${this.pos}`);
    return v;
  }

  /** A zigzag i64 varint. */
  i64() {
    const z = this.varint();
    return z % 2 === 0 ? z / 2 : -(z + 1) / 2;
  }

  f32() {
    this.need(4);
    const v = this.view.getFloat32(this.pos, true);
    this.pos += 4;
    return v;
  }

  vec3() {
    return [this.f32(), this.f32(), this.f32()];
  }

  string() {
    const n = this.varint();
    this.need(n);
    const s = utf8.decode(new Uint8Array(this.buffer, this.pos, n));
    this.pos += n;
    return s;
  }

  option(read) {
    return this.bool() ? read() : null;
  }

  vec(read) {
    const n = this.varint();
    // Every element is at least one byte: a count past the bytes left is a broken message,
    // refused before anything is allocated for it.
    if (n > this.view.byteLength - this.pos) {
      throw new DecodeError(`${n} elements announced with ${this.view.byteLength - this.pos} bytes left`);
    }
    const out = new Array(n);
    for (let i = 0; i < n; i++) out[i] = read();
    return out;
  }

  /** A Blob (`pad: bytes`, then `data: bytes`) as {offset, length} of its data. */
  blob() {
    const pad = this.varint();
    this.need(pad);
    this.pos += pad;
    const length = this.varint();
    this.need(length);
    const offset = this.pos;
    this.pos += length;
    return { offset, length };
  }

  enumIndex(names, what) {
    const i = this.varint();
    if (i >= names.length) throw new DecodeError(`${what} variant ${i}`);
    return names[i];
  }

  end() {
    if (this.pos !== this.view.byteLength) {
      throw new DecodeError(`${this.view.byteLength - this.pos} trailing bytes after the message`);
    }
  }
}

/** A JointTransform: three options of fixed 4-byte floats (translation, rotation x y z w,
 * scale), each null when absent. */
function jointTransform(r) {
  return {
    translation: r.option(() => r.vec3()),
    rotation: r.option(() => [r.f32(), r.f32(), r.f32(), r.f32()]),
    scale: r.option(() => r.vec3()),
  };
}

/** JointOverrides (a `Vec<(String, JointTransform)>` in bincode) as the JSON form: an object
 * by node name. Object.fromEntries defines own properties, so a node named `__proto__` stays a
 * node; a node named twice (which no server sends) is refused rather than merged. */
function jointOverrides(r) {
  const pairs = r.vec(() => [r.string(), jointTransform(r)]);
  const joints = Object.fromEntries(pairs);
  if (Object.keys(joints).length !== pairs.length) throw new DecodeError('a joint override names a node twice');
  return joints;
}

function sessionHead(r) {
  return {
    head: r.varint(),
    rig: r.string(),
    clip: r.string(),
    offset: r.i64(),
    position: r.vec3(),
    yaw: r.f32(),
    scale: r.f32(),
    graph: r.option(() => ({
      name: r.string(),
      start: r.string(),
      seed: r.varintLossy(),
      script: r.vec(() => r.string()),
    })),
    joints: jointOverrides(r),
    layers: r.vec(() => layer(r)),
    clamp: r.option(() => [r.f32(), r.f32()]),
    live: r.option(() => ({
      hold_ms: r.varint(),
      fade_ms: r.varint(),
      delay_ms: r.varint(),
      smoothing: r.option(() => ({ min_cutoff: r.f32(), beta: r.f32(), d_cutoff: r.f32() })),
      mapping: r.option(() => r.string()),
    })),
    alive: r.option(() => ({
      blink: r.bool(),
      saccades: r.bool(),
      look_at: r.option(() => r.vec3()),
      breathing: r.bool(),
      seed: r.option(() => r.varintLossy()),
    })),
  };
}

/** A layer's mask as its JSON form: an array of names (variant 0), an object of names to
 * weights (1), or a built-in mask's name (2). */
function mask(r) {
  const variant = r.varint();
  if (variant === 0) return r.vec(() => r.string());
  if (variant === 1) return Object.fromEntries(r.vec(() => [r.string(), r.f32()]));
  if (variant === 2) return r.string();
  throw new DecodeError(`mask variant ${variant}`);
}

/** One layer of a session head (proto/README.md, "Layers and masks"). */
function layer(r) {
  const clip = r.string();
  const frame = r.i64();
  const weight = r.f32();
  const mode = r.varint();
  if (mode > 1) throw new DecodeError(`layer mode ${mode}`);
  return {
    clip,
    frame,
    weight,
    mode: mode === 0 ? 'override' : 'additive',
    mask: r.option(() => mask(r)),
    reference: r.option(() => r.i64()),
    joint_mask: r.option(() => r.vec(() => r.string())),
  };
}

function quantization(r) {
  return { min: r.vec3(), step: r.vec3(), max_error: r.vec3() };
}

function frameBuffer(r) {
  return {
    rig: r.string(),
    clip: r.string(),
    frame: r.u32(),
    lod: r.u32(),
    vertices: r.u32(),
    quantization: r.option(() => quantization(r)),
    positions: r.blob(),
    normals: r.option(() => r.blob()),
  };
}

function headBuffer(r) {
  return { head: r.varint(), buffer: r.u32() };
}

function timings(r) {
  return {
    queue_us: r.varint(),
    compute_us: r.varint(),
    total_us: r.varint(),
    gpu_us: r.option(() => r.varint()),
  };
}

/**
 * Decodes one binary message of `GET /v1/sessions/{id}/stream`.
 *
 * Variants 0 (TickVertices) and 2 (TickDelta) both come back as kind `vertices`; a TickDelta
 * has `residual` (one flag per buffer: true for residual planes against each naming head's
 * previous buffer, false for a plain q16 keyframe), a TickVertices has `residual: null`.
 * Variant 3 (PackedMessage) comes back as kind `packed`, for unpack().
 * @param {ArrayBuffer} buffer
 * @returns {{kind: 'vertices', variant: 0|2, tick: number, format: string, normals: boolean,
 *   layout: object[]|null, residual: boolean[]|null, buffers: object[],
 *   heads: {head: number, buffer: number}[], timings: object}
 *   | {kind: 'frame', variant: 1, tick: number, format: string, width: number, height: number,
 *   image: {offset: number, length: number}}
 *   | {kind: 'packed', variant: 3, encoding: string, length: number,
 *   data: {offset: number, length: number}}
 *   | {kind: 'layers', variant: 4, tick: number, heads: {head: number, inputs: Float32Array}[]}
 *   | {kind: 'poses', variant: 5, tick: number, layout: object[]|null, poses: object[],
 *   heads: {head: number, buffer: number}[], timings: object}}
 * A pose is {weights: Float32Array (one per channel of GET /v1/rigs/{id}/channels),
 * joints: {node: number, rotation: number[4], translation: number[3]|null, scale: number[3]|null}[]}.
 */
export function decodeStreamMessage(buffer) {
  const r = new Reader(buffer);
  const variant = r.varint();
  let msg;
  if (variant === 0 || variant === 2) {
    // TickVertices, or TickDelta: the same fields with a residual flag per buffer.
    msg = {
      kind: 'vertices',
      variant,
      tick: r.varint(),
      format: r.enumIndex(FORMATS, 'Format'),
      normals: r.bool(),
      layout: r.option(() => r.vec(() => sessionHead(r))),
      residual: variant === 2 ? r.vec(() => r.bool()) : null,
      buffers: r.vec(() => frameBuffer(r)),
      heads: r.vec(() => headBuffer(r)),
      timings: timings(r),
    };
    if (variant === 2) {
      if (msg.format !== 'q16') throw new DecodeError(`a temporal message in ${msg.format}, not q16`);
      if (msg.residual.length !== msg.buffers.length) {
        throw new DecodeError(`${msg.residual.length} residual flags for ${msg.buffers.length} buffers`);
      }
    }
    checkBuffers(msg);
  } else if (variant === 1) {
    msg = {
      kind: 'frame',
      variant,
      tick: r.varint(),
      format: r.enumIndex(IMAGE_FORMATS, 'ImageFormat'),
      width: r.u32(),
      height: r.u32(),
      image: r.blob(),
    };
  } else if (variant === 3) {
    msg = {
      kind: 'packed',
      variant,
      encoding: r.enumIndex(MESSAGE_ENCODINGS, 'MessageEncoding'),
      length: r.varint(),
      data: r.blob(),
    };
  } else if (variant === 4) {
    // TickLayers: per head whose inputs changed, its expression-layer inputs.
    msg = {
      kind: 'layers',
      variant,
      tick: r.varint(),
      heads: r.vec(() => ({ head: r.varint(), inputs: Float32Array.from(r.vec(() => r.f32())) })),
    };
  } else if (variant === 5) {
    // TickPoses: per changed head its binary16 weights and moved nodes (no vertices).
    msg = {
      kind: 'poses',
      variant,
      tick: r.varint(),
      layout: r.option(() => r.vec(() => sessionHead(r))),
      poses: r.vec(() => headPose(r)),
      heads: r.vec(() => headBuffer(r)),
      timings: timings(r),
    };
    checkPoses(msg);
  } else {
    throw new DecodeError(`StreamMessage variant ${variant}`);
  }
  r.end();
  return msg;
}

/** An IEEE binary16 bit pattern as a Number (exact). */
export function halfToFloat(h) {
  const sign = h & 0x8000 ? -1 : 1;
  const exp = (h >> 10) & 0x1f;
  const man = h & 0x3ff;
  if (exp === 0) return sign * man * 2 ** -24;
  if (exp === 31) return man ? NaN : sign * Infinity;
  return sign * (1 + man / 1024) * 2 ** (exp - 15);
}

/** A HeadPose: binary16 weights (a Blob) as a Float32Array, and its moved nodes. */
function headPose(r) {
  const blob = r.blob();
  if (blob.length % 2 !== 0) throw new DecodeError(`${blob.length} bytes of binary16 weights`);
  const weights = new Float32Array(blob.length / 2);
  for (let i = 0; i < weights.length; i++) {
    weights[i] = halfToFloat(r.view.getUint16(blob.offset + 2 * i, true));
  }
  const joints = r.vec(() => ({
    node: r.u32(),
    rotation: [r.f32(), r.f32(), r.f32(), r.f32()],
    translation: r.option(() => r.vec3()),
    scale: r.option(() => r.vec3()),
  }));
  return { weights, joints };
}

function checkPoses(msg) {
  msg.heads.forEach((h, i) => {
    if (h.buffer !== HEAD_UNCHANGED && h.buffer !== HEAD_MISSING && h.buffer >= msg.poses.length) {
      throw new DecodeError(`head ${i} names pose ${h.buffer} of ${msg.poses.length}`);
    }
  });
}

/**
 * Decodes a `POST /v1/crowd/frame` answer to `"format": "weights"` (bincode CrowdPoseResponse).
 * @param {ArrayBuffer} buffer
 * @returns {{format: 'weights', poses: object[], heads: {head: number, buffer: number}[], timings: object}}
 */
export function decodeCrowdPoses(buffer) {
  const r = new Reader(buffer);
  const format = r.enumIndex(FORMATS, 'Format');
  if (format !== 'weights') throw new DecodeError(`a ${format} answer, not weights`);
  const msg = {
    format,
    poses: r.vec(() => headPose(r)),
    heads: r.vec(() => headBuffer(r)),
    timings: timings(r),
  };
  checkPoses(msg);
  r.end();
  return msg;
}

/**
 * The bytes of the message a PackedMessage holds, decompressed with the browser's own
 * DecompressionStream ("deflate" reads a zlib stream, RFC 1950, as the server sends it). A
 * claimed length past MAX_UNPACKED_BYTES is refused before anything is inflated, and inflating
 * stops as soon as the output passes the claimed length.
 * @param {{encoding: string, length: number, data: {offset: number, length: number}}} packed
 * @param {ArrayBuffer} buffer the packed message
 * @returns {Promise<ArrayBuffer>} exactly `packed.length` bytes, starting at offset 0 (so that
 *   the inner message's 16-byte payload alignment holds)
 */
export async function unpack(packed, buffer) {
  if (packed.encoding !== 'deflate') {
    throw new DecodeError(`a ${packed.encoding} packed message (this viewer asks for deflate and reads only that)`);
  }
  if (packed.length > MAX_UNPACKED_BYTES) {
    throw new DecodeError(`a packed message claims ${packed.length} bytes, more than ${MAX_UNPACKED_BYTES}`);
  }
  const ds = new DecompressionStream('deflate');
  const writer = ds.writable.getWriter();
  // Failures show up on the reading side; the writer's own promises only repeat them.
  writer.write(new Uint8Array(buffer, packed.data.offset, packed.data.length)).catch(() => {});
  writer.close().catch(() => {});
  const reader = ds.readable.getReader();
  const chunks = [];
  let n = 0;
  try {
    for (;;) {
      const { done, value } = await reader.read();
      if (done) break;
      n += value.length;
      if (n > packed.length) throw new DecodeError(`a packed message of more bytes than the ${packed.length} it claimed`);
      chunks.push(value);
    }
  } catch (e) {
    reader.cancel().catch(() => {});
    if (e instanceof DecodeError) throw e;
    throw new DecodeError(`bad deflate data: ${e.message}`);
  }
  if (n !== packed.length) throw new DecodeError(`a packed message of ${n} bytes claimed ${packed.length}`);
  if (chunks.length === 1 && chunks[0].byteOffset === 0 && chunks[0].byteLength === chunks[0].buffer.byteLength) {
    return chunks[0].buffer;
  }
  const out = new Uint8Array(n);
  let at = 0;
  for (const c of chunks) {
    out.set(c, at);
    at += c.length;
  }
  return out.buffer;
}

/**
 * A head's q16 values from residual planes against its previous values `reference`: the
 * planes are the `n` low bytes then the `n` high bytes of the u16 zigzag of the wrapping int16
 * difference q − reference (format q16r's coding, against the head's own last buffer).
 * @param {Uint8Array} planes 2 × reference.length bytes
 * @param {Int16Array} reference
 * @returns {Int16Array} a new array
 */
export function q16rDecode(planes, reference) {
  const n = reference.length;
  if (planes.length !== 2 * n) {
    throw new DecodeError(`${planes.length} residual bytes for a reference of ${n} components`);
  }
  const out = new Int16Array(n);
  for (let i = 0; i < n; i++) {
    const z = planes[i] | (planes[n + i] << 8);
    // Un-zigzag (z >>> 1 ^ -(z & 1)); the Int16Array store wraps the sum as int16 does.
    out[i] = reference[i] + ((z >>> 1) ^ -(z & 1));
  }
  return out;
}

const COMPONENT_BYTES = { f32: 4, f16: 2, q16: 2 };

/** Payload sizes must match their vertex counts before anything is uploaded to the GPU. */
function checkBuffers(msg) {
  const bytes = COMPONENT_BYTES[msg.format];
  msg.buffers.forEach((b, i) => {
    const want = b.vertices * 3 * bytes;
    if (b.positions.length !== want) {
      throw new DecodeError(`buffer ${i}: ${b.positions.length} position bytes for ${b.vertices} vertices`);
    }
    if (b.normals && b.normals.length !== want) {
      throw new DecodeError(`buffer ${i}: ${b.normals.length} normal bytes for ${b.vertices} vertices`);
    }
    if (msg.format === 'q16' && !b.quantization) {
      throw new DecodeError(`buffer ${i}: q16 without its quantization box`);
    }
  });
  msg.heads.forEach((h, i) => {
    if (h.buffer !== HEAD_UNCHANGED && h.buffer !== HEAD_MISSING && h.buffer >= msg.buffers.length) {
      throw new DecodeError(`head ${i} names buffer ${h.buffer} of ${msg.buffers.length}`);
    }
  });
}

/**
 * A typed array over a blob's bytes: in place when the offset allows it, else a copy.
 * @param {ArrayBuffer} buffer the message
 * @param {{offset: number, length: number}} blob
 * @param {'f32'|'f16'|'q16'} format
 */
export function typedView(buffer, blob, format) {
  const Type = format === 'f32' ? Float32Array : format === 'q16' ? Int16Array : Uint16Array;
  const size = Type.BYTES_PER_ELEMENT;
  if (blob.offset % size === 0) return new Type(buffer, blob.offset, blob.length / size);
  return new Type(buffer.slice(blob.offset, blob.offset + blob.length));
}
