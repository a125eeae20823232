// Offscreen crowd rendering (crates/engine/src/render/gpu.rs): blended heads drawn instanced, with per-vertex
// normals, Lambert + Blinn-Phong from a key and a fill light plus ambient, into a 4× MSAA
// sRGB target. Everything here works in linear colour; the Rgba8UnormSrgb target encodes.

struct Camera {
    // Projection × view; the projection is reversed-Z (near → 1, far → 0).
    view_proj: mat4x4<f32>,
    // World-space eye position (w unused).
    eye: vec4<f32>,
    // Unit world-space direction toward the key light (xyz) and its intensity (w).
    key: vec4<f32>,
    // Unit world-space direction toward the fill light (xyz) and its intensity (w).
    fill: vec4<f32>,
    // Ambient term, specular strength, specular exponent, unused.
    shading: vec4<f32>,
}

struct Material {
    // Linear RGBA base colour of the primitive being drawn (alpha is ignored: heads are opaque).
    base: vec4<f32>,
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

@fragment
fn fs_main(in: VertexOut) -> @location(0) vec4<f32> {
    // A degenerate normal (zero, e.g. an isolated vertex) would normalize to NaN; shade it as
    // facing the viewer instead.
    let to_eye = camera.eye.xyz - in.world;
    let view_dir = select(vec3<f32>(0.0, 0.0, 1.0), normalize(to_eye), dot(to_eye, to_eye) > 1e-30);
    let len2 = dot(in.normal, in.normal);
    let n = select(view_dir, in.normal * inverseSqrt(len2), len2 > 1e-30);

    let key_dir = camera.key.xyz;
    let fill_dir = camera.fill.xyz;
    let key_lambert = max(dot(n, key_dir), 0.0);
    let fill_lambert = max(dot(n, fill_dir), 0.0);
    let diffuse = camera.shading.x + camera.key.w * key_lambert + camera.fill.w * fill_lambert;

    // Blinn-Phong from the key light only, and only on surfaces the key light reaches.
    let half_dir = normalize(key_dir + view_dir);
    let facing = select(0.0, 1.0, key_lambert > 0.0);
    let specular = camera.shading.y * facing * pow(max(dot(n, half_dir), 0.0), camera.shading.z);

    let color = material.base.rgb * diffuse + vec3<f32>(specular);
    return vec4<f32>(color, 1.0);
}
