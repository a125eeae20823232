// Offscreen crowd rendering (crates/engine/src/render/gpu.rs): blended heads drawn instanced,
// with per-vertex normals, shaded with glTF 2.0's metallic-roughness BRDF (Appendix B) under a
// key and a fill directional light and a hemisphere ambient, into a 4× MSAA sRGB target. The
// CPU mirror is crates/engine/src/render/brdf.rs: change both together. Everything here works
// in linear colour; the Rgba8UnormSrgb target encodes, with no tone mapping.

const PI: f32 = 3.14159265358979;
// brdf::MIN_ROUGHNESS: GGX's D is a Dirac pulse at roughness 0.
const MIN_ROUGHNESS: f32 = 0.0525;

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
}

@group(0) @binding(0) var<uniform> camera: Camera;
@group(1) @binding(0) var<uniform> material: Material;

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
}

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
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
    return out;
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
fn fs_main(in: VertexOut, @builtin(front_facing) front: bool) -> @location(0) vec4<f32> {
    let base = material.base;
    if material.alpha.z > 0.5 {
        // KHR_materials_unlit: the base colour as it is.
        return vec4<f32>(base.rgb, 1.0);
    }
    // A degenerate normal (zero, e.g. an isolated vertex) would normalize to NaN; shade it as
    // facing the viewer instead.
    let to_eye = camera.eye.xyz - in.world;
    let v = select(vec3<f32>(0.0, 0.0, 1.0), normalize(to_eye), dot(to_eye, to_eye) > 1e-30);
    let len2 = dot(in.normal, in.normal);
    var n = select(v, in.normal * inverseSqrt(len2), len2 > 1e-30);
    // A double-sided material's back faces are lit as the other side of the surface.
    if material.alpha.w > 0.5 && !front {
        n = -n;
    }

    let metallic = clamp(material.pbr.x, 0.0, 1.0);
    let roughness = clamp(material.pbr.y, MIN_ROUGHNESS, 1.0);
    let c_diff = mix(base.rgb, vec3<f32>(0.0), metallic);
    let f0 = mix(vec3<f32>(0.04), base.rgb, metallic);
    let alpha = roughness * roughness;

    var c = direct(n, v, camera.key.xyz, c_diff, f0, alpha) * camera.key.w;
    c += direct(n, v, camera.fill.xyz, c_diff, f0, alpha) * camera.fill.w;
    let ambient = mix(camera.ground.rgb, camera.sky.rgb, 0.5 + 0.5 * dot(n, camera.up.xyz));
    c += ambient * c_diff / PI;
    c += material.emissive.rgb;
    return vec4<f32>(c, 1.0);
}
