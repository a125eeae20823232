// The WebGL2 renderer: one index buffer per (rig, mesh level), one pair of vertex buffers per
// unique blended buffer the heads show (uploaded when first drawn), and one draw per head and
// primitive with the head's placement. q16 positions stay 16-bit on the GPU: the vertex shader dequantizes them
// with the buffer's box (x = min + (q + 32768) × step), and q16 normals are read as normalized
// shorts. Lighting is Lambert plus a Blinn highlight from a headlight at the eye.

const VERTEX_SHADER = `#version 300 es
layout(location = 0) in vec3 a_position;
layout(location = 1) in vec3 a_normal;
uniform mat4 u_view_proj;
uniform mat4 u_model;
uniform vec3 u_qmin;
uniform vec3 u_qstep;
uniform float u_qbias;
out vec3 v_world;
out vec3 v_normal;
void main() {
  vec3 p = u_qmin + (a_position + u_qbias) * u_qstep;
  vec4 world = u_model * vec4(p, 1.0);
  v_world = world.xyz;
  // Placements are rotation times uniform scale, so the model matrix turns normals too.
  v_normal = mat3(u_model) * a_normal;
  gl_Position = u_view_proj * world;
}
`;

const FRAGMENT_SHADER = `#version 300 es
precision highp float;
in vec3 v_world;
in vec3 v_normal;
uniform vec3 u_eye;
uniform vec3 u_color;
out vec4 o_color;
void main() {
  vec3 n = normalize(v_normal);
  if (!gl_FrontFacing) n = -n;
  vec3 v = normalize(u_eye - v_world);
  // A headlight: the light comes from the eye, so the half vector is the view vector.
  float lambert = max(dot(n, v), 0.0);
  float spec = pow(max(dot(n, v), 0.0), 48.0) * 0.25;
  vec3 linear = u_color * (0.18 + 0.82 * lambert) + vec3(spec);
  o_color = vec4(pow(linear, vec3(1.0 / 2.2)), 1.0);
}
`;

/** The background, sRGB: the server's default render background. */
export const BACKGROUND = [46, 50, 56];

/** Linear base colours by primitive name. */
function primitiveColor(name) {
  if (/eye|iris|pupil|cornea/i.test(name)) return [0.75, 0.75, 0.72];
  if (/teeth|tooth/i.test(name)) return [0.8, 0.78, 0.7];
  if (/tongue|mouth|lip/i.test(name)) return [0.55, 0.2, 0.2];
  return [0.72, 0.48, 0.36];
}

export class RenderError extends Error {
  constructor(message) {
    super(message);
    this.name = 'RenderError';
  }
}

export class Renderer {
  /** @param {HTMLCanvasElement} canvas */
  constructor(canvas) {
    this.canvas = canvas;
    const gl = canvas.getContext('webgl2', { antialias: true, preserveDrawingBuffer: false });
    if (!gl) throw new RenderError('this browser cannot create a WebGL2 context');
    this.gl = gl;
    this.program = link(gl, VERTEX_SHADER, FRAGMENT_SHADER);
    this.uniforms = {};
    for (const name of ['u_view_proj', 'u_model', 'u_qmin', 'u_qstep', 'u_qbias', 'u_eye', 'u_color']) {
      this.uniforms[name] = gl.getUniformLocation(this.program, name);
    }
    this.topologies = new Map();
    this.free = [];
    this.live = 0;
    gl.enable(gl.DEPTH_TEST);
  }

  /** Keeps the index buffer and primitive ranges of a MeshResponse under `key`. */
  setTopology(key, mesh, indices) {
    const gl = this.gl;
    const old = this.topologies.get(key);
    if (old) gl.deleteBuffer(old.ibo);
    const ibo = gl.createBuffer();
    // An index buffer is bound to a vertex array object when drawn; binding it to
    // ELEMENT_ARRAY_BUFFER here without one would change whichever VAO is current.
    gl.bindVertexArray(null);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ibo);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, indices, gl.STATIC_DRAW);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, null);
    this.topologies.set(key, {
      ibo,
      vertices: mesh.vertices,
      primitives: mesh.primitives.map((p) => ({
        first: p.first_index,
        count: p.indices,
        color: primitiveColor(p.name),
      })),
    });
  }

  topology(key) {
    return this.topologies.get(key) || null;
  }

  /**
   * Describes one blended buffer; returns the entry heads draw with. Nothing goes to the GPU
   * yet: an entry is uploaded when it is first drawn, so that when ticks arrive faster than
   * frames, buffers replaced before the next frame cost no upload at all.
   * @param {string} key the topology it needs
   * @param {number} vertices
   * @param {'f32'|'f16'|'q16'} format
   * @param {ArrayBufferView} positions
   * @param {ArrayBufferView|null} normals
   * @param {{min: number[], step: number[]}|null} quantization
   */
  entry(key, vertices, format, positions, normals, quantization) {
    const q16 = format === 'q16';
    return {
      key,
      vertices,
      format,
      positions,
      normals,
      qmin: q16 ? quantization.min : [0, 0, 0],
      qstep: q16 ? quantization.step : [1, 1, 1],
      qbias: q16 ? 32768 : 0,
      gl: null,
      ibo: null,
    };
  }

  /** Uploads an entry's arrays into vertex buffers from the pool, then lets the arrays go. */
  realize(entry) {
    const gl = this.gl;
    const objects = this.free.pop() || {
      vao: gl.createVertexArray(),
      positions: gl.createBuffer(),
      normals: gl.createBuffer(),
    };
    this.live++;
    const format = entry.format;
    const type = format === 'f32' ? gl.FLOAT : format === 'f16' ? gl.HALF_FLOAT : gl.SHORT;
    gl.bindVertexArray(objects.vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, objects.positions);
    gl.bufferData(gl.ARRAY_BUFFER, entry.positions, gl.STREAM_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 3, type, false, 0, 0);
    if (entry.normals) {
      gl.bindBuffer(gl.ARRAY_BUFFER, objects.normals);
      gl.bufferData(gl.ARRAY_BUFFER, entry.normals, gl.STREAM_DRAW);
      gl.enableVertexAttribArray(1);
      // q16 normals are n = q / 32767: exactly what a normalized short reads as.
      gl.vertexAttribPointer(1, 3, type, format === 'q16', 0, 0);
    } else {
      gl.disableVertexAttribArray(1);
      gl.vertexAttrib3f(1, 0, 0, 1);
    }
    gl.bindVertexArray(null);
    gl.bindBuffer(gl.ARRAY_BUFFER, null);
    entry.gl = objects;
    entry.ibo = null; // The pooled vertex array may hold another topology's index buffer.
    entry.positions = null;
    entry.normals = null;
  }

  /** An entry no head uses any more: its vertex buffers go back to the pool. */
  release(entry) {
    entry.positions = null;
    entry.normals = null;
    const objects = entry.gl;
    if (!objects) return;
    entry.gl = null;
    this.live--;
    if (this.free.length < 64) {
      this.free.push(objects);
    } else {
      const gl = this.gl;
      gl.deleteVertexArray(objects.vao);
      gl.deleteBuffer(objects.positions);
      gl.deleteBuffer(objects.normals);
    }
  }

  /** Matches the drawing buffer to the canvas's size on screen. */
  resize() {
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(this.canvas.clientWidth * dpr));
    const h = Math.max(1, Math.round(this.canvas.clientHeight * dpr));
    if (this.canvas.width !== w || this.canvas.height !== h) {
      this.canvas.width = w;
      this.canvas.height = h;
      return true;
    }
    return false;
  }

  /**
   * Draws the crowd.
   * @param {{viewProj: Float32Array, eye: number[]}} view
   * @param {{entry: object, model: Float32Array}[]} heads
   * @returns {number} heads drawn
   */
  draw(view, heads) {
    const gl = this.gl;
    const u = this.uniforms;
    gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    gl.clearColor(BACKGROUND[0] / 255, BACKGROUND[1] / 255, BACKGROUND[2] / 255, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.useProgram(this.program);
    gl.uniformMatrix4fv(u.u_view_proj, false, view.viewProj);
    gl.uniform3fv(u.u_eye, view.eye);
    let drawn = 0;
    let bound = null;
    for (const h of heads) {
      const e = h.entry;
      const topo = e && this.topologies.get(e.key);
      // A buffer whose vertex count is not its topology's (the rig's mesh levels changed
      // since the topology was fetched) is not drawn: its indices would not fit.
      if (!topo || topo.vertices !== e.vertices) continue;
      if (bound !== e) {
        if (!e.gl) this.realize(e);
        gl.bindVertexArray(e.gl.vao);
        if (e.ibo !== topo.ibo) {
          gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, topo.ibo);
          e.ibo = topo.ibo;
        }
        gl.uniform3fv(u.u_qmin, e.qmin);
        gl.uniform3fv(u.u_qstep, e.qstep);
        gl.uniform1f(u.u_qbias, e.qbias);
        bound = e;
      }
      gl.uniformMatrix4fv(u.u_model, false, h.model);
      for (const p of topo.primitives) {
        gl.uniform3fv(u.u_color, p.color);
        gl.drawElements(gl.TRIANGLES, p.count, gl.UNSIGNED_INT, p.first * 4);
      }
      drawn++;
    }
    gl.bindVertexArray(null);
    return drawn;
  }
}

function compile(gl, type, source) {
  const s = gl.createShader(type);
  gl.shaderSource(s, source);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) {
    throw new RenderError(`shader: ${gl.getShaderInfoLog(s)}`);
  }
  return s;
}

function link(gl, vs, fs) {
  const p = gl.createProgram();
  gl.attachShader(p, compile(gl, gl.VERTEX_SHADER, vs));
  gl.attachShader(p, compile(gl, gl.FRAGMENT_SHADER, fs));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) {
    throw new RenderError(`program: ${gl.getProgramInfoLog(p)}`);
  }
  return p;
}
