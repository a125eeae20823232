// Pass `face_normals`, the first of the two that recompute normals (CPU mirror:
// `engine::cpu::CpuRig::recompute_normals`; the second pass is `vertex_normals.wgsl`).
//
// Normals of primitives whose targets carry no normal deltas are recomputed from the blended
// positions. This pass writes each triangle's area-weighted normal (the unnormalized cross
// product) to a scratch buffer.

struct Params {
    // Vertices of the rig: the stride per job is vertices * 3.
    vertices: u32,
    // Triangles of the recomputed primitives.
    triangles: u32,
    // Vertices whose normal is recomputed.
    recomputed: u32,
    // Jobs in this dispatch.
    jobs: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> positions: array<f32>;
// Three global vertex indices per triangle.
@group(0) @binding(2) var<storage, read> triangles: array<u32>;
// jobs × triangles × 3 floats of scratch, read by `vertex_normals`.
@group(0) @binding(3) var<storage, read_write> faces: array<f32>;

fn position(job: u32, v: u32) -> vec3<f32> {
    let o = job * params.vertices * 3u + v * 3u;
    return vec3<f32>(positions[o], positions[o + 1u], positions[o + 2u]);
}

@compute @workgroup_size(64)
fn face_normals(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = gid.x;
    let job = gid.y;
    if t >= params.triangles || job >= params.jobs {
        return;
    }
    let a = position(job, triangles[t * 3u]);
    let b = position(job, triangles[t * 3u + 1u]);
    let c = position(job, triangles[t * 3u + 2u]);
    let n = cross(b - a, c - a);
    let o = (job * params.triangles + t) * 3u;
    faces[o] = n.x;
    faces[o + 1u] = n.y;
    faces[o + 2u] = n.z;
}
