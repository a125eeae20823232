//! Every WGSL file in `shaders/` parses and validates with naga — no GPU needed, so this runs
//! everywhere and catches shader errors before any device sees them.

use std::path::Path;

#[test]
fn every_wgsl_file_validates_with_naga() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders");
    let mut files: Vec<_> = std::fs::read_dir(&dir)
        .expect("shaders folder")
        .map(|e| e.expect("dir entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "wgsl"))
        .collect();
    files.sort();
    assert!(
        files.len() >= 4,
        "expected the engine's passes, found {files:?}"
    );
    for path in files {
        let src = std::fs::read_to_string(&path).expect("read shader");
        let module = naga::front::wgsl::parse_str(&src)
            .unwrap_or_else(|e| panic!("{}: {}", path.display(), e.emit_to_string(&src)));
        // pack2x16float needs f16 conversion in f32 shaders, which every WebGPU-compliant
        // device (and wgpu's Vulkan, Metal and DX12 backends) has; nothing else is assumed.
        let mut validator = naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::SHADER_FLOAT16_IN_FLOAT32,
        );
        validator
            .validate(&module)
            .unwrap_or_else(|e| panic!("{}: {}", path.display(), e.emit_to_string(&src)));
        assert!(
            !module.entry_points.is_empty(),
            "{}: no entry point",
            path.display()
        );
    }
}

#[test]
fn each_pass_has_the_entry_point_its_cpu_mirror_names() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders");
    for (file, entries) in [
        ("active.wgsl", &["build_active"][..]),
        ("blend.wgsl", &["blend", "blend_packed"][..]),
        ("face_normals.wgsl", &["face_normals"][..]),
        ("vertex_normals.wgsl", &["vertex_normals"][..]),
        ("skin.wgsl", &["skin"][..]),
        ("pack_f16.wgsl", &["pack_f16"][..]),
        ("pack_q16.wgsl", &["pack_q16", "pack_q16r"][..]),
        ("render.wgsl", &["vs_main", "fs_main"][..]),
    ] {
        let src = std::fs::read_to_string(dir.join(file)).expect("read shader");
        let module = naga::front::wgsl::parse_str(&src).expect("parse");
        for e in entries {
            assert!(
                module.entry_points.iter().any(|p| p.name == *e),
                "{file} has no entry point {e}"
            );
        }
    }
}

/// Member offsets and size of the WGSL struct `name` in `file`, as naga lays it out.
fn wgsl_struct(file: &str, name: &str) -> (Vec<(String, u32)>, u32) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("shaders")
        .join(file);
    let src = std::fs::read_to_string(&path).expect("read shader");
    let module = naga::front::wgsl::parse_str(&src).expect("parse");
    module
        .types
        .iter()
        .find_map(|(_, t)| match &t.inner {
            naga::TypeInner::Struct { members, span } if t.name.as_deref() == Some(name) => Some((
                members
                    .iter()
                    .map(|m| (m.name.clone().unwrap_or_default(), m.offset))
                    .collect(),
                *span,
            )),
            _ => None,
        })
        .unwrap_or_else(|| panic!("{file} has no struct {name}"))
}

#[test]
fn both_copies_of_the_q16_parameters_are_the_hosts_layout() {
    // `pack_q16.wgsl` and `blend.wgsl` each declare the uniform `layout::Q16PackParams` fills
    // (WGSL has no include): both must be its layout, member by member.
    use crowdmorph::engine::gpu::layout::Q16PackParams;
    use std::mem::offset_of;
    let host = [
        ("count", offset_of!(Q16PackParams, count)),
        ("row", offset_of!(Q16PackParams, row)),
        ("lo", offset_of!(Q16PackParams, lo)),
        ("hi", offset_of!(Q16PackParams, hi)),
        ("sub", offset_of!(Q16PackParams, sub)),
        ("mul", offset_of!(Q16PackParams, mul)),
        ("add", offset_of!(Q16PackParams, add)),
        ("per_job", offset_of!(Q16PackParams, per_job)),
    ];
    for (file, name) in [("pack_q16.wgsl", "Params"), ("blend.wgsl", "Q16Params")] {
        let (members, span) = wgsl_struct(file, name);
        assert_eq!(
            span as usize,
            size_of::<Q16PackParams>(),
            "{file} {name}: size"
        );
        for (field, at) in host {
            let wgsl = members.iter().find(|(m, _)| m == field).map(|(_, o)| *o);
            assert_eq!(wgsl, Some(at as u32), "{file} {name}.{field}");
        }
    }
}
