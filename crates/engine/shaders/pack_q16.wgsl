// Pass `pack_q16` (CPU mirror: `engine::Q16Params::quantize`, the CPU kernels' q16 output
// stage).
//
// Quantizes an f32 buffer of xyz components to int16, two values per u32 (little-endian halves,
// so the bytes read back are the i16 array itself), axis = component % 3, with `lib/q16.wgsl`'s
// `quantize` (compiled in front of this file): bit for bit the CPU's encoding of the same f32
// values. An odd count pads the last half with 0.
//
// Pass `pack_q16r` (CPU mirror: `engine::code_residuals`, `crowdmorph_proto::q16r_encode` over
// `pack_q16`'s values) writes the same q16 positions as residual planes against a reference
// (format `q16r`): per job of `per_job` components, the low bytes of zigzag(q - reference)
// (wrapping int16), then their high bytes. One invocation per output word, byte by byte: a
// job's planes start at any byte, since `per_job` need not be a multiple of four, so each
// component is quantized twice, once per plane (docs/perf/2026-12-06-gpu-residuals.md).

@group(0) @binding(0) var<uniform> params: Q16Params;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read_write> dst: array<u32>;
// `pack_q16r`: the reference's q16 values, two per word as in `dst`.
@group(0) @binding(3) var<storage, read> reference: array<u32>;

@compute @workgroup_size(64)
fn pack_q16(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x + gid.y * params.row;
    let pairs = (params.count + 1u) / 2u;
    if i >= pairs {
        return;
    }
    let k = 2u * i;
    let a = quantize(params, src[k], k % 3u);
    var b = 0u;
    if k + 1u < params.count {
        b = quantize(params, src[k + 1u], (k + 1u) % 3u);
    }
    dst[i] = a | (b << 16u);
}

// One byte of the residual planes, for component `c` (axis `a`) of job `job`: the low
// byte of the zigzag code (`high` false) or its high byte.
fn residual_byte(job: u32, c: u32, a: u32, high: bool) -> u32 {
    let q = quantize(params, src[job * params.per_job + c], a);
    let z = residual_code(q, (reference[c >> 1u] >> (16u * (c & 1u))) & 0xffffu);
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
