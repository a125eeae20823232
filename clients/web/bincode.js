// A reader for the server's bincode messages, written from proto/README.md ("bincode" and
// "Crowd sessions"): bincode 2, standard configuration (little-endian, varint integers).
//
// Only what the viewer receives is decoded: the stream's StreamMessage. Vertex payloads are not
// copied: a Blob is returned as its byte offset and length in the message's ArrayBuffer, and
// typedView() views it in place (the server pads each payload to a 16-byte offset), copying
// only when an odd offset makes a view impossible.

/** HeadBuffer.buffer of a head whose job did not change: keep drawing what it had. */
export const HEAD_UNCHANGED = 0xffffffff;
/** HeadBuffer.buffer of a head with nothing to draw (its rig or clip was deleted). */
export const HEAD_MISSING = 0xfffffffe;

/** Scalar formats by their varint variant index. */
export const FORMATS = ['f32', 'f16', 'q16'];
/** Image formats of TickFrame by their variant index. */
export const IMAGE_FORMATS = ['png', 'jpeg', 'rgba'];

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
 * @param {ArrayBuffer} buffer
 * @returns {{kind: 'vertices', tick: number, format: string, normals: boolean,
 *   layout: object[]|null, buffers: object[], heads: {head: number, buffer: number}[],
 *   timings: object} | {kind: 'frame', tick: number, format: string, width: number,
 *   height: number, image: {offset: number, length: number}}}
 */
export function decodeStreamMessage(buffer) {
  const r = new Reader(buffer);
  const variant = r.varint();
  let msg;
  if (variant === 0) {
    msg = {
      kind: 'vertices',
      tick: r.varint(),
      format: r.enumIndex(FORMATS, 'Format'),
      normals: r.bool(),
      layout: r.option(() => r.vec(() => sessionHead(r))),
      buffers: r.vec(() => frameBuffer(r)),
      heads: r.vec(() => headBuffer(r)),
      timings: timings(r),
    };
    checkBuffers(msg);
  } else if (variant === 1) {
    msg = {
      kind: 'frame',
      tick: r.varint(),
      format: r.enumIndex(IMAGE_FORMATS, 'ImageFormat'),
      width: r.u32(),
      height: r.u32(),
      image: r.blob(),
    };
  } else {
    throw new DecodeError(`StreamMessage variant ${variant}`);
  }
  r.end();
  return msg;
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
