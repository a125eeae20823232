// Pass `pack_q16` (CPU mirror: `engine::Q16Params::quantize`, the CPU kernels' q16 output
// stage).
//
// Quantizes an f32 buffer of xyz components to int16, two values per u32 (little-endian halves,
// so the bytes read back are the i16 array itself): q = round_even(clamp((x - sub[a]) * mul[a],
// lo, hi)) + add, axis a = component % 3, in f32 as the CPU does it. Subtraction and
// multiplication are correctly rounded in WGSL's f32 and nothing here can be contracted into a
// fused multiply-add, so the result is bit for bit the CPU's encoding of the same f32 values.
// NaN goes to `lo`, as the CPU's comparisons send it. An odd count pads the last half with 0.
//
// Pass `pack_q16r` (CPU mirror: `engine::code_residuals`, `crowdmorph_proto::q16r_encode` over
// `pack_q16`'s values) writes the same q16 positions as residual planes against a reference
// (format `q16r`): per job of `per_job` components, the low bytes of zigzag(q - reference)
// (wrapping int16), then their high bytes. One invocation per output word, byte by byte: a
// job's planes start at any byte, since `per_job` need not be a multiple of four, so each
// component is quantized twice, once per plane (docs/perf/2026-12-06-gpu-residuals.md).

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
    // Components per job (`pack_q16r`).
    per_job: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read_write> dst: array<u32>;
// `pack_q16r`: the reference's q16 values, two per word as in `dst`.
@group(0) @binding(3) var<storage, read> reference: array<u32>;

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

// One byte of the residual planes, for component `c` (axis `a`) of job `job`: the low
// byte of the zigzag code (`high` false) or its high byte.
fn residual_byte(job: u32, c: u32, a: u32, high: bool) -> u32 {
    let q = quantize(src[job * params.per_job + c], a);
    let refq = (reference[c >> 1u] >> (16u * (c & 1u))) & 0xffffu;
    // The wrapping int16 difference, sign-extended, then zigzag-coded as a u16.
    let d = bitcast<i32>(((q - refq) & 0xffffu) << 16u) >> 16u;
    let z = bitcast<u32>((d << 1u) ^ (d >> 15u)) & 0xffffu;
    return (z >> select(0u, 8u, high)) & 0xffu;
}

@compute @workgroup_size(64)
fn pack_q16r(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x + gid.y * params.row;
    // Two bytes per component, four per word: as many words as `pack_q16` writes.
    let words = (params.count + 1u) / 2u;
    if i >= words {
        return;
    }
    let per_job = params.per_job;
    let bytes = 2u * params.count;
    // Where the word's first byte is (one division and one remainder a word: integer
    // division is slow on GPUs and on lavapipe alike), then byte by byte onwards: the next component, the next plane, the
    // next job. A job's components start at an x, so the axis restarts at 0 with each plane.
    let b = 4u * i;
    var job = b / (2u * per_job);
    let r = b - job * 2u * per_job;
    var high = r >= per_job;
    var c = select(r, r - per_job, high);
    var a = c % 3u;
    var w = 0u;
    for (var k = 0u; k < 4u; k++) {
        if b + k >= bytes {
            break;
        }
        w |= residual_byte(job, c, a, high) << (8u * k);
        c += 1u;
        a = select(a + 1u, 0u, a == 2u);
        if c == per_job {
            c = 0u;
            a = 0u;
            job += select(0u, 1u, high);
            high = !high;
        }
    }
    dst[i] = w;
}
