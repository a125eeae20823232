//! glTF 2.0 rigs: `.gltf` (embedded or external buffers) and `.glb`.
//!
//! A rig is the set of primitives of the default scene (or the first scene, or every root node
//! when there is no scene) in rig space: node transforms at rest are applied, deltas are
//! transformed by the node's linear part and normals by its inverse transpose. Targets are
//! named by `mesh.extras.targetNames`, else `target_<i>`, and merged rig-wide by name. Every
//! animation with `weights` channels becomes a clip baked at a fixed rate.

use std::borrow::Cow;
use std::collections::HashMap;
use std::path::{Component, Path};

use base64::Engine as _;
use glam::{Mat3, Mat4, Vec3, Vec4};
use gltf::animation::{Interpolation as GltfInterpolation, Property};
use gltf::mesh::{Mode, Semantic};
use serde::Deserialize;

use super::accessor::Source;
use super::{ImportError, ImportOptions};
use crate::rig::{
    Clip, Interpolation, KeyTrack, Lod, MAX_FRAMES, Primitive, Rig, SparseTarget, TargetId,
    sample_track, sparsify, vertex_normals,
};

/// glTF extensions a file may require that we read correctly.
const SUPPORTED_REQUIRED: &[&str] = &["KHR_mesh_quantization"];

/// Deepest node hierarchy we follow.
const MAX_DEPTH: usize = 256;

/// A parsed document with its buffers loaded.
pub(crate) struct Parsed<'a> {
    pub(crate) doc: gltf::Document,
    pub(crate) source: Source<'a>,
}

/// Reads a rig from the bytes of a `.glb` or `.gltf` file.
pub fn rig_from_slice(bytes: &[u8], options: &ImportOptions) -> Result<Rig, ImportError> {
    let parsed = parse(bytes, options)?;
    build_rig(&parsed, options)
}

/// Splits a GLB container into its JSON and BIN chunks, checking every length.
fn split_glb(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>), ImportError> {
    let bad = |m: &str| ImportError::Glb(m.to_string());
    let u32_at = |at: usize| -> Option<u32> {
        bytes
            .get(at..at + 4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    };
    if !bytes.starts_with(b"glTF") {
        return Err(bad("wrong magic (expected \"glTF\")"));
    }
    if bytes.len() < 12 {
        return Err(ImportError::Glb(format!(
            "truncated: {} bytes, a GLB header needs 12",
            bytes.len()
        )));
    }
    let version = u32_at(4).unwrap_or(0);
    if version != 2 {
        return Err(ImportError::Glb(format!(
            "unsupported GLB version {version}"
        )));
    }
    let total = u32_at(8).unwrap_or(0) as usize;
    if total > bytes.len() {
        return Err(ImportError::Glb(format!(
            "truncated: header says {total} bytes, file has {}",
            bytes.len()
        )));
    }
    if total < 20 {
        return Err(bad("too short to hold a JSON chunk"));
    }
    let bytes = &bytes[..total];
    let mut at = 12;
    let mut json = None;
    let mut bin = None;
    while at + 8 <= bytes.len() {
        let len = u32_at(at).unwrap_or(0) as usize;
        let kind = &bytes[at + 4..at + 8];
        let start = at + 8;
        let end = start
            .checked_add(len)
            .filter(|&e| e <= bytes.len())
            .ok_or_else(|| {
                ImportError::Glb(format!(
                    "truncated: chunk at byte {at} declares {len} bytes, only {} remain",
                    bytes.len() - start
                ))
            })?;
        match kind {
            b"JSON" if json.is_none() && at == 12 => json = Some(&bytes[start..end]),
            b"BIN\0" if bin.is_none() && json.is_some() => bin = Some(&bytes[start..end]),
            b"JSON" | b"BIN\0" => return Err(bad("chunks out of order or repeated")),
            _ => {} // Unknown chunks must be ignored (glTF 2.0 §4.4.3.1).
        }
        at = (end + 3) & !3;
    }
    let json = json.ok_or_else(|| bad("first chunk is not JSON"))?;
    Ok((json, bin))
}

/// Parses, validates and loads the buffers of a glTF or GLB file.
pub(crate) fn parse<'a>(
    bytes: &'a [u8],
    options: &ImportOptions,
) -> Result<Parsed<'a>, ImportError> {
    let (json, bin) = if bytes.starts_with(b"glTF") {
        split_glb(bytes)?
    } else {
        let first = bytes.iter().find(|b| !b.is_ascii_whitespace());
        if first != Some(&b'{') {
            return Err(ImportError::Glb(
                "not a glTF file: wrong magic (expected \"glTF\" or a JSON object)".into(),
            ));
        }
        (bytes, None)
    };
    let mut root: gltf::json::Root =
        gltf::json::deserialize::from_slice(json).map_err(|e| ImportError::Json(e.to_string()))?;
    drop_unknown_channels(&mut root);
    validate(&root)?;
    let doc = gltf::Document::from_json_without_validation(root);
    let mut buffers = Vec::new();
    for buffer in doc.buffers() {
        let index = buffer.index();
        let bad = |problem: String| ImportError::Buffer { index, problem };
        let data: Cow<'a, [u8]> = match buffer.source() {
            gltf::buffer::Source::Bin => Cow::Borrowed(
                bin.ok_or_else(|| bad("refers to the GLB BIN chunk, which is missing".into()))?,
            ),
            gltf::buffer::Source::Uri(uri) => Cow::Owned(load_uri(uri, options).map_err(bad)?),
        };
        if data.len() < buffer.length() {
            return Err(bad(format!(
                "declares {} bytes but only {} are present",
                buffer.length(),
                data.len()
            )));
        }
        buffers.push(match data {
            Cow::Borrowed(b) => Cow::Borrowed(&b[..buffer.length()]),
            Cow::Owned(mut v) => {
                v.truncate(buffer.length());
                Cow::Owned(v)
            }
        });
    }
    Ok(Parsed {
        doc,
        source: Source::new(buffers, options.max_decoded_bytes),
    })
}

/// Removes animation channels whose target path is not a glTF 2.0 property (extensions such as
/// KHR_animation_pointer define their own): they cannot drive morph weights, and the `gltf`
/// crate's accessors would panic on them.
fn drop_unknown_channels(root: &mut gltf::json::Root) {
    use gltf::json::validation::Checked;
    for (a, anim) in root.animations.iter_mut().enumerate() {
        let before = anim.channels.len();
        anim.channels
            .retain(|c| matches!(c.target.path, Checked::Valid(_)));
        if anim.channels.len() != before {
            tracing::warn!(
                animation = a,
                dropped = before - anim.channels.len(),
                "ignoring channels with unknown target paths"
            );
        }
    }
}

/// Runs the `gltf` crate's reference validation, tolerating what we handle ourselves.
fn validate(root: &gltf::json::Root) -> Result<(), ImportError> {
    use gltf::json::validation::{Error, Validate};
    // The crate's own validation indexes accessors from primitive attributes before checking
    // them; check those references first so a dangling one is an error, not a panic.
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, prim) in mesh.primitives.iter().enumerate() {
            let targets = prim
                .targets
                .iter()
                .flatten()
                .flat_map(|t| [t.positions, t.normals, t.tangents].into_iter().flatten());
            for acc in prim.attributes.values().copied().chain(targets) {
                if acc.value() >= root.accessors.len() {
                    return Err(ImportError::Invalid(format!(
                        "meshes[{m}].primitives[{p}] refers to accessor {} of {}",
                        acc.value(),
                        root.accessors.len()
                    )));
                }
            }
        }
    }
    // The crate does not validate channel targets, and its accessors unwrap them.
    for (a, anim) in root.animations.iter().enumerate() {
        for (c, ch) in anim.channels.iter().enumerate() {
            if ch.target.node.value() >= root.nodes.len() {
                return Err(ImportError::Invalid(format!(
                    "animations[{a}].channels[{c}] targets node {} of {}",
                    ch.target.node.value(),
                    root.nodes.len()
                )));
            }
            if ch.sampler.value() >= anim.samplers.len() {
                return Err(ImportError::Invalid(format!(
                    "animations[{a}].channels[{c}] uses sampler {} of {}",
                    ch.sampler.value(),
                    anim.samplers.len()
                )));
            }
        }
    }
    for ext in &root.extensions_required {
        if !SUPPORTED_REQUIRED.contains(&ext.as_str())
            && !gltf::json::extensions::ENABLED_EXTENSIONS.contains(&ext.as_str())
        {
            return Err(ImportError::UnsupportedExtension(ext.clone()));
        }
    }
    let mut errors = Vec::new();
    let outcome = std::panic::catch_unwind(|| {
        let mut report = |path: &dyn Fn() -> gltf::json::Path, error: Error| {
            let p = path().to_string();
            // Missing POSITION min/max is common in the wild and harmless here (we compute
            // bounds); extensions we support are allowed in extensionsRequired.
            let tolerated = (error == Error::Missing
                && (p.ends_with(".min") || p.ends_with(".max")))
                || (error == Error::Unsupported && p.starts_with("extensionsRequired"));
            if !tolerated {
                errors.push(format!("{p}: {error}"));
            }
        };
        root.validate(root, gltf::json::Path::new, &mut report);
        errors
    });
    match outcome {
        Ok(errors) if errors.is_empty() => Ok(()),
        Ok(errors) => Err(ImportError::Invalid(errors.join("; "))),
        Err(_) => Err(ImportError::Invalid(
            "document has dangling references".into(),
        )),
    }
}

/// Loads a buffer URI: a base64 data URI, or a relative file under `options.base_dir`.
fn load_uri(uri: &str, options: &ImportOptions) -> Result<Vec<u8>, String> {
    if let Some(rest) = uri.strip_prefix("data:") {
        let (meta, data) = rest
            .split_once(',')
            .ok_or_else(|| "malformed data URI".to_string())?;
        if !meta.ends_with(";base64") {
            return Err("data URI is not base64".into());
        }
        return base64::engine::general_purpose::STANDARD
            .decode(data.trim())
            .map_err(|e| format!("bad base64 in data URI: {e}"));
    }
    let Some(base) = &options.base_dir else {
        return Err(format!(
            "refers to external file {uri:?}; send a GLB or a glTF with embedded (data URI) buffers"
        ));
    };
    let decoded = percent_decode(uri);
    let rel = Path::new(&decoded);
    if rel
        .components()
        .any(|c| !matches!(c, Component::Normal(_) | Component::CurDir))
    {
        return Err(format!(
            "external buffer path {uri:?} must be relative and stay in the file's folder"
        ));
    }
    let path = base.join(rel);
    std::fs::read(&path).map_err(|e| format!("cannot read {}: {e}", path.display()))
}

fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let hex = |c: u8| (c as char).to_digit(16);
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%'
            && i + 2 < b.len()
            && let (Some(h), Some(l)) = (hex(b[i + 1]), hex(b[i + 2]))
        {
            out.push((h * 16 + l) as u8);
            i += 3;
            continue;
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[derive(Deserialize)]
struct MeshExtras {
    #[serde(rename = "targetNames")]
    target_names: Option<Vec<String>>,
}

/// Target names of a mesh: `extras.targetNames`, else `target_<i>`.
pub(crate) fn mesh_target_names(mesh: &gltf::Mesh<'_>, count: usize) -> Vec<String> {
    let names = mesh
        .extras()
        .as_ref()
        .and_then(|raw| serde_json::from_str::<MeshExtras>(raw.get()).ok())
        .and_then(|e| e.target_names)
        .filter(|n| n.len() == count);
    match names {
        Some(n) => n,
        None => (0..count).map(|i| format!("target_{i}")).collect(),
    }
}

/// Number of morph targets of a mesh; all its primitives must agree (glTF 2.0 §3.7.2.2).
pub(crate) fn mesh_target_count(mesh: &gltf::Mesh<'_>) -> Result<usize, ImportError> {
    let mut counts = mesh.primitives().map(|p| p.morph_targets().len());
    let first = counts.next().unwrap_or(0);
    if let Some(other) = counts.find(|&c| c != first) {
        return Err(ImportError::Mesh {
            mesh: mesh_label(mesh),
            problem: format!("primitives have different target counts ({first} and {other})"),
        });
    }
    Ok(first)
}

fn mesh_label(mesh: &gltf::Mesh<'_>) -> String {
    mesh.name()
        .map_or_else(|| format!("#{}", mesh.index()), str::to_string)
}

/// A mesh instance found in the scene: which node, its world matrix.
pub(crate) struct Instance<'a> {
    pub(crate) node: gltf::Node<'a>,
    pub(crate) mesh: gltf::Mesh<'a>,
    pub(crate) world: Mat4,
}

/// The mesh instances of the default scene (or first scene, or all roots), in traversal order.
pub(crate) fn scene_instances(doc: &gltf::Document) -> Result<Vec<Instance<'_>>, ImportError> {
    let roots: Vec<gltf::Node<'_>> = match doc.default_scene().or_else(|| doc.scenes().next()) {
        Some(scene) => scene.nodes().collect(),
        None => {
            let mut is_child = vec![false; doc.nodes().len()];
            for n in doc.nodes() {
                for c in n.children() {
                    is_child[c.index()] = true;
                }
            }
            doc.nodes().filter(|n| !is_child[n.index()]).collect()
        }
    };
    let mut visited = vec![false; doc.nodes().len()];
    let mut out = Vec::new();
    let mut stack: Vec<(gltf::Node<'_>, Mat4, usize)> = roots
        .into_iter()
        .rev()
        .map(|n| (n, Mat4::IDENTITY, 0))
        .collect();
    while let Some((node, parent, depth)) = stack.pop() {
        if depth > MAX_DEPTH {
            return Err(ImportError::Invalid(format!(
                "node hierarchy deeper than {MAX_DEPTH}"
            )));
        }
        if std::mem::replace(&mut visited[node.index()], true) {
            return Err(ImportError::Invalid(format!(
                "node {} is reached twice (cycle or shared child)",
                node.index()
            )));
        }
        let local = Mat4::from_cols_array_2d(&node.transform().matrix());
        let world = parent * local;
        if !world.is_finite() {
            return Err(ImportError::Invalid(format!(
                "node {} has a non-finite transform",
                node.index()
            )));
        }
        if let Some(mesh) = node.mesh() {
            out.push(Instance {
                node: node.clone(),
                mesh,
                world,
            });
        }
        let children: Vec<_> = node.children().collect();
        for c in children.into_iter().rev() {
            stack.push((c, world, depth + 1));
        }
    }
    Ok(out)
}

fn to_vec3(v: &[f32]) -> Vec<Vec3> {
    v.chunks_exact(3).map(Vec3::from_slice).collect()
}

fn read_vec3(
    source: &Source<'_>,
    acc: &gltf::Accessor<'_>,
    n: usize,
    what: &str,
) -> Result<Vec<Vec3>, ImportError> {
    if acc.dimensions() != gltf::accessor::Dimensions::Vec3 {
        return Err(ImportError::Accessor {
            index: acc.index(),
            problem: format!("{what} must be VEC3, not {:?}", acc.dimensions()),
        });
    }
    if acc.count() != n {
        return Err(ImportError::Accessor {
            index: acc.index(),
            problem: format!(
                "{what} has {} elements, the primitive has {n} vertices",
                acc.count()
            ),
        });
    }
    Ok(to_vec3(&source.read_f32(acc)?))
}

/// Triangle-list indices of a primitive, converting strips and fans.
fn triangle_indices(
    source: &Source<'_>,
    prim: &gltf::Primitive<'_>,
    n: usize,
) -> Result<Vec<u32>, ImportError> {
    let raw: Vec<u32> = match prim.indices() {
        Some(acc) => {
            let idx = source.read_indices(&acc)?;
            if let Some(&bad) = idx.iter().find(|&&i| i as usize >= n) {
                return Err(ImportError::Accessor {
                    index: acc.index(),
                    problem: format!("index {bad} out of range for {n} vertices"),
                });
            }
            idx
        }
        None => (0..n as u32).collect(),
    };
    Ok(match prim.mode() {
        Mode::Triangles => raw[..raw.len() / 3 * 3].to_vec(),
        Mode::TriangleStrip => (2..raw.len())
            .flat_map(|i| {
                if i % 2 == 0 {
                    [raw[i - 2], raw[i - 1], raw[i]]
                } else {
                    [raw[i - 1], raw[i - 2], raw[i]]
                }
            })
            .collect(),
        Mode::TriangleFan => (2..raw.len())
            .flat_map(|i| [raw[i - 1], raw[i], raw[0]])
            .collect(),
        // Points and lines still blend; they just have no triangles.
        _ => Vec::new(),
    })
}

/// Rig-wide target registry: name → id, first appearance first.
#[derive(Default)]
struct Targets {
    names: Vec<String>,
    defaults: Vec<f32>,
    index: HashMap<String, TargetId>,
}

impl Targets {
    fn id(&mut self, name: &str, default: f32) -> TargetId {
        if let Some(&id) = self.index.get(name) {
            return id;
        }
        let id = self.names.len() as TargetId;
        self.names.push(name.to_string());
        self.defaults.push(default);
        self.index.insert(name.to_string(), id);
        id
    }
}

fn build_rig(parsed: &Parsed<'_>, options: &ImportOptions) -> Result<Rig, ImportError> {
    let doc = &parsed.doc;
    let source = &parsed.source;
    let instances = scene_instances(doc)?;
    let mut targets = Targets::default();
    let mut primitives = Vec::new();
    // Rig-wide ids of each node's mesh targets, for animation channels.
    let mut node_targets: HashMap<usize, Vec<TargetId>> = HashMap::new();

    for inst in &instances {
        let mesh = &inst.mesh;
        let count = mesh_target_count(mesh)?;
        let names = mesh_target_names(mesh, count);
        let defaults = mesh.weights().filter(|w| w.len() == count);
        let ids: Vec<TargetId> = names
            .iter()
            .enumerate()
            .map(|(i, n)| targets.id(n, defaults.map_or(0.0, |d| d[i])))
            .collect();
        node_targets.insert(inst.node.index(), ids.clone());

        let linear = Mat3::from_mat4(inst.world);
        let normal_m = if linear.determinant().abs() > f32::MIN_POSITIVE {
            linear.inverse().transpose()
        } else {
            Mat3::IDENTITY
        };
        let flip = linear.determinant() < 0.0;

        for prim in mesh.primitives() {
            let label = format!("{}/{}", mesh_label(mesh), prim.index());
            let pos_acc = prim
                .get(&Semantic::Positions)
                .ok_or_else(|| ImportError::Mesh {
                    mesh: label.clone(),
                    problem: "primitive has no POSITION".into(),
                })?;
            let n = pos_acc.count();
            let positions = read_vec3(source, &pos_acc, n, "POSITION")?;
            let file_normals = match prim.get(&Semantic::Normals) {
                Some(a) => Some(read_vec3(source, &a, n, "NORMAL")?),
                None => None,
            };
            let file_tangents = match prim.get(&Semantic::Tangents) {
                Some(a) if a.dimensions() == gltf::accessor::Dimensions::Vec4 && a.count() == n => {
                    let t = source.read_f32(&a)?;
                    Some(t.chunks_exact(4).map(Vec4::from_slice).collect::<Vec<_>>())
                }
                Some(a) => {
                    return Err(ImportError::Accessor {
                        index: a.index(),
                        problem: "TANGENT must be VEC4 with one element per vertex".into(),
                    });
                }
                None => None,
            };
            let mut indices = triangle_indices(source, &prim, n)?;
            if flip {
                for tri in indices.chunks_exact_mut(3) {
                    tri.swap(1, 2);
                }
            }

            // Rig space.
            let positions: Vec<Vec3> = positions
                .iter()
                .map(|&p| inst.world.transform_point3(p))
                .collect();
            let (normals, normal_scale) = match &file_normals {
                Some(ns) => {
                    let mut out = Vec::with_capacity(n);
                    let mut scale = Vec::with_capacity(n);
                    for &nv in ns {
                        let t = normal_m * nv;
                        let s = t.length();
                        let s = if s > 0.0 { s } else { 1.0 };
                        out.push(t / s);
                        scale.push(s);
                    }
                    (out, scale)
                }
                None => (vertex_normals(&positions, &indices), vec![1.0; n]),
            };
            let (tangents, tangent_scale) = match &file_tangents {
                Some(ts) => {
                    let mut out = Vec::with_capacity(n);
                    let mut scale = Vec::with_capacity(n);
                    for &t in ts {
                        let x = linear * t.truncate();
                        let s = x.length();
                        let s = if s > 0.0 { s } else { 1.0 };
                        out.push((x / s).extend(t.w));
                        scale.push(s);
                    }
                    (Some(out), scale)
                }
                None => (None, Vec::new()),
            };

            let mut sparse = Vec::new();
            for (k, target) in prim.morph_targets().enumerate() {
                let dp = match target.positions() {
                    Some(a) => read_vec3(source, &a, n, "POSITION target")?
                        .into_iter()
                        .map(|d| linear * d)
                        .collect(),
                    None => vec![Vec3::ZERO; n],
                };
                let dn = match target.normals() {
                    Some(a) => Some(
                        read_vec3(source, &a, n, "NORMAL target")?
                            .into_iter()
                            .zip(&normal_scale)
                            .map(|(d, s)| normal_m * d / *s)
                            .collect::<Vec<_>>(),
                    ),
                    None => None,
                };
                let dt = match (target.tangents(), &tangents) {
                    (Some(a), Some(_)) => Some(
                        read_vec3(source, &a, n, "TANGENT target")?
                            .into_iter()
                            .zip(&tangent_scale)
                            .map(|(d, s)| linear * d / *s)
                            .collect::<Vec<_>>(),
                    ),
                    _ => None,
                };
                let st: SparseTarget = sparsify(
                    ids[k],
                    &dp,
                    dn.as_deref(),
                    dt.as_deref(),
                    options.delta_threshold,
                );
                if !st.vertices.is_empty() {
                    sparse.push(st);
                }
            }

            primitives.push(Primitive {
                name: label,
                positions,
                normals,
                normals_from_file: file_normals.is_some(),
                tangents,
                indices,
                targets: sparse,
            });
        }
    }

    let n_targets = targets.names.len();
    let clips = bake_animations(
        doc,
        source,
        &node_targets,
        n_targets,
        &targets.defaults,
        options.fps,
    )?;
    let lod = Lod::by_delta_energy(&primitives, n_targets);
    let rig = Rig {
        name: options.name.clone().unwrap_or_else(|| "rig".into()),
        targets: targets.names,
        default_weights: targets.defaults,
        primitives: std::sync::Arc::new(primitives),
        clips,
        lod,
    };
    rig.validate()?;
    Ok(rig)
}

/// One `weights` channel resolved to rig-wide targets.
pub(crate) struct WeightTrack {
    pub(crate) track: KeyTrack,
    /// Rig-wide target of each of the track's `width` scalars (`None`: not in the rig).
    pub(crate) targets: Vec<Option<TargetId>>,
}

/// Reads the `weights` channels of one animation. `node_targets(node)` maps a node to the
/// rig-wide ids of its mesh's targets (`None` entries are targets the rig does not have).
pub(crate) fn weight_tracks(
    source: &Source<'_>,
    anim: &gltf::Animation<'_>,
    node_targets: &dyn Fn(&gltf::Node<'_>) -> Option<Vec<Option<TargetId>>>,
) -> Result<Vec<WeightTrack>, ImportError> {
    let label = anim
        .name()
        .map_or_else(|| format!("#{}", anim.index()), str::to_string);
    let bad = |problem: String| ImportError::Animation {
        animation: label.clone(),
        problem,
    };
    let mut tracks = Vec::new();
    for channel in anim.channels() {
        if channel.target().property() != Property::MorphTargetWeights {
            continue;
        }
        let node = channel.target().node();
        let Some(ids) = node_targets(&node) else {
            tracing::warn!(animation = %label, node = node.index(), "weights channel targets a node outside the rig; ignored");
            continue;
        };
        let sampler = channel.sampler();
        let input = sampler.input();
        if input.dimensions() != gltf::accessor::Dimensions::Scalar {
            return Err(bad("sampler input must be SCALAR times".into()));
        }
        let times = source.read_f32(&input)?;
        let values = source.read_f32(&sampler.output())?;
        let interpolation = match sampler.interpolation() {
            GltfInterpolation::Step => Interpolation::Step,
            GltfInterpolation::Linear => Interpolation::Linear,
            GltfInterpolation::CubicSpline => Interpolation::CubicSpline,
        };
        let track = KeyTrack {
            times,
            values,
            width: ids.len(),
            interpolation,
        };
        track.check().map_err(&bad)?;
        tracks.push(WeightTrack {
            track,
            targets: ids,
        });
    }
    Ok(tracks)
}

/// Bakes weight tracks into a `targets × frames` table at `fps`.
///
/// Frame `f` samples `t = f / fps` on the glTF timeline; the clip has
/// `floor(last_key_time × fps) + 1` frames. Targets no track drives hold `defaults`.
pub(crate) fn bake(
    name: &str,
    tracks: &[WeightTrack],
    n_targets: usize,
    defaults: &[f32],
    fps: f32,
) -> Result<Clip, ImportError> {
    let last = tracks
        .iter()
        .map(|t| t.track.last_time())
        .fold(0.0f32, f32::max);
    let frames_f = (last.max(0.0) * fps + 1e-3).floor();
    if frames_f.is_nan() || frames_f >= MAX_FRAMES as f32 {
        return Err(ImportError::Animation {
            animation: name.to_string(),
            problem: format!("lasts {last} s: more than {MAX_FRAMES} frames at {fps} fps"),
        });
    }
    let frames = frames_f as usize + 1;
    let mut weights = vec![0.0; n_targets * frames];
    for (t, row) in weights.chunks_exact_mut(frames.max(1)).enumerate() {
        row.fill(defaults.get(t).copied().unwrap_or(0.0));
    }
    let mut tmp = Vec::new();
    for wt in tracks {
        tmp.resize(wt.track.width, 0.0);
        for f in 0..frames {
            sample_track(&wt.track, f as f32 / fps, &mut tmp);
            for (i, id) in wt.targets.iter().enumerate() {
                if let Some(id) = id {
                    weights[*id as usize * frames + f] = tmp[i];
                }
            }
        }
    }
    Ok(Clip::new(name, fps, n_targets, frames, weights)?)
}

/// Makes `name` unique among `taken` by appending `_2`, `_3`, ...
pub(crate) fn unique_name(name: String, taken: &[String]) -> String {
    if !taken.contains(&name) {
        return name;
    }
    (2..)
        .map(|i| format!("{name}_{i}"))
        .find(|n| !taken.contains(n))
        .unwrap_or(name)
}

fn bake_animations(
    doc: &gltf::Document,
    source: &Source<'_>,
    node_targets: &HashMap<usize, Vec<TargetId>>,
    n_targets: usize,
    defaults: &[f32],
    fps: f32,
) -> Result<Vec<Clip>, ImportError> {
    let lookup = |node: &gltf::Node<'_>| {
        node_targets
            .get(&node.index())
            .map(|ids| ids.iter().map(|&i| Some(i)).collect())
    };
    let mut clips: Vec<Clip> = Vec::new();
    for anim in doc.animations() {
        let tracks = weight_tracks(source, &anim, &lookup)?;
        if tracks.is_empty() {
            continue;
        }
        let name = anim
            .name()
            .filter(|n| !n.is_empty())
            .map_or_else(|| format!("anim{}", anim.index()), str::to_string);
        let taken: Vec<String> = clips.iter().map(|c| c.name.clone()).collect();
        let name = unique_name(name, &taken);
        clips.push(bake(&name, &tracks, n_targets, defaults, fps)?);
    }
    Ok(clips)
}
