// Shared piece (`crates/engine/shaders/lib/`): compiled in front of `pack_q16.wgsl` and `blend.wgsl`, which
// both write q16 and q16r (WGSL has no include; the engine joins the sources,
// `engine::gpu::SHADERS`). CPU mirrors: `engine::Q16Params::quantize` and
// `crowdmorph_proto::q16r_encode`.

// The uniform `layout::Q16PackParams` fills (`tests/shaders.rs` holds the two to one layout).
struct Q16Params {
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
    // Components per job (q16r's planes).
    per_job: u32,
    _pad1: u32,
    _pad2: u32,
}

// x on axis `a` as q16 bits: q = round_even(clamp((x - sub[a]) * mul[a], lo, hi)) + add, in
// f32 as the CPU does it. Subtraction and multiplication are correctly rounded in WGSL's f32
// and nothing here can be contracted into a fused multiply-add, so the result is bit for bit
// the CPU's encoding of the same f32 value. NaN goes to `lo`, as the CPU's comparisons send it.
fn quantize(p: Q16Params, x: f32, a: u32) -> u32 {
    var u = (x - p.sub[a]) * p.mul[a];
    u = select(p.lo, u, u > p.lo);
    u = select(p.hi, u, u < p.hi);
    return bitcast<u32>(i32(round(u)) + p.add) & 0xffffu;
}

// q16r's code of q16 bits `q` against the reference's `r`: the wrapping int16 difference,
// zigzag-coded as a u16.
fn residual_code(q: u32, r: u32) -> u32 {
    let d = bitcast<i32>(((q - r) & 0xffffu) << 16u) >> 16u;
    return bitcast<u32>((d << 1u) ^ (d >> 15u)) & 0xffffu;
}

