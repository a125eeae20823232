// Pass `pack_q16` (CPU mirror: `engine::Q16Params::quantize`, the CPU kernels' q16 output
// stage).
//
// Quantizes an f32 buffer of xyz components to int16, two values per u32 (little-endian halves,
// so the bytes read back are the i16 array itself): q = round_even(clamp((x - sub[a]) * mul[a],
// lo, hi)) + add, axis a = component % 3, in f32 as the CPU does it. Subtraction and
// multiplication are correctly rounded in WGSL's f32 and nothing here can be contracted into a
// fused multiply-add, so the result is bit for bit the CPU's encoding of the same f32 values.
// NaN goes to `lo`, as the CPU's comparisons send it. An odd count pads the last half with 0.

struct Params {
    // f32 values to pack.
    count: u32,
    // Invocations along x per row of the dispatch (workgroups_x * 64).
    row: u32,
    // Clamp of the scaled value.
    lo: f32,
    hi: f32,
    // Per axis (xyz; w unused): subtracted, then the scale.
    sub: vec4<f32>,
    mul: vec4<f32>,
    // Added to the rounded integer.
    add: i32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read_write> dst: array<u32>;

fn quantize(x: f32, a: u32) -> u32 {
    var u = (x - params.sub[a]) * params.mul[a];
    u = select(params.lo, u, u > params.lo);
    u = select(params.hi, u, u < params.hi);
    return bitcast<u32>(i32(round(u)) + params.add) & 0xffffu;
}

@compute @workgroup_size(64)
fn pack_q16(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x + gid.y * params.row;
    let pairs = (params.count + 1u) / 2u;
    if i >= pairs {
        return;
    }
    let k = 2u * i;
    let a = quantize(src[k], k % 3u);
    var b = 0u;
    if k + 1u < params.count {
        b = quantize(src[k + 1u], (k + 1u) % 3u);
    }
    dst[i] = a | (b << 16u);
}
