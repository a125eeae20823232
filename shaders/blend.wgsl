// Pass `blend` (CPU mirror: `engine::cpu::CpuRig::blend`).
//
// Eq. 1 of Costigan et al. 2016, v = base + sum_k w_k * delta_k, for every vertex of a tile and
// four jobs at once. One workgroup is one tile of 64 vertices and one group of four jobs; each
// invocation owns one vertex and keeps x, y, z accumulators for the four jobs in vec4s, so every
// delta it loads serves four jobs. The loop visits only the group's active slots (Lorach's
// index + weight list from `build_active`); a slot that does not move this tile costs one mask
// lookup and no loads.
//
// Deltas are stored per (tile, slot) as a 64-lane structure-of-arrays block: x[64], y[64],
// z[64], so the 64 invocations of a tile read consecutive floats (coalesced). Which slots have a
// block in a tile is a bitmask per 32 slots with the running block count, so finding slot s's
// block is one load and a popcount.
//
// The same pass blends normals (base normals + normal deltas, then normalized) when
// `params.normalize` is 1.

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
    // Workgroups along x; the tile is workgroup_id.x + workgroup_id.z * tiles_x.
    tiles_x: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
// Neutral values of the chunk's vertices, x y z per vertex.
@group(0) @binding(1) var<storage, read> base: array<f32>;
// Delta blocks of the chunk, 192 floats each.
@group(0) @binding(2) var<storage, read> blocks: array<f32>;
// Per (chunk tile, word): .x the slots of the word that have a block, .y the index of the first
// of them in `blocks`.
@group(0) @binding(3) var<storage, read> masks: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read> active_weights: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> active_slots: array<u32>;
@group(0) @binding(6) var<storage, read> active_count: array<u32>;
// jobs × vertices × 3 floats.
@group(0) @binding(7) var<storage, read_write> out: array<f32>;

const TILE: u32 = 64u;
const BATCH: u32 = 256u;
const NONE: u32 = 0xffffffffu;

var<workgroup> sh_weights: array<vec4<f32>, BATCH>;
var<workgroup> sh_blocks: array<u32, BATCH>;
var<workgroup> sh_count: u32;

fn block_of(tile: u32, s: u32) -> u32 {
    let m = masks[tile * params.words + s / 32u];
    let bit = 1u << (s % 32u);
    if (m.x & bit) == 0u {
        return NONE;
    }
    return m.y + countOneBits(m.x & (bit - 1u));
}

@compute @workgroup_size(64)
fn blend(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let tile = wid.x + wid.z * params.tiles_x;
    let g = wid.y;
    let tile_ok = tile < params.tiles;
    let v = (params.tile_begin + tile) * TILE + lane;
    let has_vertex = tile_ok && v < params.vertices;

    var ax = vec4<f32>(0.0);
    var ay = vec4<f32>(0.0);
    var az = vec4<f32>(0.0);
    if has_vertex {
        let lv = tile * TILE + lane;
        ax = vec4<f32>(base[lv * 3u]);
        ay = vec4<f32>(base[lv * 3u + 1u]);
        az = vec4<f32>(base[lv * 3u + 2u]);
    }

    if lane == 0u {
        sh_count = active_count[g];
    }
    let n = workgroupUniformLoad(&sh_count);
    for (var start = 0u; start < n; start += BATCH) {
        let m = min(BATCH, n - start);
        // Stage this batch of the active list in workgroup memory, with this tile's block for
        // each slot, so the inner loop reads nothing from global memory but deltas.
        for (var i = lane; i < m; i += TILE) {
            let e = g * params.slots + start + i;
            sh_weights[i] = active_weights[e];
            sh_blocks[i] = select(NONE, block_of(tile, active_slots[e]), tile_ok);
        }
        workgroupBarrier();
        for (var i = 0u; i < m; i++) {
            let b = sh_blocks[i];
            if b != NONE {
                let w = sh_weights[i];
                let o = b * 192u + lane;
                ax += w * blocks[o];
                ay += w * blocks[o + 64u];
                az += w * blocks[o + 128u];
            }
        }
        workgroupBarrier();
    }

    if !has_vertex {
        return;
    }
    let stride = params.vertices * 3u;
    for (var q = 0u; q < 4u; q++) {
        let job = g * 4u + q;
        if job >= params.jobs {
            break;
        }
        var r = vec3<f32>(ax[q], ay[q], az[q]);
        if params.normalize == 1u {
            let l2 = dot(r, r);
            r = select(vec3<f32>(0.0), r * inverseSqrt(l2), l2 > 0.0);
        }
        let o = job * stride + v * 3u;
        out[o] = r.x;
        out[o + 1u] = r.y;
        out[o + 2u] = r.z;
    }
}
