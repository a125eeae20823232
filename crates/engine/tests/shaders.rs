//! Every WGSL module the engine compiles (each pass's file after the shared pieces of
//! `shaders/lib/` it uses, `crowdmorph_engine::gpu::SHADERS`) and the renderer's parses and validates with
//! naga — no GPU needed, so this runs everywhere and catches shader errors before any device
//! sees them.

use std::path::Path;

use crowdmorph_engine::gpu::SHADERS;

/// Each compiled module by its file name: the engine's passes as joined, and the renderer's.
fn modules() -> Vec<(String, String)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders");
    let mut v: Vec<(String, String)> = SHADERS
        .iter()
        .map(|(n, s)| (n.to_string(), s.to_string()))
        .collect();
    let render = std::fs::read_to_string(dir.join("render.wgsl")).expect("render.wgsl");
    v.push(("render.wgsl".into(), render));
    v
}

/// The `.wgsl` files under `dir`, with their paths relative to `shaders/`.
fn wgsl_files(dir: &Path, under: &str) -> Vec<(String, String)> {
    let mut files = Vec::new();
    for e in std::fs::read_dir(dir).expect("shaders folder") {
        let path = e.expect("dir entry").path();
        let name = path
            .file_name()
            .expect("name")
            .to_string_lossy()
            .into_owned();
        if path.is_dir() {
            files.extend(wgsl_files(&path, &format!("{under}{name}/")));
        } else if path.extension().is_some_and(|e| e == "wgsl") {
            let src = std::fs::read_to_string(&path).expect("read shader");
            files.push((format!("{under}{name}"), src));
        }
    }
    files
}

#[test]
fn every_wgsl_file_validates_with_naga() {
    let modules = modules();
    for (name, src) in &modules {
        let module = naga::front::wgsl::parse_str(src)
            .unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(src)));
        // pack2x16float needs f16 conversion in f32 shaders, which every WebGPU-compliant
        // device (and wgpu's Vulkan, Metal and DX12 backends) has; nothing else is assumed.
        let mut validator = naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::SHADER_FLOAT16_IN_FLOAT32,
        );
        validator
            .validate(&module)
            .unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(src)));
        assert!(!module.entry_points.is_empty(), "{name}: no entry point");
    }
    // Every file in `shaders/` is compiled: a pass's file as its module's end, a shared piece
    // inside some module.
    let files = wgsl_files(&Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders"), "");
    assert!(
        files.len() >= 4,
        "expected the engine's passes, found {files:?}"
    );
    for (path, src) in files {
        let used = match path.strip_prefix("lib/") {
            Some(_) => modules.iter().any(|(_, m)| m.contains(&src)),
            None => modules.iter().any(|(n, m)| *n == path && m.ends_with(&src)),
        };
        assert!(
            used,
            "shaders/{path} is in no module the engine or renderer compiles"
        );
    }
}

#[test]
fn each_pass_has_the_entry_point_its_cpu_mirror_names() {
    let modules = modules();
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
        let (_, src) = modules
            .iter()
            .find(|(n, _)| n == file)
            .unwrap_or_else(|| panic!("no module {file}"));
        let module = naga::front::wgsl::parse_str(src).expect("parse");
        for e in entries {
            assert!(
                module.entry_points.iter().any(|p| p.name == *e),
                "{file} has no entry point {e}"
            );
        }
    }
}

/// Member offsets and size of the WGSL struct `name` in the compiled module `file`, as naga
/// lays it out.
fn wgsl_struct(file: &str, name: &str) -> (Vec<(String, u32)>, u32) {
    let (_, src) = SHADERS
        .iter()
        .find(|(n, _)| *n == file)
        .unwrap_or_else(|| panic!("no module {file}"));
    let module = naga::front::wgsl::parse_str(src).expect("parse");
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
fn both_users_of_the_q16_parameters_see_the_hosts_layout() {
    // `pack_q16` and `blend` read the uniform `layout::Q16PackParams` fills through
    // `lib/q16.wgsl`'s `Q16Params`: as each module lays it out, member by member, it must be
    // the host's layout.
    use crowdmorph_engine::gpu::layout::Q16PackParams;
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
    for file in ["pack_q16.wgsl", "blend.wgsl"] {
        let (members, span) = wgsl_struct(file, "Q16Params");
        assert_eq!(
            span as usize,
            size_of::<Q16PackParams>(),
            "{file} Q16Params: size"
        );
        for (field, at) in host {
            let wgsl = members.iter().find(|(m, _)| m == field).map(|(_, o)| *o);
            assert_eq!(wgsl, Some(at as u32), "{file} Q16Params.{field}");
        }
    }
}
