//! glTF 2.0 rigs: `.gltf` (embedded or external buffers) and `.glb`.
//!
//! A rig is the set of primitives of the default scene (or the first scene, or every root node
//! when there is no scene) in rig space: node transforms at rest are applied, deltas are
//! transformed by the node's linear part and normals by its inverse transpose. Targets are
//! named by `mesh.extras.targetNames`, else `target_<i>`, and merged rig-wide by name. Every
//! animation with `weights` channels becomes a clip baked at a fixed rate.

use std::borrow::Cow;
use std::collections::HashMap;
use std::sync::Arc;

use base64::Engine as _;
use glam::{Mat3, Vec3};
use gltf::animation::Property;
use gltf::mesh::{Mode, Semantic};

use super::accessor::{CompressedView, Source};
use super::channels::{ChannelPlan, plan_channels};
use super::material::Pending;
use super::scene::{
    AnimationTracks, MeshNames, WeightTrack, json_nodes, mesh_label, mesh_target_count,
    scene_instances, tracks_bytes,
};
use super::uri::resolve_relative;
use super::{ImportError, ImportOptions};
use super::{extensions, meshopt, skin};
use crowdmorph_core::budget::Budget;
use crowdmorph_core::rig::{
    Clip, Lod, MAX_FRAMES, MAX_TARGETS, MAX_VERTICES, PrimShape, Primitive, Rig, RigError,
    RigShape, SparseTarget, TargetId, VertexLook, sample_track, sparse_len, sparsify,
    vertex_normals,
};

/// glTF extensions a file may require that we read correctly.
const SUPPORTED_REQUIRED: &[&str] = &[
    "KHR_mesh_quantization",
    "EXT_meshopt_compression",
    "KHR_meshopt_compression",
];

/// A parsed document with its buffers loaded.
pub(crate) struct Parsed<'a> {
    /// The document's JSON, for what the `gltf` crate does not read safely (materials).
    pub(crate) json: &'a [u8],
    pub(crate) doc: gltf::Document,
    pub(crate) source: Source<'a>,
}

/// Reads a rig from the bytes of a `.glb` or `.gltf` file. Its size is checked from the
/// file's headers and reserved in the import's budget before anything is decoded.
pub fn rig_from_slice(bytes: &[u8], options: &ImportOptions) -> Result<Rig, ImportError> {
    let import = GltfImport::open(bytes, options)?;
    let budget = import.parsed.source.budget().clone();
    let need = budget.used() + import.import_bytes();
    budget.reserve(need, || "importing the rig".to_string())?;
    import.build(options)
}

/// A glTF file parsed and sized, not yet decoded: what the server checks against its budgets
/// before it commits to the work.
pub struct GltfImport<'a> {
    parsed: Parsed<'a>,
    /// Which (node, target) pairs share a weight channel.
    plan: ChannelPlan,
    /// Every animation's weight tracks, decoded once to make the plan and kept (charged to
    /// the budget) until [`GltfImport::build`] bakes them.
    animations: Vec<AnimationTracks>,
    shape: RigShape,
    /// Materials and images, fetched and sized, decoded by the build.
    appearance: Option<Pending>,
    /// Largest transient decode of one primitive (dense target deltas, raw indices), plus the
    /// compressed views the geometry reads, decoded during the build and kept until its end,
    /// beyond the rig's own arrays.
    transient: u64,
}

impl<'a> GltfImport<'a> {
    /// Parses the document (its parsed size charged to the budget first) and reads the rig's
    /// shape from the headers: vertex, index, target and keyframe counts. Limits that the
    /// counts alone break (targets, vertices, frames) are refused here, before any decoding.
    pub fn open(bytes: &'a [u8], options: &ImportOptions) -> Result<GltfImport<'a>, ImportError> {
        let parsed = parse(bytes, options)?;
        let (mut shape, transient, plan, animations) = document_shape(&parsed, options)?;
        let appearance = Pending::read(
            parsed.json,
            &parsed.source,
            &parsed.doc,
            options.base_dir.as_deref(),
            options.max_texture_size,
        )?;
        // What the rig keeps of its images, and the largest one's decode on top of the
        // geometry's transient peak (images are decoded after the geometry is built).
        let transient = transient + appearance.as_ref().map_or(0, Pending::peak_decode);
        shape.appearance = appearance.as_ref().map_or(0, Pending::kept_bytes);
        Ok(GltfImport {
            parsed,
            plan,
            animations,
            shape,
            appearance,
            transient,
        })
    }

    /// The rig's counts from the headers (every target counted as moving every vertex).
    pub fn shape(&self) -> &RigShape {
        &self.shape
    }

    /// Most bytes the import holds at once beyond what the budget already holds (which
    /// includes the decoded keyframes): the rig's arrays plus the largest transient decode.
    pub fn import_bytes(&self) -> u64 {
        self.shape.cost(false).rig + self.transient
    }

    /// Decodes and builds the rig, charging every allocation to the budget.
    pub fn build(self, options: &ImportOptions) -> Result<Rig, ImportError> {
        build_rig(
            &self.parsed,
            self.plan,
            self.animations,
            self.appearance,
            options,
        )
    }
}

/// Every extension a `.glb` or `.gltf` file uses or requires, and how the importer treats
/// it (read, ignored, unsupported): what `crowdmorph inspect` lists. Reads the JSON only.
pub fn extension_report(bytes: &[u8]) -> Result<Vec<extensions::ExtensionUse>, ImportError> {
    let json = if bytes.starts_with(b"glTF") {
        split_glb(bytes)?.0
    } else {
        bytes
    };
    let root: serde_json::Value =
        serde_json::from_slice(json).map_err(|e| ImportError::Json(e.to_string()))?;
    Ok(extensions::report(&root))
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
    let budget = options.budget();
    budget.charge(document_cost(json), || {
        format!("the glTF document ({} bytes of JSON)", json.len())
    })?;
    let mut root: gltf::json::Root =
        gltf::json::deserialize::from_slice(json).map_err(|e| ImportError::Json(e.to_string()))?;
    drop_unknown_channels(&mut root);
    validate(&root, json, &budget)?;
    let doc = gltf::Document::from_json_without_validation(root);
    let mut buffers = Vec::new();
    for buffer in doc.buffers() {
        let index = buffer.index();
        let bad = |problem: String| ImportError::Buffer { index, problem };
        // Fallback buffers stand in for compressed views and are never read; so are buffers
        // past the first without a URI (only buffer 0 may be a GLB's BIN chunk), which are
        // placeholders of the same kind. A view that reads one without decompressing finds
        // no bytes there, an error naming it.
        let placeholder = meshopt::is_fallback(&buffer)
            || (index > 0 && matches!(buffer.source(), gltf::buffer::Source::Bin));
        if placeholder {
            buffers.push(Cow::Borrowed(&[][..]));
            continue;
        }
        let data: Cow<'a, [u8]> = match buffer.source() {
            gltf::buffer::Source::Bin => Cow::Borrowed(
                bin.ok_or_else(|| bad("refers to the GLB BIN chunk, which is missing".into()))?,
            ),
            gltf::buffer::Source::Uri(uri) => {
                Cow::Owned(load_uri(uri, options, &budget).map_err(|e| match e {
                    UriError::Budget(b) => ImportError::Budget(b),
                    UriError::Bad(m) => bad(m),
                })?)
            }
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
    // Compressed views: headers checked now, bytes decoded when an accessor first reads them.
    let mut compressed = HashMap::new();
    for view in doc.views() {
        let Some(ext) = meshopt::view_extension(&view) else {
            continue;
        };
        let (name, ext) = ext?;
        let data = buffers.get(ext.buffer).ok_or_else(|| {
            ImportError::Invalid(format!(
                "bufferViews[{}].extensions.{name} refers to buffer {} of {}",
                view.index(),
                ext.buffer,
                buffers.len()
            ))
        })?;
        meshopt::check_view(view.index(), name, &ext, view.length(), data.len())?;
        compressed.insert(view.index(), CompressedView::new(name, ext, view.length()));
    }
    Ok(Parsed {
        json,
        doc,
        source: Source::new(buffers, compressed, budget),
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

/// Runs the `gltf` crate's reference validation, tolerating what we handle ourselves, and
/// refuses required extensions that could change the geometry (see [`super::extensions`]).
fn validate(root: &gltf::json::Root, json: &[u8], budget: &Budget) -> Result<(), ImportError> {
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
    // Required extensions we do not read are accepted only when they touch textures alone.
    // Rare: the document is then read again as plain JSON and walked once for all of them.
    let unknown: Vec<&str> = root
        .extensions_required
        .iter()
        .map(String::as_str)
        .filter(|ext| {
            !SUPPORTED_REQUIRED.contains(ext)
                && !gltf::json::extensions::ENABLED_EXTENSIONS.contains(ext)
        })
        .collect();
    if !unknown.is_empty() {
        let cost = document_cost(json);
        budget.charge(cost, || {
            format!(
                "the glTF document ({} bytes of JSON), to check its extensions",
                json.len()
            )
        })?;
        let value: serde_json::Value =
            serde_json::from_slice(json).map_err(|e| ImportError::Json(e.to_string()))?;
        let texture_only = extensions::texture_only(&value, &unknown);
        drop(value);
        budget.release(cost);
        for (ext, texture_only) in unknown.iter().zip(texture_only) {
            if !texture_only {
                return Err(ImportError::UnsupportedExtension(ext.to_string()));
            }
            tracing::info!(extension = %ext, "required extension is used only by textures; ignored");
        }
    }
    let mut errors = Vec::new();
    let outcome = std::panic::catch_unwind(|| {
        let mut report = |path: &dyn Fn() -> gltf::json::Path, error: Error| {
            let p = path().to_string();
            // Missing POSITION min/max is common in the wild and harmless here (we compute
            // bounds); extensions we support are allowed in extensionsRequired.
            // A texture whose image comes from an extension (KHR_texture_basisu, ...) has no
            // `source`; textures are never read here.
            let tolerated = (error == Error::Missing
                && (p.ends_with(".min")
                    || p.ends_with(".max")
                    || (p.starts_with("textures[") && p.ends_with(".source"))))
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

/// Why a buffer URI could not be loaded.
enum UriError {
    Budget(crowdmorph_core::budget::BudgetError),
    Bad(String),
}

impl From<String> for UriError {
    fn from(m: String) -> Self {
        UriError::Bad(m)
    }
}

/// Loads a buffer URI: a base64 data URI, or a relative file under `options.base_dir`; the
/// bytes are charged to `budget` before they are allocated.
fn load_uri(uri: &str, options: &ImportOptions, budget: &Budget) -> Result<Vec<u8>, UriError> {
    if let Some(rest) = uri.strip_prefix("data:") {
        let (meta, data) = rest
            .split_once(',')
            .ok_or_else(|| "malformed data URI".to_string())?;
        if !meta.ends_with(";base64") {
            return Err("data URI is not base64".to_string().into());
        }
        budget
            .charge(data.len() as u64 * 3 / 4 + 3, || "a data URI buffer".into())
            .map_err(UriError::Budget)?;
        return base64::engine::general_purpose::STANDARD
            .decode(data.trim())
            .map_err(|e| format!("bad base64 in data URI: {e}").into());
    }
    let Some(base) = &options.base_dir else {
        return Err(format!(
            "refers to external file {uri:?}; send a GLB or a glTF with embedded (data URI) buffers"
        )
        .into());
    };
    let path = resolve_relative(base, uri)?;
    let len = std::fs::metadata(&path)
        .map_err(|e| format!("cannot read {}: {e}", path.display()))?
        .len();
    budget
        .charge(len, || format!("buffer file {}", path.display()))
        .map_err(UriError::Budget)?;
    std::fs::read(&path).map_err(|e| format!("cannot read {}: {e}", path.display()).into())
}

/// Bytes the parsed glTF document may occupy: its strings (at most the text itself) plus one
/// typed node per structural character (the `gltf` crate's largest, a node or an accessor
/// with its options, is under 256 bytes). A few kilobytes of `[0,0,0,...]` cannot make the
/// parser allocate gigabytes unnoticed.
pub(crate) fn document_cost(json: &[u8]) -> u64 {
    json.len() as u64 + 256 * json_nodes(json)
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
    source.read_vec3s(acc)
}

/// Reads a VEC2 accessor of one element per vertex (texture coordinates; normalized integer
/// ones are decoded to floats, as glTF's `KHR_mesh_quantization` stores them).
fn read_vec2(
    source: &Source<'_>,
    acc: &gltf::Accessor<'_>,
    n: usize,
    what: &str,
) -> Result<Vec<glam::Vec2>, ImportError> {
    if acc.dimensions() != gltf::accessor::Dimensions::Vec2 || acc.count() != n {
        return Err(ImportError::Accessor {
            index: acc.index(),
            problem: format!(
                "{what} must be VEC2 with one element per vertex ({n}), not {} of {:?}",
                acc.count(),
                acc.dimensions()
            ),
        });
    }
    source.read_vec2s(acc)
}

/// A primitive's `COLOR_0`: VEC3 (alpha 1) or VEC4, float or normalized integers.
fn read_colors(
    source: &Source<'_>,
    acc: &gltf::Accessor<'_>,
    n: usize,
) -> Result<Vec<glam::Vec4>, ImportError> {
    use gltf::accessor::Dimensions;
    if acc.count() != n {
        return Err(ImportError::Accessor {
            index: acc.index(),
            problem: format!(
                "COLOR_0 must have one element per vertex ({n}), not {}",
                acc.count()
            ),
        });
    }
    match acc.dimensions() {
        Dimensions::Vec4 => source.read_vec4s(acc),
        Dimensions::Vec3 => Ok(source
            .read_vec3s(acc)?
            .into_iter()
            .map(|c| c.extend(1.0))
            .collect()),
        d => Err(ImportError::Accessor {
            index: acc.index(),
            problem: format!("COLOR_0 must be VEC3 or VEC4, not {d:?}"),
        }),
    }
}

/// Triangle-list indices a primitive will have: its index (or vertex) count as a list.
fn list_len(prim: &gltf::Primitive<'_>, vertices: usize) -> u64 {
    let raw = prim.indices().map_or(vertices, |a| a.count()) as u64;
    match prim.mode() {
        Mode::Triangles => raw / 3 * 3,
        Mode::TriangleStrip | Mode::TriangleFan => raw.saturating_sub(2) * 3,
        _ => 0,
    }
}

/// The shape of the rig a document describes, from its headers, the largest transient decode
/// of one primitive, the weight channels and the decoded keyframes. Counts that break a limit
/// on their own are refused first: too many target names, too many vertices, clips too long
/// by their declared key times. Then every animation's keyframes are decoded (charged, and
/// kept for baking) to tell which nodes share a channel ([`plan_channels`]), which gives the
/// clip tables' exact size; clips whose key times declare no `max` are measured on them.
fn document_shape(
    parsed: &Parsed<'_>,
    options: &ImportOptions,
) -> Result<(RigShape, u64, ChannelPlan, Vec<AnimationTracks>), ImportError> {
    let doc = &parsed.doc;
    let instances = scene_instances(doc)?;
    let names = MeshNames::read(doc, &instances, parsed.source.budget())?;
    // Distinct names seen so far: at most MAX_TARGETS + 1 entries before the refusal.
    let mut distinct: std::collections::HashSet<&str> = std::collections::HashSet::new();
    let mut primitives = Vec::new();
    let mut node_targets: HashMap<usize, usize> = HashMap::new();
    let mut transient = 0u64;
    let mut vertices = 0u64;
    // Which buffer views the geometry's accessors read: the compressed ones among them are
    // decoded during the build, so their decoded bytes join the estimate.
    let views = doc.views().len();
    parsed
        .source
        .budget()
        .charge(views as u64, || format!("a mark per buffer view ({views})"))?;
    let mut read_views = vec![false; views];
    for inst in &instances {
        let count = mesh_target_count(&inst.mesh)?;
        for name in names.of(&inst.mesh) {
            distinct.insert(name);
            if distinct.len() > MAX_TARGETS {
                return Err(RigError::TooLarge(format!(
                    "more than {MAX_TARGETS} rig-wide targets (the file names at least {})",
                    distinct.len()
                ))
                .into());
            }
        }
        node_targets.insert(inst.node.index(), count);
        for prim in inst.mesh.primitives() {
            let Some(pos) = prim.get(&Semantic::Positions) else {
                continue;
            };
            let mut check = |acc: gltf::Accessor<'_>| -> Result<(), ImportError> {
                for v in parsed.source.check_bounds(&acc)?.into_iter().flatten() {
                    if let Some(r) = read_views.get_mut(v) {
                        *r = true;
                    }
                }
                Ok(())
            };
            for (_, acc) in prim.attributes() {
                check(acc)?;
            }
            if let Some(acc) = prim.indices() {
                check(acc)?;
            }
            for t in prim.morph_targets() {
                for acc in [t.positions(), t.normals(), t.tangents()]
                    .into_iter()
                    .flatten()
                {
                    check(acc)?;
                }
            }
            let n = pos.count() as u64;
            vertices += n;
            if vertices > MAX_VERTICES as u64 {
                return Err(RigError::TooLarge(format!(
                    "more than {MAX_VERTICES} vertices (the file declares at least {vertices})"
                ))
                .into());
            }
            let tangents = prim.get(&Semantic::Tangents).is_some();
            let has = |s: Semantic| u64::from(prim.get(&s).is_some());
            let look = 8 * has(Semantic::TexCoords(0))
                + 8 * has(Semantic::TexCoords(1))
                + 16 * has(Semantic::Colors(0));
            let (mut k, mut kn, mut kt) = (0u64, 0u64, 0u64);
            for t in prim.morph_targets() {
                k += 1;
                kn += u64::from(t.normals().is_some());
                kt += u64::from(t.tangents().is_some() && tangents);
            }
            let indices = list_len(&prim, n as usize);
            let raw_indices = prim.indices().map_or(0, |a| a.count() as u64);
            // One target decoded dense (positions, normals, tangents) with its scale factors,
            // or the raw indices beside the list, whichever is larger.
            transient = transient
                .max(n * (12 + 12 + 12 + 8))
                .max(raw_indices * 4 + indices * 4);
            primitives.push(PrimShape::upper_bound(
                n, indices, tangents, look, k, kn, kt,
            ));
        }
    }
    // Clip lengths from the declared key times first, so that a clip too long on its
    // headers alone is refused before any keyframe is decoded; animations with a channel
    // that declares no `max` wait for the decoded keyframes below.
    let anim_label = |anim: &gltf::Animation<'_>| {
        anim.name()
            .map_or_else(|| format!("#{}", anim.index()), str::to_string)
    };
    let too_long = |anim: &gltf::Animation<'_>, last: f32| ImportError::Animation {
        animation: anim_label(anim),
        problem: format!(
            "lasts {last} s: more than {MAX_FRAMES} frames at {} fps",
            options.fps
        ),
    };
    let mut clip_frames = 0u64;
    let mut undeclared = Vec::new();
    for anim in doc.animations() {
        let mut last = None::<f32>;
        let mut complete = true;
        for channel in anim.channels() {
            if channel.target().property() != Property::MorphTargetWeights
                || !node_targets.contains_key(&channel.target().node().index())
            {
                continue;
            }
            let Some(t) = declared_last(&channel.sampler().input()) else {
                complete = false;
                continue;
            };
            if !t.is_finite() {
                return Err(ImportError::Animation {
                    animation: anim_label(&anim),
                    problem: "key times are non-finite".into(),
                });
            }
            last = Some(last.map_or(t, |l: f32| l.max(t)));
        }
        if let Some(last) = last {
            baked_frames(last, options.fps).ok_or_else(|| too_long(&anim, last))?;
        }
        match (complete, last) {
            (false, _) => undeclared.push(anim.index()),
            (true, Some(last)) => {
                clip_frames += baked_frames(last, options.fps).unwrap_or(0) as u64;
            }
            (true, None) => {}
        }
    }
    // The keyframes are decoded once, here, to tell which nodes share a channel; they stay
    // charged (in the budget's use) until the build bakes them.
    let (plan, animations) = plan_channels(doc, &parsed.source, &instances, &names)?;
    for decoded in animations
        .iter()
        .filter(|d| undeclared.binary_search(&d.index).is_ok())
    {
        let Some(anim) = doc.animations().nth(decoded.index) else {
            continue;
        };
        // A channel's end is its declared `max`, else its last key (the keys are checked to
        // be finite and increasing).
        let last = decoded
            .tracks
            .iter()
            .map(|t| {
                doc.accessors()
                    .nth(t.times_accessor)
                    .and_then(|a| declared_last(&a))
                    .unwrap_or_else(|| t.track.last_time().max(0.0))
            })
            .fold(None::<f32>, |l, t| Some(l.map_or(t, |l| l.max(t))));
        if let Some(last) = last {
            let frames = baked_frames(last, options.fps).ok_or_else(|| too_long(&anim, last))?;
            clip_frames += frames as u64;
        }
    }
    // Compressed views the geometry reads, not decoded yet (the keyframes' were, above): they
    // stay decoded for the whole build.
    let decompress = parsed.source.pending_decode_bytes(
        read_views
            .iter()
            .enumerate()
            .filter_map(|(v, &read)| read.then_some(v)),
    );
    drop(read_views);
    parsed.source.budget().release(views as u64);
    let transient = transient + decompress;
    let n_targets = plan.len() as u64;
    Ok((
        RigShape {
            primitives,
            targets: n_targets,
            clip_cells: n_targets * clip_frames,
            mesh_levels: Vec::new(),
            pca_levels: Vec::new(),
            // The skin's arrays are charged as they are read (`import::skin`).
            skin: Default::default(),
            // Added by the caller from the materials (`material::Pending`).
            appearance: 0,
        },
        transient,
        plan,
        animations,
    ))
}

/// Frames of a clip baked at `fps` from a timeline whose last key is at `last` seconds;
/// `None` past [`MAX_FRAMES`].
fn baked_frames(last: f32, fps: f32) -> Option<usize> {
    let frames_f = (last.max(0.0) * fps + 1e-3).floor();
    (frames_f.is_finite() && frames_f < MAX_FRAMES as f32).then(|| frames_f as usize + 1)
}

/// Triangle-list indices of a primitive, converting strips and fans.
fn triangle_indices(
    source: &Source<'_>,
    prim: &gltf::Primitive<'_>,
    n: usize,
) -> Result<Vec<u32>, ImportError> {
    // The list is charged before it is built; the raw indices are released after.
    let list = list_len(prim, n);
    source.budget().charge(list * 4, || {
        format!("triangles of a primitive of {n} vertices")
    })?;
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
        None => {
            source
                .budget()
                .charge(n as u64 * 4, || "implicit indices".to_string())?;
            (0..n as u32).collect()
        }
    };
    let raw_len = raw.len() as u64 * 4;
    let list = match prim.mode() {
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
    };
    drop(raw);
    source.budget().release(raw_len);
    Ok(list)
}

fn build_rig(
    parsed: &Parsed<'_>,
    plan: ChannelPlan,
    animations: Vec<AnimationTracks>,
    appearance: Option<Pending>,
    options: &ImportOptions,
) -> Result<Rig, ImportError> {
    let doc = &parsed.doc;
    let source = &parsed.source;
    // The clips first: baking releases the keyframes the plan decoded before the geometry's
    // decodes need the memory.
    let n_targets = plan.len();
    let instances = scene_instances(doc)?;
    let skeleton = skin::plan(doc, source, &instances)?;
    let mut report = skin::SkinReport::default();
    let clips = bake_animations(
        doc,
        source,
        animations,
        &plan.node_channels,
        n_targets,
        &plan.defaults,
        options.fps,
        skeleton.as_ref(),
        &mut report,
    )?;
    let mut primitives = Vec::new();

    for inst in &instances {
        let mesh = &inst.mesh;
        let count = mesh_target_count(mesh)?;
        let ids = plan
            .node_channels
            .get(&inst.node.index())
            .filter(|ids| ids.len() == count)
            .ok_or_else(|| {
                ImportError::Invalid(format!(
                    "node {} has no weight channels planned",
                    inst.node.index()
                ))
            })?;

        let attach = skeleton
            .as_ref()
            .and_then(|p| p.attach.get(&inst.node.index()));
        // A skinned mesh ignores its node's transform (glTF 2.0 §3.7.3.3): its vertices go to
        // rig space by its skin's bind pose instead (`crates/core/src/rig/skin.rs`).
        let world = match attach {
            Some(skin::Attach::Skinned { world, .. }) => *world,
            _ => inst.world,
        };
        let linear = Mat3::from_mat4(world);
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
            let budget = source.budget();
            // Rig space, transformed in place: the decoded arrays become the rig's.
            let mut positions = read_vec3(source, &pos_acc, n, "POSITION")?;
            for p in &mut positions {
                *p = world.transform_point3(*p);
            }
            let file_normals = prim.get(&Semantic::Normals).is_some();
            // Per-vertex length of each transformed file normal (and tangent): their deltas
            // are divided by it so that normalized vectors plus deltas stay consistent.
            budget.charge(n as u64 * 8, || "normal and tangent scales".into())?;
            let (normals, normal_scale) = match prim.get(&Semantic::Normals) {
                Some(a) => {
                    let mut ns = read_vec3(source, &a, n, "NORMAL")?;
                    let mut scale = Vec::with_capacity(n);
                    for nv in &mut ns {
                        let t = normal_m * *nv;
                        let l = t.length();
                        let l = if l > 0.0 { l } else { 1.0 };
                        *nv = t / l;
                        scale.push(l);
                    }
                    (ns, scale)
                }
                None => (Vec::new(), vec![1.0; n]),
            };
            let (tangents, tangent_scale) = match prim.get(&Semantic::Tangents) {
                Some(a) if a.dimensions() == gltf::accessor::Dimensions::Vec4 && a.count() == n => {
                    let mut ts = source.read_vec4s(&a)?;
                    let mut scale = Vec::with_capacity(n);
                    for t in &mut ts {
                        let x = linear * t.truncate();
                        let l = x.length();
                        let l = if l > 0.0 { l } else { 1.0 };
                        *t = (x / l).extend(t.w);
                        scale.push(l);
                    }
                    (Some(ts), scale)
                }
                Some(a) => {
                    return Err(ImportError::Accessor {
                        index: a.index(),
                        problem: "TANGENT must be VEC4 with one element per vertex".into(),
                    });
                }
                None => (None, Vec::new()),
            };
            let mut indices = triangle_indices(source, &prim, n)?;
            if flip {
                for tri in indices.chunks_exact_mut(3) {
                    tri.swap(1, 2);
                }
            }
            let normals = if file_normals {
                normals
            } else {
                budget.charge(n as u64 * 24, || "computed normals".into())?;
                let computed = vertex_normals(&positions, &indices);
                budget.release(n as u64 * 12);
                computed
            };

            let mut sparse = Vec::new();
            for (k, target) in prim.morph_targets().enumerate() {
                // Dense deltas, decoded and transformed in place, then kept sparse: the dense
                // arrays are released once the sparse target is built.
                let mut dense = 0u64;
                let dp = match target.positions() {
                    Some(a) => {
                        let mut d = read_vec3(source, &a, n, "POSITION target")?;
                        for v in &mut d {
                            *v = linear * *v;
                        }
                        d
                    }
                    None => {
                        budget.charge(n as u64 * 12, || "an empty target".into())?;
                        vec![Vec3::ZERO; n]
                    }
                };
                dense += n as u64 * 12;
                let dn = match target.normals() {
                    Some(a) => {
                        let mut d = read_vec3(source, &a, n, "NORMAL target")?;
                        for (v, s) in d.iter_mut().zip(&normal_scale) {
                            *v = normal_m * *v / *s;
                        }
                        dense += n as u64 * 12;
                        Some(d)
                    }
                    None => None,
                };
                let dt = match (target.tangents(), &tangents) {
                    (Some(a), Some(_)) => {
                        let mut d = read_vec3(source, &a, n, "TANGENT target")?;
                        for (v, s) in d.iter_mut().zip(&tangent_scale) {
                            *v = linear * *v / *s;
                        }
                        dense += n as u64 * 12;
                        Some(d)
                    }
                    _ => None,
                };
                let m = sparse_len(&dp, dn.as_deref(), dt.as_deref(), options.delta_threshold);
                let per =
                    4 + 12 + if dn.is_some() { 12 } else { 0 } + if dt.is_some() { 12 } else { 0 };
                budget.charge(m as u64 * per, || format!("target {k} of {label}"))?;
                let st: SparseTarget = sparsify(
                    ids[k],
                    &dp,
                    dn.as_deref(),
                    dt.as_deref(),
                    options.delta_threshold,
                );
                drop((dp, dn, dt));
                budget.release(dense);
                if !st.vertices.is_empty() {
                    sparse.push(st);
                }
            }
            drop((normal_scale, tangent_scale));
            budget.release(n as u64 * 8);

            // glTF 2.0 §3.9.2: a primitive without a material, or a material without a
            // factor, has base colour white.
            let base_color = prim.material().pbr_metallic_roughness().base_color_factor();
            let skin = match attach {
                Some(a) => Some(skin::influences(source, &prim, a, n, &mut report)?),
                None => None,
            };
            let look = VertexLook {
                uv0: match prim.get(&Semantic::TexCoords(0)) {
                    Some(a) => Some(read_vec2(source, &a, n, "TEXCOORD_0")?),
                    None => None,
                },
                uv1: match prim.get(&Semantic::TexCoords(1)) {
                    Some(a) => Some(read_vec2(source, &a, n, "TEXCOORD_1")?),
                    None => None,
                },
                colors: match prim.get(&Semantic::Colors(0)) {
                    Some(a) => Some(read_colors(source, &a, n)?),
                    None => None,
                },
                material: appearance
                    .as_ref()
                    .and_then(|_| prim.material().index())
                    .map(|m| m as u32),
            };
            primitives.push(Primitive {
                name: label,
                positions,
                normals,
                normals_from_file: file_normals,
                tangents,
                indices,
                targets: sparse,
                base_color,
                skin,
                look,
            });
        }
    }

    // Images last: the geometry's transient decodes are released by now.
    let appearance = match appearance {
        Some(pending) => Some(Arc::new(pending.decode(source.budget())?)),
        None => None,
    };
    let mut notes = report.notes();
    notes.extend(appearance.iter().flat_map(|a| a.notes.iter().cloned()));
    // A target texture naming no target of the rig is kept (a later clip or a renamed export
    // may still mean it) but never drawn: said once, not refused.
    let names: std::collections::HashSet<&str> = plan.names.iter().map(String::as_str).collect();
    for t in appearance.iter().flat_map(|a| a.target_textures.iter()) {
        if !names.contains(t.target.as_str()) {
            notes.push(format!(
                "material {}: target texture for {} names no morph target of the rig; not drawn",
                t.material,
                crowdmorph_core::rig::quoted_name(&t.target)
            ));
        }
    }
    drop(names);
    let lod = Lod::by_delta_energy(&primitives, n_targets);
    let rig = Rig {
        name: options.name.clone().unwrap_or_else(|| "rig".into()),
        // The plan's names and defaults (charged when it was made) become the rig's.
        targets: plan.names,
        default_weights: plan.defaults,
        primitives: Arc::new(primitives),
        clips,
        lod,
        skeleton: skeleton.map(|p| {
            source.budget().release(p.charged);
            Arc::new(p.skeleton)
        }),
        import_notes: notes,
        appearance,
    };
    rig.validate()?;
    if report.largest_dropped_weight > 0.0 || report.channels_on_unused_nodes > 0 {
        tracing::info!(
            joint_channels = report.joint_channels,
            unused = report.channels_on_unused_nodes,
            dropped = report.largest_dropped_weight,
            "skin import"
        );
    }
    Ok(rig)
}

/// The last key time an accessor of key times declares (its `max`), if it declares one.
fn declared_last(times: &gltf::Accessor<'_>) -> Option<f32> {
    times
        .max()
        .and_then(|m| {
            m.as_array()
                .and_then(|a| a.first())
                .and_then(serde_json::Value::as_f64)
        })
        .map(|m| m as f32)
}

/// Bakes weight tracks into a `targets × frames` table at `fps`.
///
/// Frame `f` samples `t = f / fps` on the glTF timeline; the clip has
/// `floor(last_key_time × fps) + 1` frames. Targets no track drives hold `defaults`. Scalar `k`
/// of a track on node `n` writes the weight channels `channels(n, k)`. `other_last` is the last
/// key time of the animation's other channels (its joints), so both tables get equal frames.
#[allow(clippy::too_many_arguments)]
pub(crate) fn bake<'c>(
    name: &str,
    tracks: &[WeightTrack],
    channels: impl Fn(usize, usize) -> &'c [TargetId],
    n_targets: usize,
    defaults: &[f32],
    fps: f32,
    budget: &Budget,
    other_last: f32,
) -> Result<Clip, ImportError> {
    let last = tracks
        .iter()
        .map(|t| t.track.last_time())
        .fold(other_last, f32::max);
    let frames = baked_frames(last, fps).ok_or_else(|| ImportError::Animation {
        animation: name.to_string(),
        problem: format!("lasts {last} s: more than {MAX_FRAMES} frames at {fps} fps"),
    })?;
    budget.charge((n_targets * frames * 4) as u64, || {
        format!("clip table {name:?} ({n_targets} targets × {frames} frames at {fps} fps)")
    })?;
    let mut weights = vec![0.0; n_targets * frames];
    for (t, row) in weights.chunks_exact_mut(frames.max(1)).enumerate() {
        row.fill(defaults.get(t).copied().unwrap_or(0.0));
    }
    // Per track: one sample and one channel list per scalar (charged: a track may be wide).
    let widest = tracks.iter().map(|t| t.track.width).max().unwrap_or(0) as u64;
    let scratch = widest * (4 + 16);
    budget.charge(scratch, || format!("baking clip {name:?}"))?;
    let mut tmp = Vec::new();
    let mut ids: Vec<&[TargetId]> = Vec::new();
    for wt in tracks {
        tmp.resize(wt.track.width, 0.0);
        ids.clear();
        ids.extend((0..wt.track.width).map(|k| channels(wt.node, k)));
        for f in 0..frames {
            sample_track(&wt.track, f as f32 / fps, &mut tmp);
            for (i, ids) in ids.iter().enumerate() {
                for &id in *ids {
                    if let Some(w) = weights.get_mut(id as usize * frames + f) {
                        *w = tmp[i];
                    }
                }
            }
        }
    }
    drop((tmp, ids));
    budget.release(scratch);
    Ok(Clip::new(name, fps, n_targets, frames, weights)?)
}

/// Names made unique as they are taken: a name taken before gets the first free `_2`, `_3`...
/// suffix. Hash lookups and a next-suffix counter per name keep this linear in the names:
/// with a scan of the names taken so far for every candidate, a file of thousands of
/// animations with one name cost a cube of their number.
pub(crate) struct UniqueNames<'b> {
    /// Every name handed out.
    taken: std::collections::HashSet<String>,
    /// Per name asked for again: the next suffix to try.
    next: HashMap<String, u64>,
    /// Where the names are charged while they are held, and how much.
    budget: &'b Budget,
    charged: u64,
}

impl<'b> UniqueNames<'b> {
    /// An empty set whose names are charged to `budget` (given back when it is dropped).
    pub(crate) fn new(budget: &'b Budget) -> UniqueNames<'b> {
        UniqueNames {
            taken: std::collections::HashSet::new(),
            next: HashMap::new(),
            budget,
            charged: 0,
        }
    }

    /// `name`, or its first free suffixed form; the copies this keeps (in the set, and as a
    /// counter's key) are charged first.
    pub(crate) fn take(&mut self, name: String) -> Result<String, ImportError> {
        let bytes = 2 * (name.len() as u64 + 48) + 32;
        self.budget
            .charge(bytes, || format!("the animation name {name:?}"))?;
        self.charged += bytes;
        if !self.taken.contains(&name) {
            self.taken.insert(name.clone());
            return Ok(name);
        }
        let next = self.next.entry(name.clone()).or_insert(2);
        loop {
            let candidate = format!("{name}_{next}");
            *next += 1;
            if !self.taken.contains(&candidate) {
                self.taken.insert(candidate.clone());
                return Ok(candidate);
            }
        }
    }
}

impl Drop for UniqueNames<'_> {
    fn drop(&mut self) {
        self.budget.release(self.charged);
    }
}

/// Bakes the animations the plan decoded, one at a time, releasing each one's keyframes once
/// its table is made. With a skeleton, each animation's joint channels are baked beside its
/// weights (an animation with only joint channels is a clip too).
#[allow(clippy::too_many_arguments)]
fn bake_animations(
    doc: &gltf::Document,
    source: &Source<'_>,
    animations: Vec<AnimationTracks>,
    node_channels: &HashMap<usize, Vec<TargetId>>,
    n_targets: usize,
    defaults: &[f32],
    fps: f32,
    skeleton: Option<&skin::SkeletonPlan>,
    report: &mut skin::SkinReport,
) -> Result<Vec<Clip>, ImportError> {
    let channels = |node: usize, k: usize| -> &[TargetId] {
        node_channels
            .get(&node)
            .and_then(|ids| ids.get(k))
            .map_or(&[], std::slice::from_ref)
    };
    let mut weights: HashMap<usize, Vec<WeightTrack>> = animations
        .into_iter()
        .map(|a| (a.index, a.tracks))
        .collect();
    let mut clips: Vec<Clip> = Vec::new();
    let mut taken = UniqueNames::new(source.budget());
    for anim in doc.animations() {
        let tracks = weights.remove(&anim.index()).unwrap_or_default();
        let joints = match skeleton {
            Some(plan) => Some(skin::joint_tracks(source, &anim, plan, report)?),
            None => {
                // No mesh follows any node: such channels move nothing the rig has.
                report.channels_on_unused_nodes += anim
                    .channels()
                    .filter(|c| c.target().property() != Property::MorphTargetWeights)
                    .count();
                None
            }
        };
        if tracks.is_empty() && joints.as_ref().is_none_or(skin::JointTracks::is_empty) {
            continue;
        }
        let name = anim
            .name()
            .map(str::to_string)
            .filter(|n| !n.is_empty())
            .unwrap_or_else(|| format!("anim{}", anim.index()));
        let name = taken.take(name)?;
        let joint_last = joints.as_ref().map_or(0.0, skin::JointTracks::last_time);
        let mut clip = bake(
            &name,
            &tracks,
            channels,
            n_targets,
            defaults,
            fps,
            source.budget(),
            joint_last,
        )?;
        source.budget().release(tracks_bytes(&tracks));
        if let (Some(j), Some(plan)) = (joints, skeleton) {
            clip.joints = skin::bake_joints(
                &name,
                j,
                &plan.skeleton,
                clip.frames as usize,
                fps,
                source.budget(),
            )?
            .map(Arc::new);
        }
        clips.push(clip);
    }
    Ok(clips)
}
