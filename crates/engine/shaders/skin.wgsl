// Pass `skin` (CPU mirror: `engine::cpu::skin_lanes`, in the output stage of `blend`), after
// `blend` and before the normals
// are recomputed: glTF §3.7.3 poses a skinned mesh as morph targets first, then linear blend
// skinning.
//
// One invocation per (vertex, job): the vertex's blended position becomes Σ w M p over its
// (up to four) bones' matrices in the job's pose, and, where its normal was blended (rigs with
// normal deltas), the normal becomes normalize(Σ w N n). A vertex whose first weight is 0
// follows no bone (a primitive that is neither skinned nor under an animated node) and is left
// as blended. The host resolves each unique job's bone matrices once (clones share the job),
// so this pass is a gather and twelve multiply-adds per influence. The influences come in the
// CPU's order (`layout::pack_influences`) and are summed with the same fused multiply-adds, so
// the same blended positions skin to the CPU engine's bit for bit where the driver fuses
// `fma()` (NVIDIA's and lavapipe do; WGSL allows an unfused one): a skinned rig's neutral, the
// reference of q16r residuals, is then the same on both engines.

struct Params {
    // Vertices of the rig: the stride per job is vertices * 3.
    vertices: u32,
    // Jobs in this dispatch.
    jobs: u32,
    // Bones of the rig: the stride per job in `bones` is bones * 6 rows.
    bones: u32,
    // 1 when `normals` holds blended normals to skin, else 0.
    normals: u32,
    // Invocations along x per row of vertices (workgroups_x * 64).
    row: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
// Per vertex six words: bone ids 0 and 1 (low and high halves), bone ids 2 and 3, then the
// four weights as f32 bits.
@group(0) @binding(1) var<storage, read> influences: array<u32>;
// Per job, per bone: three rows of the affine position transform ([m0, m1, m2, t]), then three
// rows of the normal transform ([n0, n1, n2, 0]).
@group(0) @binding(2) var<storage, read> bones: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> positions: array<f32>;
@group(0) @binding(4) var<storage, read_write> normals: array<f32>;

// One row of a bone's transform: r.x x + r.y y + r.z z + r.w, as the CPU's `skin_row`.
fn row(r: vec4<f32>, p: vec4<f32>) -> f32 {
    return fma(r.x, p.x, fma(r.y, p.y, fma(r.z, p.z, r.w)));
}

@compute @workgroup_size(64)
fn skin(@builtin(global_invocation_id) gid: vec3<u32>) {
    let v = gid.x + gid.z * params.row;
    let job = gid.y;
    if v >= params.vertices || job >= params.jobs {
        return;
    }
    let i = v * 6u;
    let w = vec4<f32>(
        bitcast<f32>(influences[i + 2u]),
        bitcast<f32>(influences[i + 3u]),
        bitcast<f32>(influences[i + 4u]),
        bitcast<f32>(influences[i + 5u]),
    );
    if w.x == 0.0 {
        return;
    }
    let ids = array<u32, 4>(
        influences[i] & 0xffffu,
        influences[i] >> 16u,
        influences[i + 1u] & 0xffffu,
        influences[i + 1u] >> 16u,
    );
    let ws = array<f32, 4>(w.x, w.y, w.z, w.w);
    let o = job * params.vertices * 3u + v * 3u;
    let p = vec4<f32>(positions[o], positions[o + 1u], positions[o + 2u], 1.0);
    let skin_normals = params.normals != 0u;
    var n = vec4<f32>(0.0);
    if skin_normals {
        n = vec4<f32>(normals[o], normals[o + 1u], normals[o + 2u], 0.0);
    }
    var sp = vec3<f32>(0.0);
    var sn = vec3<f32>(0.0);
    for (var k = 0u; k < 4u; k++) {
        if ws[k] == 0.0 {
            continue;
        }
        let b = (job * params.bones + ids[k]) * 6u;
        // Fused multiply-adds in the CPU's order (`skin_lanes`, `skin_row`), the influences in
        // its order too.
        let w = vec3<f32>(ws[k]);
        sp = fma(w, vec3<f32>(row(bones[b], p), row(bones[b + 1u], p), row(bones[b + 2u], p)), sp);
        if skin_normals {
            sn = fma(
                w,
                vec3<f32>(row(bones[b + 3u], n), row(bones[b + 4u], n), row(bones[b + 5u], n)),
                sn,
            );
        }
    }
    positions[o] = sp.x;
    positions[o + 1u] = sp.y;
    positions[o + 2u] = sp.z;
    if skin_normals {
        let l2 = dot(sn, sn);
        // As the CPU's `try_normalize`: +Z where the sum has no direction.
        let ok = l2 > 0.0 && l2 < 3.0e38;
        let m = select(vec3<f32>(0.0, 0.0, 1.0), sn * inverseSqrt(l2), ok);
        normals[o] = m.x;
        normals[o + 1u] = m.y;
        normals[o + 2u] = m.z;
    }
}
