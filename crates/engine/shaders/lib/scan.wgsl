// Shared piece (`crates/engine/shaders/lib/`): compiled in front of `active.wgsl` and `blend.wgsl`, which
// both compact a list across a workgroup of 64 invocations (WGSL has no include; the engine
// joins the sources, `engine::gpu::SHADERS`).

var<workgroup> sh_scan: array<u32, 64>;
var<workgroup> sh_part: array<u32, 8>;
var<workgroup> sh_total: u32;

// Where the first of `mine` items of invocation `lane` goes when every invocation's items are
// laid out in invocation order (an exclusive scan over the workgroup); the total is left in
// `sh_total`. Eight partial sums rather than a 64-wide Hillis-Steele scan: three barriers
// instead of thirteen, which is what a workgroup with a short list pays for. Every invocation
// of the workgroup calls it.
fn place(lane: u32, mine: u32) -> u32 {
    sh_scan[lane] = mine;
    workgroupBarrier();
    if lane < 8u {
        var t = 0u;
        for (var k = 0u; k < 8u; k++) {
            t += sh_scan[lane * 8u + k];
        }
        sh_part[lane] = t;
    }
    workgroupBarrier();
    if lane == 0u {
        var t = 0u;
        for (var k = 0u; k < 8u; k++) {
            let x = sh_part[k];
            sh_part[k] = t;
            t += x;
        }
        sh_total = t;
    }
    workgroupBarrier();
    var at = sh_part[lane / 8u];
    for (var k = lane & ~7u; k < lane; k++) {
        at += sh_scan[k];
    }
    return at;
}
