// Pass `blend` (CPU mirror: `engine::cpu::CpuRig::blend`).
//
// Eq. 1 of Costigan et al. 2016, v = base + sum_k w_k * delta_k, for every vertex of a tile and
// eight jobs at once (the CPU engine's group). One workgroup is one tile of 64 vertices and one
// group of eight jobs; each invocation owns one vertex and keeps x, y, z accumulators for the
// eight jobs in two vec4s each, so every delta it loads serves eight jobs. The loop visits only
// the group's active slots that move this tile (Lorach's index + weight list from
// `build_active`, compacted per tile here): a slot without a block in the tile costs nothing in
// the loop.
//
// Workgroups are numbered group first (x) and tile second (y, z), so the workgroups the device
// runs side by side are the groups of one tile, which read the same deltas while they are in
// the cache.
//
// Deltas are stored per (tile, slot) as a 64-lane structure-of-arrays block: x[64], y[64],
// z[64], so the 64 invocations of a tile read consecutive floats (coalesced). With
// `F16_DELTAS` (`--gpu-deltas f16`) a block is half the words: x and y of a lane as two
// binary16 in one word, then the z of two neighbouring lanes in one word (the host's
// `layout::DeltaFormat::F16`). Which slots have a
// block in a tile is a bitmask per 32 slots with the running block count, so finding slot s's
// block is one load and a popcount.
//
// Each term is one fused multiply-add, as the CPU engine's `mul_add`, in the same slot order,
// so both round alike.
//
// The same pass blends normals (base normals + normal deltas, then normalized) when
// `params.normalize` is 1.
//
// With `PACK` set the pass writes the batch's wire format itself, q16 in the box (`pack_q16`'s
// arithmetic) or binary16 (`pack_f16`'s), into `packed` instead of f32 into `out`: the host
// does this where nothing reads the f32 positions after the blend (no skin, no normals), which
// saves writing 12 bytes a vertex and a pass reading them back. Component `i` of the batch is
// half `i % 2` of word `i / 2`; a word whose halves belong to two invocations (neighbouring
// vertices, or the last vertex of a job and the first of the next) is or-ed into a word the
// host cleared, the others are stored whole. `PACK` 3 writes q16r's residual planes against
// `reference` (`pack_q16r`'s bytes): a vertex's three bytes of each plane start at any byte, so
// they are or-ed in, and a word of zero bytes is skipped (the buffer is cleared).

struct Params {
    // Vertices of the whole rig: the output stride per job is vertices * 3.
    vertices: u32,
    // First tile of this chunk of the rig (rigs larger than a storage binding are split).
    tile_begin: u32,
    // Tiles in this chunk.
    tiles: u32,
    // Slots (targets) of the rig.
    slots: u32,
    // Mask words per tile: ceil(slots / 32).
    words: u32,
    // Jobs in this dispatch.
    jobs: u32,
    // 1: scale each result to unit length (normal blending).
    normalize: u32,
    // Workgroups along y; the tile is workgroup_id.y + workgroup_id.z * tiles_y.
    tiles_y: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
// Neutral values of the chunk's vertices, x y z per vertex.
@group(0) @binding(1) var<storage, read> base: array<f32>;
// Delta blocks of the chunk: 192 f32 words each, or 96 words of binary16 pairs.
@group(0) @binding(2) var<storage, read> blocks: array<u32>;
// Per (chunk tile, word): .x the slots of the word that have a block, .y the index of the first
// of them in `blocks`.
@group(0) @binding(3) var<storage, read> masks: array<vec2<u32>>;
// Per group and active slot, two vec4s: the weights of jobs 0-3, then of jobs 4-7.
@group(0) @binding(4) var<storage, read> active_weights: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> active_slots: array<u32>;
@group(0) @binding(6) var<storage, read> active_count: array<u32>;
// jobs × vertices × 3 floats.
@group(0) @binding(7) var<storage, read_write> out: array<f32>;
// With `PACK`: jobs × vertices × 3 halves, two a word, cleared by the host.
@group(0) @binding(8) var<storage, read_write> packed: array<atomic<u32>>;
// With `PACK` 1 or 3: the box's quantization, as `pack_q16` takes it.
@group(0) @binding(9) var<uniform> q16: Q16Params;
// With `PACK` 3: one job's reference q16 values, two a word.
@group(0) @binding(10) var<storage, read> reference: array<u32>;

// Set for rigs uploaded with binary16 deltas.
override F16_DELTAS: bool = false;
// What `blend_packed` writes into `packed`: 1 q16, 2 binary16, 3 q16r's residual planes.
override PACK: u32 = 1u;


const TILE: u32 = 64u;
const GROUP: u32 = 8u;
// Active-list entries staged at a time, four per invocation.
const BATCH: u32 = 256u;
const PER_LANE: u32 = BATCH / TILE;
const NONE: u32 = 0xffffffffu;

var<workgroup> sh_lo: array<vec4<f32>, BATCH>;
var<workgroup> sh_hi: array<vec4<f32>, BATCH>;
var<workgroup> sh_blocks: array<u32, BATCH>;
var<workgroup> sh_count: u32;

// Component `x` on axis `a` as a 16-bit half of the wire format: `lib/q16.wgsl`'s `quantize`
// (as `pack_q16`, so the same bits) or `pack_f16`'s rounding.
fn half(x: f32, a: u32) -> u32 {
    if PACK == 1u || PACK == 3u {
        return quantize(q16, x, a);
    }
    return pack2x16float(vec2<f32>(x, 0.0)) & 0xffffu;
}

// Writes components `g`, `g + 1`, `g + 2` of the batch (one vertex of one job) as halves.
fn write_halves(g: u32, r: vec3<f32>) {
    let h = array<u32, 3>(half(r.x, 0u), half(r.y, 1u), half(r.z, 2u));
    if (g & 1u) == 0u {
        // x and y fill a word; z shares the next with the following vertex's x.
        atomicStore(&packed[g / 2u], h[0] | (h[1] << 16u));
        atomicOr(&packed[g / 2u + 1u], h[2]);
    } else {
        // x shares a word with the previous vertex's z; y and z fill the next.
        atomicOr(&packed[g / 2u], h[0] << 16u);
        atomicStore(&packed[g / 2u + 1u], h[1] | (h[2] << 16u));
    }
}

// Ors bytes `v` into bytes `b`, `b + 1`, `b + 2` of `packed`: one word, or two.
fn or_bytes(b: u32, v: array<u32, 3>) {
    var w = array<u32, 2>(0u, 0u);
    for (var k = 0u; k < 3u; k++) {
        let at = b + k;
        w[at / 4u - b / 4u] |= v[k] << (8u * (at % 4u));
    }
    for (var k = 0u; k < 2u; k++) {
        if w[k] != 0u {
            atomicOr(&packed[b / 4u + k], w[k]);
        }
    }
}

// Writes component `c` to `c + 2` of job `job` (one vertex) as q16r residual bytes: low bytes
// into the job's first plane, high bytes into its second (`pack_q16r`'s zigzag).
fn write_residuals(job: u32, c: u32, r: vec3<f32>) {
    let per_job = q16.per_job;
    var lo = array<u32, 3>(0u, 0u, 0u);
    var hi = array<u32, 3>(0u, 0u, 0u);
    let q = array<u32, 3>(half(r.x, 0u), half(r.y, 1u), half(r.z, 2u));
    for (var k = 0u; k < 3u; k++) {
        let i = c + k;
        let z = residual_code(q[k], (reference[i >> 1u] >> (16u * (i & 1u))) & 0xffffu);
        lo[k] = z & 0xffu;
        hi[k] = z >> 8u;
    }
    let b = 2u * job * per_job + c;
    or_bytes(b, lo);
    or_bytes(b + per_job, hi);
}

// Lane `lane`'s delta in block `b`.
fn delta(b: u32, lane: u32) -> vec3<f32> {
    if F16_DELTAS {
        let o = b * 96u;
        let xy = unpack2x16float(blocks[o + lane]);
        let zz = unpack2x16float(blocks[o + 64u + lane / 2u]);
        return vec3<f32>(xy, select(zz.x, zz.y, (lane & 1u) == 1u));
    }
    let o = b * 192u + lane;
    return vec3<f32>(
        bitcast<f32>(blocks[o]),
        bitcast<f32>(blocks[o + 64u]),
        bitcast<f32>(blocks[o + 128u]),
    );
}

fn block_of(tile: u32, s: u32) -> u32 {
    let m = masks[tile * params.words + s / 32u];
    let bit = 1u << (s % 32u);
    if (m.x & bit) == 0u {
        return NONE;
    }
    return m.y + countOneBits(m.x & (bit - 1u));
}


// Eight jobs' blended x, y, z of one vertex: jobs 0-3 in the `0` vectors, 4-7 in the `1`s.
struct Sums {
    x0: vec4<f32>,
    y0: vec4<f32>,
    z0: vec4<f32>,
    x1: vec4<f32>,
    y1: vec4<f32>,
    z1: vec4<f32>,
}

// Eq. 1 for vertex `v` (lane `lane` of tile `tile`, `tile_ok` when the tile is in the chunk) and
// the eight jobs of group `g`. Every invocation of the workgroup calls it (it has barriers).
fn accumulate(g: u32, tile: u32, tile_ok: bool, lane: u32, has_vertex: bool) -> Sums {
    var x0 = vec4<f32>(0.0);
    var y0 = vec4<f32>(0.0);
    var z0 = vec4<f32>(0.0);
    if has_vertex {
        let lv = tile * TILE + lane;
        x0 = vec4<f32>(base[lv * 3u]);
        y0 = vec4<f32>(base[lv * 3u + 1u]);
        z0 = vec4<f32>(base[lv * 3u + 2u]);
    }
    var x1 = x0;
    var y1 = y0;
    var z1 = z0;

    if lane == 0u {
        sh_count = active_count[g];
    }
    let n = workgroupUniformLoad(&sh_count);
    let eight = params.jobs > g * GROUP + 4u;
    for (var start = 0u; start < n; start += BATCH) {
        let m = min(BATCH, n - start);
        // Stage this batch of the active list in workgroup memory, keeping only the slots with a
        // block in this tile, in list order: each invocation looks up four consecutive entries,
        // and a scan of the counts over the workgroup says where its survivors go.
        let first = lane * PER_LANE;
        var found = array<u32, PER_LANE>(NONE, NONE, NONE, NONE);
        var mine = 0u;
        for (var k = 0u; k < PER_LANE; k++) {
            let i = first + k;
            if tile_ok && i < m {
                found[k] = block_of(tile, active_slots[g * params.slots + start + i]);
                mine += u32(found[k] != NONE);
            }
        }
        var at = place(lane, mine);
        for (var k = 0u; k < PER_LANE; k++) {
            if found[k] != NONE {
                let e = g * params.slots + start + first + k;
                sh_lo[at] = active_weights[2u * e];
                sh_hi[at] = active_weights[2u * e + 1u];
                sh_blocks[at] = found[k];
                at++;
            }
        }
        let kept = workgroupUniformLoad(&sh_total);
        if eight {
            for (var i = 0u; i < kept; i++) {
                let d = delta(sh_blocks[i], lane);
                let lo = sh_lo[i];
                let hi = sh_hi[i];
                x0 = fma(lo, vec4<f32>(d.x), x0);
                y0 = fma(lo, vec4<f32>(d.y), y0);
                z0 = fma(lo, vec4<f32>(d.z), z0);
                x1 = fma(hi, vec4<f32>(d.x), x1);
                y1 = fma(hi, vec4<f32>(d.y), y1);
                z1 = fma(hi, vec4<f32>(d.z), z1);
            }
        } else {
            // A group of at most four jobs (a batch's last, or a batch of one): half the work.
            for (var i = 0u; i < kept; i++) {
                let d = delta(sh_blocks[i], lane);
                let lo = sh_lo[i];
                x0 = fma(lo, vec4<f32>(d.x), x0);
                y0 = fma(lo, vec4<f32>(d.y), y0);
                z0 = fma(lo, vec4<f32>(d.z), z0);
            }
        }
        workgroupBarrier();
    }
    return Sums(x0, y0, z0, x1, y1, z1);
}

// Job `q` of the group (0-7) from `s`, scaled to unit length when blending normals.
fn job_result(s: Sums, q: u32) -> vec3<f32> {
    var r: vec3<f32>;
    if q < 4u {
        r = vec3<f32>(s.x0[q], s.y0[q], s.z0[q]);
    } else {
        r = vec3<f32>(s.x1[q - 4u], s.y1[q - 4u], s.z1[q - 4u]);
    }
    if params.normalize == 1u {
        let l2 = dot(r, r);
        r = select(vec3<f32>(0.0), r * inverseSqrt(l2), l2 > 0.0);
    }
    return r;
}

// What one invocation blended: its group `g`, its vertex `v` (when it has one) and the sums.
struct Blended {
    g: u32,
    v: u32,
    has_vertex: bool,
    s: Sums,
}

fn blend_here(wid: vec3<u32>, lane: u32) -> Blended {
    let g = wid.x;
    let tile = wid.y + wid.z * params.tiles_y;
    let tile_ok = tile < params.tiles;
    let v = (params.tile_begin + tile) * TILE + lane;
    let has_vertex = tile_ok && v < params.vertices;
    return Blended(g, v, has_vertex, accumulate(g, tile, tile_ok, lane, has_vertex));
}

// Jobs in group `g` (eight but in a batch's last group; the dispatch has no empty group).
fn group_jobs(g: u32) -> u32 {
    return min(GROUP, params.jobs - g * GROUP);
}

// f32 output into `out`. Two entry points rather than one with every binding: each stays
// within WebGPU's eight storage buffers a stage (this one uses seven, `blend_packed` eight).
@compute @workgroup_size(64)
fn blend(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let b = blend_here(wid, lane);
    if !b.has_vertex {
        return;
    }
    for (var q = 0u; q < group_jobs(b.g); q++) {
        let r = job_result(b.s, q);
        let o = (b.g * GROUP + q) * params.vertices * 3u + b.v * 3u;
        out[o] = r.x;
        out[o + 1u] = r.y;
        out[o + 2u] = r.z;
    }
}

// The wire format (`PACK` 1, 2 or 3) into `packed`.
@compute @workgroup_size(64)
fn blend_packed(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let b = blend_here(wid, lane);
    if !b.has_vertex {
        return;
    }
    for (var q = 0u; q < group_jobs(b.g); q++) {
        let r = job_result(b.s, q);
        let job = b.g * GROUP + q;
        if PACK == 3u {
            write_residuals(job, b.v * 3u, r);
        } else {
            write_halves(job * params.vertices * 3u + b.v * 3u, r);
        }
    }
}
