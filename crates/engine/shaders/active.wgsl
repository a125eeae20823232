// Pass `build_active` (CPU mirror: `engine::cpu::Groups::build_active`).
//
// Lorach 2007: only active weights are processed. For each group of eight jobs this pass writes
// the list of LOD slots that are active for at least one job of the group — among each job's
// first `shapes` slots of the importance order, with |w| > 1e-6 — together with the eight jobs'
// weights for that slot (zero for the jobs where it is inactive). Weights come straight from the
// clip tables resident on the GPU (Costigan et al. 2016, Fig. 4: rows are blendshapes, columns
// are frames), a blend summing its terms; per batch only the small job list is uploaded, plus
// one row per job that carries live weights.
//
// One workgroup per group: its 64 invocations take 64 consecutive slots at a time, and a scan
// over the workgroup gives each active slot its place, so the list is sorted by slot (the blend
// sums in list order, as the CPU engine does) while the slots are read in parallel. One
// invocation per group walking every slot in turn cost 10-30 µs before every blend.

// One term of a job's pose: `t ×` frame `frame` of the clip table at `table`.
struct Term {
    // Offset of the term's clip table in `tables` (row-major targets × frames).
    table: u32,
    // Frames in that clip.
    frames: u32,
    // Frame to play, already wrapped or clamped.
    frame: u32,
    // Fraction: 1.0 for a plain frame, a multiple of 1/4096 in a blend.
    t: f32,
}

// GPU Gems 3 ch. 15: blending in weight space is blending the meshes (Eq. 1 is linear), so a
// blend costs one weight per term and slot here, and nothing in the blend pass.
struct Job {
    // Length of the job's LOD prefix.
    shapes: u32,
    // Terms in use (1..=5); ignored for live weights.
    terms: u32,
    // Index of the job's first weight in `live`, or 0xffffffff: live weights (one per rig
    // channel, uploaded with the batch) instead of clip tables.
    live: u32,
    pad: u32,
    term: array<Term, 5>,
}

struct Params {
    // Jobs in this dispatch (a sub-batch of the batch when the output exceeds one binding).
    jobs: u32,
    groups: u32,
    slots: u32,
    // Index of the dispatch's first job in `jobs`.
    job_base: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> jobs: array<Job>;
@group(0) @binding(2) var<storage, read> tables: array<f32>;
// Slot -> target id: the rig's LOD order.
@group(0) @binding(3) var<storage, read> order: array<u32>;
// Per group, `slots` entries of two vec4s each (jobs 0-3, then 4-7): the active slots' eight
// weights; then, in `active_slots`, their slot numbers.
@group(0) @binding(4) var<storage, read_write> active_weights: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> active_slots: array<u32>;
@group(0) @binding(6) var<storage, read_write> active_count: array<u32>;
// Live weights of the batch's jobs that carry them, by target id.
@group(0) @binding(7) var<storage, read> live: array<f32>;

// Weights at or below this magnitude are inactive (the CPU engine's ACTIVE_WEIGHT_EPSILON).
const EPS: f32 = 1e-6;
const LANES: u32 = 64u;
const GROUP: u32 = 8u;

// The group's jobs, read once per workgroup rather than once per slot and job.
var<workgroup> sh_jobs: array<Job, GROUP>;

fn weight(q: u32, j: u32, s: u32) -> f32 {
    if j >= params.jobs {
        return 0.0;
    }
    let job = sh_jobs[q];
    if s >= job.shapes {
        return 0.0;
    }
    let t = order[s];
    var w = 0.0;
    if job.live != 0xffffffffu {
        w = live[job.live + t];
    } else {
        for (var k = 0u; k < job.terms; k++) {
            let term = job.term[k];
            w += term.t * tables[term.table + t * term.frames + term.frame];
        }
    }
    return select(0.0, w, abs(w) > EPS);
}


@compute @workgroup_size(64)
fn build_active(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let g = wid.x;
    let j = g * GROUP;
    if lane < GROUP && j + lane < params.jobs {
        sh_jobs[lane] = jobs[params.job_base + j + lane];
    }
    workgroupBarrier();
    var n = 0u;
    for (var start = 0u; start < params.slots; start += LANES) {
        let s = start + lane;
        var lo = vec4<f32>(0.0);
        var hi = vec4<f32>(0.0);
        if s < params.slots {
            lo = vec4<f32>(weight(0u, j, s), weight(1u, j + 1u, s), weight(2u, j + 2u, s),
                weight(3u, j + 3u, s));
            hi = vec4<f32>(weight(4u, j + 4u, s), weight(5u, j + 5u, s), weight(6u, j + 6u, s),
                weight(7u, j + 7u, s));
        }
        let on = any(lo != vec4<f32>(0.0)) || any(hi != vec4<f32>(0.0));
        let at = place(lane, u32(on));
        if on {
            let e = g * params.slots + n + at;
            active_weights[2u * e] = lo;
            active_weights[2u * e + 1u] = hi;
            active_slots[e] = s;
        }
        n += workgroupUniformLoad(&sh_total);
    }
    if lane == 0u {
        active_count[g] = n;
    }
}
