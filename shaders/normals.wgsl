// Passes `face_normals` and `vertex_normals` (CPU mirror: `engine::cpu::CpuRig::recompute_normals`).
//
// Normals of primitives whose targets carry no normal deltas are recomputed from the blended
// positions: first each triangle's area-weighted normal (the unnormalized cross product), then
// each vertex sums the normals of its incident triangles (a gather over a CSR list, so no
// atomics) and normalizes. Vertices on no triangle get +Z, as on the CPU.

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
// jobs × triangles × 3 floats of scratch.
@group(0) @binding(3) var<storage, read_write> faces: array<f32>;

// `vertex_normals` reads the face normals back through its own binding (each entry point gets
// its own pipeline layout with only the bindings it uses).
@group(0) @binding(4) var<storage, read> face_in: array<f32>;
// The recomputed vertices, their incident-triangle ranges, and the incident triangles.
@group(0) @binding(5) var<storage, read> recomputed: array<u32>;
@group(0) @binding(6) var<storage, read> incident_start: array<u32>;
@group(0) @binding(7) var<storage, read> incident: array<u32>;
@group(0) @binding(8) var<storage, read_write> normals: array<f32>;

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

@compute @workgroup_size(64)
fn vertex_normals(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    let job = gid.y;
    if i >= params.recomputed || job >= params.jobs {
        return;
    }
    var sum = vec3<f32>(0.0);
    for (var k = incident_start[i]; k < incident_start[i + 1u]; k++) {
        let o = (job * params.triangles + incident[k]) * 3u;
        sum += vec3<f32>(face_in[o], face_in[o + 1u], face_in[o + 2u]);
    }
    let l2 = dot(sum, sum);
    let n = select(vec3<f32>(0.0, 0.0, 1.0), sum * inverseSqrt(l2), l2 > 0.0);
    let o = job * params.vertices * 3u + recomputed[i] * 3u;
    normals[o] = n.x;
    normals[o + 1u] = n.y;
    normals[o + 2u] = n.z;
}
