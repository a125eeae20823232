// Pass `build_active` (CPU mirror: `engine::cpu::Groups::build_active`).
//
// Lorach 2007: only active weights are processed. For each group of four jobs this pass writes
// the list of LOD slots that are active for at least one job of the group — among each job's
// first `shapes` slots of the importance order, with |w| > 1e-6 — together with the four jobs'
// weights for that slot (zero for the jobs where it is inactive). Weights come straight from the
// clip tables resident on the GPU (Costigan et al. 2016, Fig. 4: rows are blendshapes, columns
// are frames), a blend summing its terms; per batch only the small job list is uploaded, plus
// one row per job that carries live weights.
//
// One invocation per group scans the slots in order, so the list is sorted by slot and the
// summation order matches the CPU engine's.

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
// Per group, `slots` entries: the active slots' four weights, then their slot numbers.
@group(0) @binding(4) var<storage, read_write> active_weights: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> active_slots: array<u32>;
@group(0) @binding(6) var<storage, read_write> active_count: array<u32>;
// Live weights of the batch's jobs that carry them, by target id.
@group(0) @binding(7) var<storage, read> live: array<f32>;

// Weights at or below this magnitude are inactive (the CPU engine's ACTIVE_WEIGHT_EPSILON).
const EPS: f32 = 1e-6;

fn weight(j: u32, s: u32) -> f32 {
    if j >= params.jobs {
        return 0.0;
    }
    let job = jobs[params.job_base + j];
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
fn build_active(@builtin(global_invocation_id) gid: vec3<u32>) {
    let g = gid.x;
    if g >= params.groups {
        return;
    }
    let j = g * 4u;
    var n = 0u;
    for (var s = 0u; s < params.slots; s++) {
        let w = vec4<f32>(weight(j, s), weight(j + 1u, s), weight(j + 2u, s), weight(j + 3u, s));
        if any(w != vec4<f32>(0.0)) {
            active_weights[g * params.slots + n] = w;
            active_slots[g * params.slots + n] = s;
            n++;
        }
    }
    active_count[g] = n;
}
