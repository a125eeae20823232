// The WebGL2 renderer: one index buffer (and, for a textured rig, one texture coordinate
// buffer) per (rig, mesh level), one pair of vertex buffers per unique blended buffer the heads
// show (uploaded when first drawn), and one draw per head and primitive with the head's
// placement. q16 positions stay 16-bit on the GPU: the vertex shader dequantizes them with the
// buffer's box (x = min + (q + 32768) × step), and q16 normals are read as normalized shorts.
// Texture coordinates never change with the weights, so they are static per topology and bound
// beside the streamed buffers in each head's vertex array: appearance costs no byte per tick.
//
// Primitives with a glTF material (GET /v1/rigs/{id}/materials) are shaded as glTF 2.0's
// Appendix B has it: metallic-roughness with GGX, height-correlated Smith and Schlick, under a
// key and a fill light that turn with the camera and a sky/ground hemisphere (the server's
// renderer's lights), sRGB out and no tone mapping; base colour and emissive textures are
// sRGB, the others linear, each with the file's sampler, texture coordinate set and
// KHR_texture_transform, and COLOR_0 multiplies the base colour. MASK discards, BLEND is
// drawn after everything opaque, far heads first, without writing depth; single-sided
// materials cull back faces. A material's expression layers (GET /v1/rigs/{id}/layers: wrinkle
// maps, a clip's PCA texture) are one RGBA16F 2D array with the server's texels and mips, summed
// onto the base colour with each head's coefficients as the server's render.wgsl sums them.
// Primitives without a material keep the plaster look: Lambert plus a Blinn highlight from a
// headlight, coloured by primitive name.

const VERTEX_SHADER = `#version 300 es
layout(location = 0) in vec3 a_position;
layout(location = 1) in vec3 a_normal;
layout(location = 2) in vec2 a_uv;
layout(location = 3) in vec2 a_uv1;
layout(location = 4) in vec4 a_color;
uniform mat4 u_view_proj;
uniform mat4 u_model;
uniform vec3 u_qmin;
uniform vec3 u_qstep;
uniform float u_qbias;
out vec3 v_world;
out vec3 v_normal;
out vec2 v_uv;
out vec2 v_uv1;
out vec4 v_color;
void main() {
  vec3 p = u_qmin + (a_position + u_qbias) * u_qstep;
  vec4 world = u_model * vec4(p, 1.0);
  v_world = world.xyz;
  // Placements are rotation times uniform scale, so the model matrix turns normals too.
  v_normal = mat3(u_model) * a_normal;
  v_uv = a_uv;
  v_uv1 = a_uv1;
  v_color = a_color;
  gl_Position = u_view_proj * world;
}
`;

const PLASTER_SHADER = `#version 300 es
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

/** Texture units, one per material slot; u_uv[] has the same order. */
const BASE = 0;
const METALLIC_ROUGHNESS = 1;
const NORMAL = 2;
const OCCLUSION = 3;
const EMISSIVE = 4;
const SLOTS = 5;
/** The texture unit of a material's expression layers (a TEXTURE_2D_ARRAY). */
const LAYER_UNIT = SLOTS;
/** Most layers a material sums (crowdmorph_core::rig::MAX_LAYERS, the server's shader's). */
export const MAX_LAYERS = 16;

const PBR_SHADER = `#version 300 es
precision highp float;
in vec3 v_world;
in vec3 v_normal;
in vec2 v_uv;
in vec2 v_uv1;
// COLOR_0 (white without): it multiplies the base colour.
in vec4 v_color;
uniform vec3 u_eye;
// World-space unit directions toward the key and fill lights, their irradiance in w.
uniform vec4 u_key;
uniform vec4 u_fill;
// The ambient hemisphere's irradiance along the camera's up (u_up) and opposite it.
uniform vec3 u_up;
uniform vec3 u_sky;
uniform vec3 u_ground;
uniform vec4 u_base_factor;
// emissiveFactor × KHR_materials_emissive_strength.
uniform vec3 u_emissive;
// metallicFactor, roughnessFactor, normalTexture.scale, occlusionTexture.strength.
uniform vec4 u_pbr;
// Alpha cutoff (-1 unless MASK), unlit, normal map bound, blended: the last three 0 or 1.
uniform vec4 u_mode;
// KHR_texture_transform per slot (base, metallic-roughness, normal, occlusion, emissive).
uniform mat3 u_uv[${SLOTS}];
// The texture coordinate set (0 or 1) per slot.
uniform int u_set[${SLOTS}];
uniform sampler2D u_textures[${SLOTS}];
// Expression layers (signed linear RGBA, RGBA16F), read through the base colour's sampler,
// set and transform, and each one's coefficient for this head; u_layer_count is 0 without.
uniform highp sampler2DArray u_layers;
uniform int u_layer_count;
uniform float u_coefficients[${MAX_LAYERS}];
out vec4 o_color;

const float PI = 3.141592653589793;

vec2 slot_uv(int i) {
  return (u_uv[i] * vec3(u_set[i] == 1 ? v_uv1 : v_uv, 1.0)).xy;
}

vec4 slot(int i) {
  vec2 uv = slot_uv(i);
  switch (i) {
    case ${BASE}: return texture(u_textures[${BASE}], uv);
    case ${METALLIC_ROUGHNESS}: return texture(u_textures[${METALLIC_ROUGHNESS}], uv);
    case ${NORMAL}: return texture(u_textures[${NORMAL}], uv);
    case ${OCCLUSION}: return texture(u_textures[${OCCLUSION}], uv);
    default: return texture(u_textures[${EMISSIVE}], uv);
  }
}

// The exact sRGB encoding: the canvas is composited as sRGB.
vec3 encode_srgb(vec3 c) {
  c = clamp(c, 0.0, 1.0);
  return mix(c * 12.92, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), c));
}

// The normal map's normal. No tangents come from the server, so the frame is the cotangent
// frame of the screen-space derivatives of position and texture coordinate (Schüler): t along
// +u, b along +v. glTF's tangent space has +Y up the image, which is -v.
vec3 mapped_normal(vec3 n) {
  vec2 uv = slot_uv(${NORMAL});
  vec3 dpx = dFdx(v_world);
  vec3 dpy = dFdy(v_world);
  vec2 dux = dFdx(uv);
  vec2 duy = dFdy(uv);
  vec3 dpy_perp = cross(dpy, n);
  vec3 dpx_perp = cross(n, dpx);
  vec3 t = dpy_perp * dux.x + dpx_perp * duy.x;
  vec3 b = dpy_perp * dux.y + dpx_perp * duy.y;
  float len2 = max(dot(t, t), dot(b, b));
  if (len2 < 1e-24) return n; // No texture coordinates to speak of here.
  float k = inversesqrt(len2);
  vec3 tn = slot(${NORMAL}).xyz * 2.0 - 1.0;
  tn.xy *= u_pbr.z;
  return normalize(mat3(t * k, -b * k, n) * tn);
}

// One directional light through glTF's BRDF: (1 - F) c_diff / π + F D V.
vec3 direct(vec3 n, vec3 v, vec4 light, vec3 c_diff, vec3 f0, float alpha) {
  vec3 l = light.xyz;
  float nl = dot(n, l);
  if (nl <= 0.0) return vec3(0.0);
  vec3 h = normalize(l + v);
  float nv = max(dot(n, v), 1e-4);
  float nh = max(dot(n, h), 0.0);
  float vh = max(dot(v, h), 0.0);
  vec3 f = f0 + (1.0 - f0) * pow(1.0 - vh, 5.0);
  float a2 = alpha * alpha;
  float dd = nh * nh * (a2 - 1.0) + 1.0;
  float d = a2 / (PI * dd * dd);
  float vis = 0.5 / (nl * sqrt(nv * nv * (1.0 - a2) + a2) + nv * sqrt(nl * nl * (1.0 - a2) + a2));
  return light.w * nl * ((1.0 - f) * c_diff / PI + f * d * vis);
}

void main() {
  // The server's render.wgsl: base(uv) + Σ c_k · layer_k(uv) in linear RGBA, clamped to
  // [0, 1], then the factor and the vertex colour.
  vec4 tex = slot(${BASE});
  if (u_layer_count > 0) {
    vec2 luv = slot_uv(${BASE});
    for (int k = 0; k < u_layer_count; k++) {
      tex += u_coefficients[k] * texture(u_layers, vec3(luv, float(k)));
    }
    tex = clamp(tex, 0.0, 1.0);
  }
  vec4 base = u_base_factor * v_color * tex;
  if (base.a < u_mode.x) discard;
  float alpha_out = u_mode.w > 0.5 ? base.a : 1.0;
  vec3 emissive = u_emissive * slot(${EMISSIVE}).rgb;
  if (u_mode.y > 0.5) {
    // KHR_materials_unlit: the base colour as it is.
    o_color = vec4(encode_srgb(base.rgb), alpha_out);
    return;
  }
  vec3 n = normalize(v_normal);
  if (!gl_FrontFacing) n = -n;
  if (u_mode.z > 0.5) n = mapped_normal(n);
  vec4 mr = slot(${METALLIC_ROUGHNESS});
  float metallic = clamp(u_pbr.x * mr.b, 0.0, 1.0);
  // A floor on roughness (brdf::MIN_ROUGHNESS) keeps a mirror's highlight from a delta light
  // finite.
  float roughness = clamp(u_pbr.y * mr.g, 0.0525, 1.0);
  float alpha = roughness * roughness;
  vec3 c_diff = mix(base.rgb, vec3(0.0), metallic);
  vec3 f0 = mix(vec3(0.04), base.rgb, metallic);
  vec3 v = normalize(u_eye - v_world);
  vec3 color = direct(n, v, u_key, c_diff, f0, alpha) + direct(n, v, u_fill, c_diff, f0, alpha);
  float occlusion = 1.0 + u_pbr.w * (slot(${OCCLUSION}).r - 1.0);
  // The server's hemisphere ambient (render.wgsl): diffuse only, irradiance by the normal's
  // side of the camera's up.
  vec3 ambient = mix(u_ground, u_sky, 0.5 + 0.5 * dot(n, u_up));
  color += ambient * c_diff / PI * occlusion;
  o_color = vec4(encode_srgb(color + emissive), alpha_out);
}
`;

/**
 * The lights of textured rigs: the server renderer's (crates/engine/src/render/brdf.rs,
 * KEY_LIGHT, FILL_LIGHT, SKY, GROUND), in view space (x right, y up, z toward the viewer) so
 * that they turn with the camera as the server's do: a key from the upper left and in front, a
 * dimmer fill from the lower right, and a hemisphere of sky along the camera's up and ground
 * opposite. The viewer's end-to-end test compares its screenshot with the server's render of
 * the same camera, so a change there must come here too.
 */
const KEY = { dir: [-0.5, 0.6, 0.8], irradiance: 2.4 };
const FILL = { dir: [0.7, -0.2, 0.6], irradiance: 0.85 };
const SKY = [0.7, 0.7, 0.7];
const GROUND = [0.42, 0.42, 0.42];

/** The background, sRGB: the server's default render background. */
export const BACKGROUND = [46, 50, 56];

/** Linear base colours by primitive name. */
function primitiveColor(name) {
  if (/eye|iris|pupil|cornea/i.test(name)) return [0.75, 0.75, 0.72];
  if (/teeth|tooth/i.test(name)) return [0.8, 0.78, 0.7];
  if (/tongue|mouth|lip/i.test(name)) return [0.55, 0.2, 0.2];
  return [0.72, 0.48, 0.36];
}

/** glTF sampler codes, which are WebGL's own enums. */
const FILTERS = new Set([0x2600, 0x2601, 0x2700, 0x2701, 0x2702, 0x2703]);
const WRAPS = new Set([0x812f, 0x8370, 0x2901]);
const MIPMAPPED = new Set([0x2700, 0x2701, 0x2702, 0x2703]);

const IDENTITY3 = [1, 0, 0, 0, 1, 0, 0, 0, 1];

function finite(x, fallback) {
  return typeof x === 'number' && Number.isFinite(x) ? x : fallback;
}

function numbers(a, n, fallback) {
  return Array.isArray(a) && a.length === n && a.every((x) => Number.isFinite(x)) ? a : fallback;
}

/**
 * KHR_texture_transform as a column-major mat3: T · R · S, with the rows the server's
 * UvTransform uses (u' = c·sx·u + s·sy·v + ox, v' = −s·sx·u + c·sy·v + oy): counter-clockwise
 * with v down, as three.js and the Khronos TextureTransformTest have it.
 */
function uvTransform(t) {
  if (!t) return IDENTITY3;
  const [ox, oy] = numbers(t.offset, 2, [0, 0]);
  const [sx, sy] = numbers(t.scale, 2, [1, 1]);
  const r = finite(t.rotation, 0);
  const c = Math.cos(r);
  const s = Math.sin(r);
  return [c * sx, -s * sx, 0, s * sy, c * sy, 0, ox, oy, 1];
}

function normalize3(a) {
  const l = Math.hypot(a[0], a[1], a[2]) || 1;
  return [a[0] / l, a[1] / l, a[2] / l];
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
    this.plaster = program(gl, VERTEX_SHADER, PLASTER_SHADER, ['u_color']);
    this.pbr = program(gl, VERTEX_SHADER, PBR_SHADER, [
      'u_key',
      'u_fill',
      'u_up',
      'u_sky',
      'u_ground',
      'u_base_factor',
      'u_emissive',
      'u_pbr',
      'u_mode',
      'u_uv',
      'u_set',
      'u_textures',
      'u_layers',
      'u_layer_count',
      'u_coefficients',
    ]);
    gl.useProgram(this.pbr.program);
    gl.uniform1iv(this.pbr.u.u_textures, [0, 1, 2, 3, 4]);
    gl.uniform1i(this.pbr.u.u_layers, LAYER_UNIT);
    // Expression layers by "rig NUL material": {tex, count, sources: [{input, clamp}]}.
    this.layers = new Map();
    this.coefficients = new Float32Array(MAX_LAYERS);
    // What the layer unit samples when a material has none: one layer of zeros.
    this.noLayers = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.noLayers);
    gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl.RGBA16F, 1, 1, 1);
    gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, 0, 1, 1, 1, gl.RGBA, gl.HALF_FLOAT, new Uint16Array(4));
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, null);
    this.topologies = new Map();
    this.free = [];
    this.live = 0;
    // Appearance: materials by rig, textures by (URI, colour space), samplers by their codes.
    this.materials = new Map();
    this.textures = new Map();
    this.samplers = new Map();
    this.maxTextureSize = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    const aniso = gl.getExtension('EXT_texture_filter_anisotropic');
    this.anisotropy = aniso ? [aniso.TEXTURE_MAX_ANISOTROPY_EXT, Math.min(8, gl.getParameter(aniso.MAX_TEXTURE_MAX_ANISOTROPY_EXT))] : null;
    // What a slot samples while its texture loads, or when it has none: white multiplies the
    // factors by one; the flat normal is never read (u_mode.z is 0 without a normal map).
    this.white = solidTexture(gl, [255, 255, 255, 255]);
    // Heads whose topology has no texture coordinates read (0, 0), no colours white.
    gl.vertexAttrib2f(2, 0, 0);
    gl.vertexAttrib2f(3, 0, 0);
    gl.vertexAttrib4f(4, 1, 1, 1, 1);
    gl.enable(gl.DEPTH_TEST);
    gl.cullFace(gl.BACK);
  }

  /**
   * Keeps the index buffer, texture coordinates and primitive ranges of a MeshResponse under
   * `key`, for heads of rig `rig`.
   * @param {Float32Array|null} uvs u, v per vertex, or null when the mesh has none
   */
  setTopology(key, rig, mesh, indices, uvs, uvs1, colors) {
    const gl = this.gl;
    const old = this.topologies.get(key);
    if (old) {
      gl.deleteBuffer(old.ibo);
      for (const b of [old.uvs, old.uvs1, old.colors]) if (b) gl.deleteBuffer(b);
    }
    const ibo = gl.createBuffer();
    // An index buffer is bound to a vertex array object when drawn; binding it to
    // ELEMENT_ARRAY_BUFFER here without one would change whichever VAO is current.
    gl.bindVertexArray(null);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ibo);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, indices, gl.STATIC_DRAW);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, null);
    const buffer = (data) => {
      if (!data) return null;
      const b = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, b);
      gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
      gl.bindBuffer(gl.ARRAY_BUFFER, null);
      return b;
    };
    const { min, max } = mesh.bbox;
    this.topologies.set(key, {
      rig,
      ibo,
      uvs: buffer(uvs),
      uvs1: buffer(uvs1),
      colors: buffer(colors),
      vertices: mesh.vertices,
      center: [0, 1, 2].map((a) => (min[a] + max[a]) / 2),
      primitives: mesh.primitives.map((p) => ({
        first: p.first_index,
        count: p.indices,
        color: primitiveColor(p.name),
        material: Number.isInteger(p.material) ? p.material : null,
      })),
    });
  }

  topology(key) {
    return this.topologies.get(key) || null;
  }

  /**
   * Takes a rig's `GET /v1/rigs/{id}/materials` and returns the images its materials sample
   * that are not on the GPU yet, each with the colour spaces it is needed in:
   * `[{uri, width, height, srgb, linear}]`. Until setImage() brings one, its slots sample white.
   */
  setMaterials(rig, doc) {
    const textures = Array.isArray(doc.textures) ? doc.textures : [];
    const images = Array.isArray(doc.images) ? doc.images : [];
    const samplers = Array.isArray(doc.samplers) ? doc.samplers : [];
    const wanted = new Map();
    const slot = (ref, srgb) => {
      if (!ref || !Number.isInteger(ref.index)) return null;
      const transform = ref.extensions && ref.extensions.KHR_texture_transform;
      const set = transform && Number.isInteger(transform.texCoord) ? transform.texCoord : ref.texCoord || 0;
      // The server sends texture coordinate sets 0 and 1: a slot on another set is drawn
      // with its factors alone.
      if (set !== 0 && set !== 1) return null;
      const texture = textures[ref.index];
      const image = texture && images[texture.source];
      if (!image || typeof image.uri !== 'string') return null;
      const key = `${srgb ? 'srgb' : 'linear'} ${image.uri}`;
      if (!this.textures.has(key)) {
        const w = wanted.get(image.uri) || { uri: image.uri, width: image.width, height: image.height, srgb: false, linear: false };
        w[srgb ? 'srgb' : 'linear'] = true;
        wanted.set(image.uri, w);
      }
      return { key, set, sampler: this.sampler(Number.isInteger(texture.sampler) ? samplers[texture.sampler] : null), uv: uvTransform(transform) };
    };
    const materials = (Array.isArray(doc.materials) ? doc.materials : []).map((m, index) => {
      const pbr = m.pbrMetallicRoughness || {};
      const ext = m.extensions || {};
      const strength = ext.KHR_materials_emissive_strength ? finite(ext.KHR_materials_emissive_strength.emissiveStrength, 1) : 1;
      const emissive = numbers(m.emissiveFactor, 3, [0, 0, 0]).map((x) => x * strength);
      const slots = new Array(SLOTS).fill(null);
      slots[BASE] = slot(pbr.baseColorTexture, true);
      slots[METALLIC_ROUGHNESS] = slot(pbr.metallicRoughnessTexture, false);
      slots[NORMAL] = slot(m.normalTexture, false);
      slots[OCCLUSION] = slot(m.occlusionTexture, false);
      slots[EMISSIVE] = slot(m.emissiveTexture, true);
      const uv = new Float32Array(9 * SLOTS);
      slots.forEach((s, i) => uv.set(s ? s.uv : IDENTITY3, 9 * i));
      const sets = new Int32Array(slots.map((s) => (s ? s.set : 0)));
      return {
        rig,
        index,
        base: numbers(pbr.baseColorFactor, 4, [1, 1, 1, 1]),
        emissive,
        pbr: [
          finite(pbr.metallicFactor, 1),
          finite(pbr.roughnessFactor, 1),
          finite(m.normalTexture && m.normalTexture.scale, 1),
          finite(m.occlusionTexture && m.occlusionTexture.strength, 1),
        ],
        cutoff: m.alphaMode === 'MASK' ? finite(m.alphaCutoff, 0.5) : -1,
        blend: m.alphaMode === 'BLEND',
        unlit: !!ext.KHR_materials_unlit,
        doubleSided: !!m.doubleSided,
        slots,
        uv,
        sets,
      };
    });
    this.materials.set(rig, materials);
    return [...wanted.values()];
  }

  /** A WebGL sampler for a glTF sampler (or glTF's default, repeat and trilinear, for null). */
  sampler(s) {
    const pick = (v, allowed, fallback) => (allowed.has(v) ? v : fallback);
    const gl = this.gl;
    const mag = pick(s && s.magFilter, new Set([gl.NEAREST, gl.LINEAR]), gl.LINEAR);
    const min = pick(s && s.minFilter, FILTERS, gl.LINEAR_MIPMAP_LINEAR);
    const wrapS = pick(s && s.wrapS, WRAPS, gl.REPEAT);
    const wrapT = pick(s && s.wrapT, WRAPS, gl.REPEAT);
    const id = `${mag} ${min} ${wrapS} ${wrapT}`;
    let out = this.samplers.get(id);
    if (!out) {
      out = gl.createSampler();
      gl.samplerParameteri(out, gl.TEXTURE_MAG_FILTER, mag);
      gl.samplerParameteri(out, gl.TEXTURE_MIN_FILTER, min);
      gl.samplerParameteri(out, gl.TEXTURE_WRAP_S, wrapS);
      gl.samplerParameteri(out, gl.TEXTURE_WRAP_T, wrapT);
      // Faces seen at a slant stay sharp where the file asks for mipmaps.
      if (this.anisotropy && MIPMAPPED.has(min)) gl.samplerParameterf(out, this.anisotropy[0], this.anisotropy[1]);
      this.samplers.set(id, out);
    }
    return out;
  }

  /**
   * Uploads a decoded image in the colour spaces it is wanted in (SRGB8_ALPHA8 for base colour
   * and emissive, RGBA8 for the rest) with a full mip chain. Row 0 of the bitmap, the image's
   * top, becomes t = 0: glTF's v = 0 is the image's top, so v is t as it is.
   * @param {ImageBitmap} bitmap
   */
  setImage(uri, bitmap, { srgb, linear }) {
    const gl = this.gl;
    // Ignored for ImageBitmaps by the WebGL spec (the bitmap's own options decide); set anyway
    // so that no browser that does honour them flips or premultiplies.
    gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
    gl.pixelStorei(gl.UNPACK_PREMULTIPLY_ALPHA_WEBGL, false);
    gl.pixelStorei(gl.UNPACK_COLORSPACE_CONVERSION_WEBGL, gl.NONE);
    const w = bitmap.width;
    const h = bitmap.height;
    const levels = Math.floor(Math.log2(Math.max(w, h, 1))) + 1;
    for (const [wanted, space, format] of [
      [srgb, 'srgb', gl.SRGB8_ALPHA8],
      [linear, 'linear', gl.RGBA8],
    ]) {
      if (!wanted) continue;
      const key = `${space} ${uri}`;
      const old = this.textures.get(key);
      if (old) gl.deleteTexture(old);
      const tex = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.texStorage2D(gl.TEXTURE_2D, levels, format, w, h);
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, gl.RGBA, gl.UNSIGNED_BYTE, bitmap);
      gl.generateMipmap(gl.TEXTURE_2D);
      this.textures.set(key, tex);
    }
    gl.bindTexture(gl.TEXTURE_2D, null);
  }

  /**
   * Uploads material `material` of `rig`'s expression layers, as `GET /v1/rigs/{id}/layers`
   * describes them (`desc`: its `levels` and `layers`) and `GET /v1/rigs/{id}/layers/{m}` gives
   * their texels (`texels`: little-endian binary16 RGBA, layer by layer, each layer's levels
   * largest first, rows top to bottom), as one RGBA16F TEXTURE_2D_ARRAY with the server's mip
   * chain. Row 0 is t = 0, as for images.
   */
  setLayers(rig, material, desc, texels) {
    const gl = this.gl;
    const levels = desc.levels;
    const count = Math.min(desc.layers.length, MAX_LAYERS);
    const [w0, h0] = levels[0];
    if (w0 > this.maxTextureSize || h0 > this.maxTextureSize || desc.layers.length > gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS)) {
      throw new RenderError(`layers of ${w0}×${h0}×${desc.layers.length} are past this GPU's textures`);
    }
    const perLayer = levels.reduce((n, [w, h]) => n + w * h * 8, 0);
    if (texels.byteLength !== perLayer * desc.layers.length) {
      throw new RenderError(`layer texels of ${texels.byteLength} bytes, want ${perLayer * desc.layers.length}`);
    }
    const key = `${rig}\u0000${material}`;
    const old = this.layers.get(key);
    if (old) gl.deleteTexture(old.tex);
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, tex);
    gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 4);
    gl.texStorage3D(gl.TEXTURE_2D_ARRAY, levels.length, gl.RGBA16F, w0, h0, count);
    for (let layer = 0; layer < count; layer++) {
      let at = layer * perLayer;
      levels.forEach(([w, h], level) => {
        const data = new Uint16Array(texels, at, w * h * 4);
        gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, level, 0, 0, layer, w, h, 1, gl.RGBA, gl.HALF_FLOAT, data);
        at += w * h * 8;
      });
    }
    // Used when the material has no base colour sampler (glTF's default: repeat, trilinear).
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MIN_FILTER, gl.LINEAR_MIPMAP_LINEAR);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_WRAP_S, gl.REPEAT);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_WRAP_T, gl.REPEAT);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, null);
    const sources = desc.layers.slice(0, count).map((l) => ({ input: Number.isInteger(l.input) ? l.input : -1, clamp: !!l.clamp }));
    this.layers.set(key, { tex, count, sources });
  }

  /** Materials with expression layers on the GPU. */
  get layerCount() {
    return this.layers.size;
  }

  /**
   * Binds material `m`'s layers, if it has any, with their coefficients for a head whose
   * layer inputs are `inputs` (a layer reading no input, or an input not received yet,
   * counts 0; a clamped one is clamped to [0, 1], as the server's renderer does).
   */
  bindLayers(m, textured, inputs) {
    const gl = this.gl;
    const u = this.pbr.u;
    const l = textured ? this.layers.get(`${m.rig}\u0000${m.index}`) : null;
    gl.activeTexture(gl.TEXTURE0 + LAYER_UNIT);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, l ? l.tex : this.noLayers);
    const base = m.slots[BASE];
    gl.bindSampler(LAYER_UNIT, l && base && this.textures.has(base.key) ? base.sampler : null);
    gl.uniform1i(u.u_layer_count, l ? l.count : 0);
    if (!l) return;
    const c = this.coefficients;
    c.fill(0);
    l.sources.forEach((s, k) => {
      let v = inputs && s.input >= 0 && s.input < inputs.length ? inputs[s.input] : 0;
      if (!Number.isFinite(v)) v = 0;
      c[k] = s.clamp ? Math.min(1, Math.max(0, v)) : v;
    });
    gl.uniform1fv(u.u_coefficients, c);
  }

  /** Textures on the GPU (one per image and colour space). */
  get textureCount() {
    return this.textures.size;
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
      topo: null,
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
    // The pooled vertex array may hold another topology's index and UV buffers.
    entry.topo = null;
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

  /** Binds a head's vertex array (with its topology's index and UV buffers) for `prog`. */
  bindHead(prog, h, e, topo) {
    const gl = this.gl;
    gl.bindVertexArray(e.gl.vao);
    if (e.topo !== topo) {
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, topo.ibo);
      for (const [location, b, size] of [[2, topo.uvs, 2], [3, topo.uvs1, 2], [4, topo.colors, 4]]) {
        if (b) {
          gl.bindBuffer(gl.ARRAY_BUFFER, b);
          gl.enableVertexAttribArray(location);
          gl.vertexAttribPointer(location, size, gl.FLOAT, false, 0, 0);
          gl.bindBuffer(gl.ARRAY_BUFFER, null);
        } else {
          gl.disableVertexAttribArray(location);
        }
      }
      e.topo = topo;
    }
    const u = prog.u;
    gl.uniform3fv(u.u_qmin, e.qmin);
    gl.uniform3fv(u.u_qstep, e.qstep);
    gl.uniform1f(u.u_qbias, e.qbias);
    gl.uniformMatrix4fv(u.u_model, false, h.model);
  }

  /** Sets a material's uniforms, textures and samplers, and its culling. */
  bindMaterial(m, textured) {
    const gl = this.gl;
    const u = this.pbr.u;
    gl.uniform4fv(u.u_base_factor, m.base);
    gl.uniform3fv(u.u_emissive, m.emissive);
    gl.uniform4fv(u.u_pbr, m.pbr);
    let normalMap = 0;
    for (let i = 0; i < SLOTS; i++) {
      const s = textured ? m.slots[i] : null;
      const tex = s && this.textures.get(s.key);
      gl.activeTexture(gl.TEXTURE0 + i);
      gl.bindTexture(gl.TEXTURE_2D, tex || this.white);
      gl.bindSampler(i, tex ? s.sampler : null);
      if (tex && i === NORMAL) normalMap = 1;
    }
    gl.uniform4f(u.u_mode, m.cutoff, m.unlit ? 1 : 0, normalMap, m.blend ? 1 : 0);
    gl.uniformMatrix3fv(u.u_uv, false, m.uv);
    gl.uniform1iv(u.u_set, m.sets);
    if (m.doubleSided) gl.disable(gl.CULL_FACE);
    else gl.enable(gl.CULL_FACE);
  }

  /**
   * Draws the crowd.
   * @param {{viewProj: Float32Array, view: Float32Array, eye: number[]}} view
   * @param {{entry: object, model: Float32Array}[]} heads
   * @param {Map<number, Float32Array>} [layerInputs] each head id's expression-layer inputs
   * @returns {number} heads drawn
   */
  draw(view, heads, layerInputs = new Map()) {
    const gl = this.gl;
    gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    gl.clearColor(BACKGROUND[0] / 255, BACKGROUND[1] / 255, BACKGROUND[2] / 255, 1);
    gl.depthMask(true);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);

    // Heads that can be drawn, and their primitives by how they are drawn.
    const shown = [];
    for (const h of heads) {
      const e = h.entry;
      const topo = e && this.topologies.get(e.key);
      // A buffer whose vertex count is not its topology's (the rig's mesh levels changed
      // since the topology was fetched) is not drawn: its indices would not fit.
      if (!topo || topo.vertices !== e.vertices) continue;
      if (!e.gl) this.realize(e);
      shown.push({ h, e, topo });
    }
    const groups = (topo) => {
      const materials = this.materials.get(topo.rig);
      if (topo.groups && topo.groups.materials === materials) return topo.groups;
      const g = { materials, plaster: [], solid: [], blend: [] };
      for (const p of topo.primitives) {
        const m = materials && p.material !== null ? materials[p.material] : null;
        if (!m) g.plaster.push(p);
        else (m.blend ? g.blend : g.solid).push({ p, m });
      }
      topo.groups = g;
      return g;
    };

    // Without a material: the plaster look, both sides drawn.
    let prog = this.plaster;
    gl.useProgram(prog.program);
    gl.uniformMatrix4fv(prog.u.u_view_proj, false, view.viewProj);
    gl.uniform3fv(prog.u.u_eye, view.eye);
    gl.disable(gl.CULL_FACE);
    for (const s of shown) {
      const list = groups(s.topo).plaster;
      if (!list.length) continue;
      this.bindHead(prog, s.h, s.e, s.topo);
      for (const p of list) {
        gl.uniform3fv(prog.u.u_color, p.color);
        gl.drawElements(gl.TRIANGLES, p.count, gl.UNSIGNED_INT, p.first * 4);
      }
    }

    // With one: opaque and masked first, then blended ones far to near over them.
    prog = this.pbr;
    gl.useProgram(prog.program);
    gl.uniformMatrix4fv(prog.u.u_view_proj, false, view.viewProj);
    gl.uniform3fv(prog.u.u_eye, view.eye);
    this.setLights(view.view);
    let bound = null;
    let boundTextured = false;
    const blended = [];
    for (const s of shown) {
      const g = groups(s.topo);
      if (g.blend.length) {
        const m = s.h.model;
        const c = s.topo.center;
        const d = [0, 1, 2].map((a) => m[a] * c[0] + m[4 + a] * c[1] + m[8 + a] * c[2] + m[12 + a] - view.eye[a]);
        for (const pm of g.blend) blended.push({ s, pm, depth: d[0] * d[0] + d[1] * d[1] + d[2] * d[2] });
      }
      if (!g.solid.length) continue;
      this.bindHead(prog, s.h, s.e, s.topo);
      const textured = !!(s.topo.uvs || s.topo.uvs1);
      const inputs = layerInputs.get(s.h.spec.head);
      for (const { p, m } of g.solid) {
        if (bound !== m || boundTextured !== textured) {
          this.bindMaterial(m, textured);
          bound = m;
          boundTextured = textured;
        }
        // Per head: its coefficients are its own.
        this.bindLayers(m, textured, inputs);
        gl.drawElements(gl.TRIANGLES, p.count, gl.UNSIGNED_INT, p.first * 4);
      }
    }
    if (blended.length) {
      blended.sort((a, b) => b.depth - a.depth);
      gl.enable(gl.BLEND);
      // Colour over what is behind; alpha stays 1 (the canvas is composited with the page).
      gl.blendFuncSeparate(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA, gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
      gl.depthMask(false);
      let head = null;
      for (const { s, pm } of blended) {
        if (head !== s) {
          this.bindHead(prog, s.h, s.e, s.topo);
          head = s;
        }
        const textured = !!(s.topo.uvs || s.topo.uvs1);
        this.bindMaterial(pm.m, textured);
        this.bindLayers(pm.m, textured, layerInputs.get(s.h.spec.head));
        gl.drawElements(gl.TRIANGLES, pm.p.count, gl.UNSIGNED_INT, pm.p.first * 4);
      }
      gl.depthMask(true);
      gl.disable(gl.BLEND);
    }
    gl.disable(gl.CULL_FACE);
    gl.bindVertexArray(null);
    return shown.length;
  }

  /** The lights in world space from the view matrix (rows: the camera's right, up, back). */
  setLights(v) {
    const gl = this.gl;
    const u = this.pbr.u;
    const world = (d) => normalize3([0, 1, 2].map((a) => v[a * 4] * d[0] + v[a * 4 + 1] * d[1] + v[a * 4 + 2] * d[2]));
    gl.uniform4fv(u.u_key, [...world(normalize3(KEY.dir)), KEY.irradiance]);
    gl.uniform4fv(u.u_fill, [...world(normalize3(FILL.dir)), FILL.irradiance]);
    gl.uniform3fv(u.u_up, world([0, 1, 0]));
    gl.uniform3fv(u.u_sky, SKY);
    gl.uniform3fv(u.u_ground, GROUND);
  }
}

/** A 1×1 texture of one RGBA8 colour. */
function solidTexture(gl, rgba) {
  const tex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, tex);
  gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA8, 1, 1);
  gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(rgba));
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
  gl.bindTexture(gl.TEXTURE_2D, null);
  return tex;
}

/** A linked program and the locations of the uniforms every draw sets plus `extra`. */
function program(gl, vs, fs, extra) {
  const p = link(gl, vs, fs);
  const u = {};
  for (const name of ['u_view_proj', 'u_model', 'u_qmin', 'u_qstep', 'u_qbias', 'u_eye', ...extra]) {
    u[name] = gl.getUniformLocation(p, name);
  }
  return { program: p, u };
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
