// Offscreen crowd rendering (crates/engine/src/render/gpu.rs): blended heads drawn instanced,
// with per-vertex normals, shaded with glTF 2.0's metallic-roughness BRDF (Appendix B) under a
// key and a fill directional light and a hemisphere ambient, into a 4× MSAA sRGB target. The
// CPU mirror is crates/engine/src/render/brdf.rs: change both together. Everything here works
// in linear colour; the Rgba8UnormSrgb target encodes, with no tone mapping.
//
// Textures (crates/engine/src/render/appearance.rs): five slots of a glTF material, each with
// its sampler, read through texture coordinate set 0 or 1 and its KHR_texture_transform.
// Colour slots (base colour, emissive) are bound through sRGB views, so sampling decodes them;
// data slots (metallic-roughness, normal, occlusion) through linear ones. A slot the material
// leaves empty is bound to a 1×1 white texture and flagged NO_TEXTURE, so its branch is skipped
// (the branch is on a uniform, so sampling inside it stays in uniform control flow).
//
// Layers (crates/core/src/rig/animated_texture.rs): the base colour texture becomes
// clamp(base(uv) + Σ_k c_k · layer_k(uv), 0, 1) in linear RGBA before the factor, with up to 16
// signed layers in one 2D array texture read through the base colour's sampler, set and
// transform. Wrinkle maps (c_k a target's weight) and a clip's PCA texture (the mean's and the
// components' coefficients of the frame) are both this sum; the coefficients are the draw's,
// since a draw's instances are clones of one job. CPU mirror: brdf::layered_base.

const PI: f32 = 3.14159265358979;
// brdf::MIN_ROUGHNESS: GGX's D is a Dirac pulse at roughness 0.
const MIN_ROUGHNESS: f32 = 0.0525;
// A slot's texture coordinate set when the material has no texture there.
const NO_TEXTURE: u32 = 255u;
// Alpha modes.
const MASK: f32 = 1.0;
const BLEND: f32 = 2.0;

struct Camera {
    // Projection × view; the projection is reversed-Z (near → 1, far → 0).
    view_proj: mat4x4<f32>,
    // World-space eye position (w unused).
    eye: vec4<f32>,
    // Unit world-space direction toward the key light (xyz) and its irradiance (w).
    key: vec4<f32>,
    // Unit world-space direction toward the fill light (xyz) and its irradiance (w).
    fill: vec4<f32>,
    // The hemisphere ambient's unit up (xyz; the camera's up).
    up: vec4<f32>,
    // Sky and ground irradiance of the hemisphere ambient, linear RGB.
    sky: vec4<f32>,
    ground: vec4<f32>,
}

struct Material {
    // Linear RGBA base colour factor.
    base: vec4<f32>,
    // Emitted radiance: emissiveFactor × emissive strength (rgb).
    emissive: vec4<f32>,
    // Metallic, roughness, normal scale, occlusion strength.
    pbr: vec4<f32>,
    // Alpha cutoff, alpha mode (0 opaque, 1 mask, 2 blend), unlit (0/1), double-sided (0/1).
    alpha: vec4<f32>,
    // Texture coordinate set (0, 1, or NO_TEXTURE) of base colour, metallic-roughness, normal
    // and occlusion; then of emissive (x; yzw unused).
    sets: vec4<u32>,
    sets2: vec4<u32>,
    // Per slot, in the order above, the two rows of its KHR_texture_transform (a 2×3 matrix:
    // uv' = (dot(row0.xyz, (u, v, 1)), dot(row1.xyz, (u, v, 1)))).
    transforms: array<vec4<f32>, 10>,
    // Layers summed (x; 0 none) and their texture coordinate set (y).
    layers: vec4<u32>,
    // Each layer's coefficient for this draw, four to a vec4.
    coefficients: array<vec4<f32>, 4>,
}

@group(0) @binding(0) var<uniform> camera: Camera;
@group(1) @binding(0) var<uniform> material: Material;
@group(2) @binding(0) var base_tex: texture_2d<f32>;
@group(2) @binding(1) var mr_tex: texture_2d<f32>;
@group(2) @binding(2) var normal_tex: texture_2d<f32>;
@group(2) @binding(3) var occlusion_tex: texture_2d<f32>;
@group(2) @binding(4) var emissive_tex: texture_2d<f32>;
@group(2) @binding(5) var base_smp: sampler;
@group(2) @binding(6) var mr_smp: sampler;
@group(2) @binding(7) var normal_smp: sampler;
@group(2) @binding(8) var occlusion_smp: sampler;
@group(2) @binding(9) var emissive_smp: sampler;
@group(2) @binding(10) var layer_tex: texture_2d_array<f32>;

struct VertexIn {
    @location(0) position: vec3<f32>,
    @location(1) normal: vec3<f32>,
    // The instance's model matrix (rig space → world), by columns.
    @location(2) model0: vec4<f32>,
    @location(3) model1: vec4<f32>,
    @location(4) model2: vec4<f32>,
    @location(5) model3: vec4<f32>,
    // Inverse transpose of the model's upper 3×3 (up to a positive scale), by columns: correct
    // for non-uniform scale, and computed once per instance on the host rather than per vertex.
    @location(6) normal0: vec4<f32>,
    @location(7) normal1: vec4<f32>,
    @location(8) normal2: vec4<f32>,
    // The topology's static attributes: texture coordinates of sets 0 and 1, the vertex colour
    // (linear RGBA; white without COLOR_0) and the rest tangent (xyz, w handedness; zero
    // without one).
    @location(9) uv0: vec2<f32>,
    @location(10) uv1: vec2<f32>,
    @location(11) color: vec4<f32>,
    @location(12) tangent: vec4<f32>,
}

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) uv0: vec2<f32>,
    @location(3) uv1: vec2<f32>,
    @location(4) color: vec4<f32>,
    // World-space tangent (xyz) and handedness × the instance's mirror sign (w).
    @location(5) tangent: vec4<f32>,
    // +1, or −1 for an instance whose model matrix mirrors (its triangles' facing flips).
    @location(6) @interpolate(flat) mirror: f32,
}

@vertex
fn vs_main(v: VertexIn) -> VertexOut {
    let model = mat4x4<f32>(v.model0, v.model1, v.model2, v.model3);
    let normal_matrix = mat3x3<f32>(v.normal0.xyz, v.normal1.xyz, v.normal2.xyz);
    let world = model * vec4<f32>(v.position, 1.0);
    var out: VertexOut;
    out.clip = camera.view_proj * world;
    out.world = world.xyz;
    // Not normalized here: interpolation of unnormalized normals is renormalized per fragment.
    out.normal = normal_matrix * v.normal;
    out.uv0 = v.uv0;
    out.uv1 = v.uv1;
    out.color = v.color;
    // Tangents follow the surface (the model matrix), normals its inverse transpose; a mirror
    // flips the bitangent, whose sign goes along.
    let mirror = v.normal0.w;
    out.tangent = vec4<f32>(mat3x3<f32>(v.model0.xyz, v.model1.xyz, v.model2.xyz) * v.tangent.xyz, v.tangent.w * mirror);
    out.mirror = mirror;
    return out;
}

// The texture coordinates slot `k` reads: its set, through its transform.
fn slot_uv(k: u32, uv_set: u32, uv0: vec2<f32>, uv1: vec2<f32>) -> vec2<f32> {
    let uv = vec3<f32>(select(uv0, uv1, uv_set == 1u), 1.0);
    return vec2<f32>(dot(material.transforms[2u * k].xyz, uv), dot(material.transforms[2u * k + 1u].xyz, uv));
}

// One directional light's BRDF times n·l (brdf::direct): (1 − F)·c_diff/π + F·D·V.
fn direct(n: vec3<f32>, v: vec3<f32>, l: vec3<f32>, c_diff: vec3<f32>, f0: vec3<f32>, alpha: f32) -> vec3<f32> {
    let n_l = clamp(dot(n, l), 0.0, 1.0);
    if n_l <= 0.0 {
        return vec3<f32>(0.0);
    }
    // A normal facing away from the eye (interpolated at a silhouette) shades as grazing.
    let n_v = clamp(dot(n, v), 0.0, 1.0);
    let hl = l + v;
    let h = select(vec3<f32>(0.0), normalize(hl), dot(hl, hl) > 1e-30);
    let n_h = clamp(dot(n, h), 0.0, 1.0);
    let v_h = clamp(dot(v, h), 0.0, 1.0);
    let f = f0 + (vec3<f32>(1.0) - f0) * pow(1.0 - v_h, 5.0);
    let a2 = alpha * alpha;
    let d_den = n_h * n_h * (a2 - 1.0) + 1.0;
    let d = a2 / (PI * d_den * d_den);
    let vis_den = n_l * sqrt(n_v * n_v * (1.0 - a2) + a2) + n_v * sqrt(n_l * n_l * (1.0 - a2) + a2);
    let vis = select(0.0, 0.5 / vis_den, vis_den > 0.0);
    return ((vec3<f32>(1.0) - f) * c_diff / PI + f * (d * vis)) * n_l;
}

@fragment
fn fs_main(in: VertexOut, @builtin(front_facing) front_facing: bool) -> @location(0) vec4<f32> {
    var base = material.base * in.color;
    var tex = vec4<f32>(1.0);
    if material.sets.x != NO_TEXTURE {
        tex = textureSample(base_tex, base_smp, slot_uv(0u, material.sets.x, in.uv0, in.uv1));
    }
    if material.layers.x > 0u {
        let luv = slot_uv(0u, material.layers.y, in.uv0, in.uv1);
        for (var k = 0u; k < material.layers.x; k++) {
            tex += material.coefficients[k / 4u][k % 4u] * textureSample(layer_tex, base_smp, luv, k);
        }
        tex = clamp(tex, vec4<f32>(0.0), vec4<f32>(1.0));
    }
    base *= tex;
    let mode = material.alpha.y;
    // MASK: a hole below the cutoff (each MSAA sample of the pixel alike); BLEND keeps alpha,
    // everything else is opaque.
    if mode == MASK && base.a < material.alpha.x {
        discard;
    }
    let alpha_out = select(1.0, base.a, mode == BLEND);
    if material.alpha.z > 0.5 {
        // KHR_materials_unlit: the base colour as it is.
        return vec4<f32>(base.rgb, alpha_out);
    }
    // A degenerate normal (zero, e.g. an isolated vertex) would normalize to NaN; shade it as
    // facing the viewer instead.
    let to_eye = camera.eye.xyz - in.world;
    let v = select(vec3<f32>(0.0, 0.0, 1.0), normalize(to_eye), dot(to_eye, to_eye) > 1e-30);
    let len2 = dot(in.normal, in.normal);
    var n = select(v, in.normal * inverseSqrt(len2), len2 > 1e-30);
    // The triangle's own side: a mirroring instance flips what the rasterizer calls front.
    let front = front_facing == (in.mirror > 0.0);
    // A double-sided material's back faces are lit as the other side of the surface (glTF:
    // normal, tangent and bitangent all flip).
    let back = material.alpha.w > 0.5 && !front;
    if back {
        n = -n;
    }
    if material.sets.z != NO_TEXTURE {
        // The rest tangent made orthogonal to the blended normal (Gram-Schmidt): morph targets
        // bend the surface, and the tangent frame must follow the normal it perturbs. A zero or
        // parallel tangent (none in the file) leaves the normal as it is.
        let t_raw = select(in.tangent.xyz, -in.tangent.xyz, back);
        let t_ortho = t_raw - n * dot(n, t_raw);
        let t_len2 = dot(t_ortho, t_ortho);
        let tn = textureSample(normal_tex, normal_smp, slot_uv(2u, material.sets.z, in.uv0, in.uv1)).xyz * 2.0 - vec3<f32>(1.0);
        if t_len2 > 1e-12 {
            let t = t_ortho * inverseSqrt(t_len2);
            let b = cross(n, t) * select(1.0, -1.0, in.tangent.w < 0.0) * select(1.0, -1.0, back);
            let scaled = vec3<f32>(tn.xy * material.pbr.z, tn.z);
            let mapped = t * scaled.x + b * scaled.y + n * scaled.z;
            if dot(mapped, mapped) > 1e-30 {
                n = normalize(mapped);
            }
        }
    }

    var metallic = material.pbr.x;
    var roughness = material.pbr.y;
    if material.sets.y != NO_TEXTURE {
        // glTF: roughness in G, metalness in B.
        let mr = textureSample(mr_tex, mr_smp, slot_uv(1u, material.sets.y, in.uv0, in.uv1));
        roughness *= mr.g;
        metallic *= mr.b;
    }
    var occlusion = 1.0;
    if material.sets.w != NO_TEXTURE {
        let ao = textureSample(occlusion_tex, occlusion_smp, slot_uv(3u, material.sets.w, in.uv0, in.uv1)).r;
        occlusion = 1.0 + material.pbr.w * (ao - 1.0);
    }
    var emissive = material.emissive.rgb;
    if material.sets2.x != NO_TEXTURE {
        emissive *= textureSample(emissive_tex, emissive_smp, slot_uv(4u, material.sets2.x, in.uv0, in.uv1)).rgb;
    }

    metallic = clamp(metallic, 0.0, 1.0);
    roughness = clamp(roughness, MIN_ROUGHNESS, 1.0);
    let c_diff = mix(base.rgb, vec3<f32>(0.0), metallic);
    let f0 = mix(vec3<f32>(0.04), base.rgb, metallic);
    let alpha = roughness * roughness;

    var c = direct(n, v, camera.key.xyz, c_diff, f0, alpha) * camera.key.w;
    c += direct(n, v, camera.fill.xyz, c_diff, f0, alpha) * camera.fill.w;
    let ambient = mix(camera.ground.rgb, camera.sky.rgb, 0.5 + 0.5 * dot(n, camera.up.xyz));
    c += ambient * c_diff / PI * occlusion;
    c += emissive;
    return vec4<f32>(c, alpha_out);
}
