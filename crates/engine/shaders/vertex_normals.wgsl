// Pass `vertex_normals`, the second of the two that recompute normals (CPU mirror:
// `engine::cpu::CpuRig::recompute_normals`; the first pass is `face_normals.wgsl`).
//
// Each recomputed vertex sums the normals of its incident triangles (a gather over a CSR
// list, so no atomics) and normalizes. Vertices on no triangle get +Z, as on the CPU. The
// bindings keep the numbers they have next to `face_normals`, so one parameter block and one
// scratch buffer serve both passes.

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
// The face normals `face_normals` wrote.
@group(0) @binding(4) var<storage, read> face_in: array<f32>;
// The recomputed vertices, their incident-triangle ranges, and the incident triangles.
@group(0) @binding(5) var<storage, read> recomputed: array<u32>;
@group(0) @binding(6) var<storage, read> incident_start: array<u32>;
@group(0) @binding(7) var<storage, read> incident: array<u32>;
@group(0) @binding(8) var<storage, read_write> normals: array<f32>;

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
