// Pass `pack_f16` (CPU mirror: `engine::VertexData::encode`, its f16 branch).
//
// Rounds an f32 buffer to binary16, two values per u32 (little-endian halves, so the bytes read
// back are the f16 array itself). An odd count pads the last half with zero.

struct Params {
    // f32 values to pack.
    count: u32,
    // Invocations along x per row of the dispatch (workgroups_x * 64).
    row: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read_write> dst: array<u32>;

@compute @workgroup_size(64)
fn pack_f16(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x + gid.y * params.row;
    let pairs = (params.count + 1u) / 2u;
    if i >= pairs {
        return;
    }
    let a = src[2u * i];
    let b = select(0.0, src[min(2u * i + 1u, params.count - 1u)], 2u * i + 1u < params.count);
    dst[i] = pack2x16float(vec2<f32>(a, b));
}
