//! The memory cost model (`rig::RigShape`) against what the layers above it build: the CPU
//! engine's layout and the stored record. (Moved here from `rig/cost.rs` when the data layer
//! became its own crate: the check needs the engine and the codec, which sit above it.)

use crowdmorph::rig::{CPU_BLOCK, PrimShape, RigShape};

#[test]
fn the_embedded_rig_costs_what_its_arrays_and_layouts_hold() {
    let rig = crowdmorph::embedded::default_rig();
    let cost = RigShape::of(&rig).cost(false);
    // Exact counts: the rig's own arrays are what `Rig::host_bytes` reports (the LOD
    // table is bounded by its 64-level cap).
    let host = rig.host_bytes() as u64;
    assert!(
        cost.rig >= host && cost.rig <= host + 1024,
        "{} vs {host}",
        cost.rig
    );
    // From exact counts, the layout estimate holds the layout the CPU engine builds and is
    // within a few percent of it in the rig's vertex order (the estimate counts the blocks
    // of tiles of consecutive vertices; the engine's regrouping only removes blocks).
    let cpu = crowdmorph::engine::cpu::CpuRig::new(&rig);
    let built = cpu.bytes() as u64;
    let (blocks, in_order) = cpu.blocks();
    assert!(blocks <= in_order);
    let in_order_bytes = built + (in_order - blocks) as u64 * CPU_BLOCK;
    assert!(cost.layout >= built, "{} < {built}", cost.layout);
    assert!(
        cost.layout <= in_order_bytes + in_order_bytes / 20,
        "{} vs {in_order_bytes}",
        cost.layout
    );
    let stored = crowdmorph::store::codec::to_stored(&rig)
        .expect("encode")
        .len() as u64;
    assert!(cost.stored >= stored, "{} < {stored}", cost.stored);
}

#[test]
fn mesh_level_shapes_are_counted_as_the_derived_rigs_have_them() {
    let mut rig = crowdmorph::embedded::default_rig();
    let spec = crowdmorph::engine::lod::LodSpec {
        method: crowdmorph::engine::lod::OrderMethod::FileOrder,
        mesh_fractions: vec![0.5, 0.1],
        ..crowdmorph::engine::lod::LodSpec::default()
    };
    rig.lod = crowdmorph::engine::lod::build_lod(&rig, &spec, None, None).expect("lod");
    let counted = RigShape::of(&rig).mesh_levels;
    let derived: Vec<Vec<PrimShape>> = crowdmorph::rig::mesh_level_rigs(&rig)
        .expect("derive")
        .iter()
        .map(|r| RigShape::of(r).primitives)
        .collect();
    assert_eq!(counted.len(), 2);
    assert_eq!(counted, derived);
}
