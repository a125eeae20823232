//! crowdmorph-import: readers that turn files into validated rigs and clips.
//!
//! | module | what it is |
//! |---|---|
//! | [`gltf`] | `.gltf` and `.glb` rigs: primitives, morph targets, weight animations baked into clips |
//! | `accessor` | accessors checked against the bytes present before they allocate |
//! | `channels` | weight channels: one per target name, unless nodes sharing a name behave differently |
//! | `scene` | what the scene instances and its weight channels hold, read once and charged |
//! | `meshopt` | `EXT_meshopt_compression` buffer views |
//! | [`extensions`] | the extension policy: which are read, ignored, or refused by name |
//! | [`image`] | texture images: headers sniffed and charged before decoding, downscale, mips |
//! | `uri` | files a `.gltf` names beside itself: percent-decoded, kept inside its folder |
//! | `material` | materials, textures, samplers and the images they reach ([`crowdmorph_core::rig::Appearance`]) |
//! | [`clips`] | CSV, JSON and glTF clips mapped onto an existing rig; joint-map columns become joint tables |
//! | `skin` | skins, meshes under animated nodes, node animation baked into joint tables |
//! | [`vrm`] | a VRM avatar's expressions (VRM 1.0 `VRMC_vrm`, VRM 0.x `VRM`) as the rig's `vrm` mapping |
//! | [`mapped`] | a CSV clip whose columns are a mapping's sources, rewritten onto its targets |
//!
//! - [`gltf`]: `.gltf` (embedded or external buffers) and `.glb` rigs, with every animation that
//!   drives morph weights or moves a skin's joints (or a mesh's node) baked into a clip; skins
//!   and node hierarchies are read by `skin`;
//! - [`clips`]: clip sources on their own — CSV (ARKit face-capture style) and JSON tables, and
//!   the animations of another glTF file — mapped onto an existing rig by target name.
//!
//! Everything here treats its input as hostile: sizes are checked against the bytes actually
//! present before anything is allocated, and every problem is a typed [`ImportError`] that names
//! what is wrong. Nothing here panics on bad input.

mod accessor;
mod channels;
pub mod clips;
pub mod extensions;
pub mod gltf;
pub mod image;
pub mod mapped;
mod material;
mod meshopt;
mod scene;
mod skin;
mod uri;
pub mod vrm;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use crowdmorph_core::budget::{Budget, BudgetError};
use crowdmorph_core::rig::{ClipError, DEFAULT_DELTA_THRESHOLD, Rig, RigError};

pub use self::clips::{clip_from_csv, clip_from_json, clips_from_gltf};
pub use self::material::decode_stored_images;

/// Most names an error message quotes (the live-weights path names one; a clip source's list
/// names a few, so that a file with several misspellings is fixed in one round).
pub const LISTED_NAMES: usize = 16;

/// `names` as an error message lists them: the first [`LISTED_NAMES`], quoted and cut to
/// [`crowdmorph_core::rig::QUOTED_NAME_CHARS`] characters each, then how many more there are.
pub fn listed(names: &[String]) -> String {
    let mut out = names
        .iter()
        .take(LISTED_NAMES)
        .map(|n| crowdmorph_core::rig::quoted_name(n))
        .collect::<Vec<_>>()
        .join(", ");
    if names.len() > LISTED_NAMES {
        out.push_str(&format!(" and {} more", names.len() - LISTED_NAMES));
    }
    out
}

/// Default of [`ImportOptions::max_texture_size`]: what every desktop GPU samples and a
/// 4K avatar atlas needs.
pub const DEFAULT_MAX_TEXTURE_SIZE: u32 = 4096;

/// Options of an import.
#[derive(Clone, Debug)]
pub struct ImportOptions {
    /// Vertices whose deltas are all at most this (per component, rig units) are not stored.
    pub delta_threshold: f32,
    /// Rate at which keyframed animations are baked into weight tables.
    pub fps: f32,
    /// Directory that relative buffer URIs resolve against; `None` accepts only self-contained
    /// files (GLB, data URIs), as the server does.
    pub base_dir: Option<PathBuf>,
    /// Rig name; defaults to the file stem.
    pub name: Option<String>,
    /// Most bytes one import may hold at once (decoded arrays, baked clip tables, the rig it
    /// builds), when no [`ImportOptions::budget`] is given. Bounds what a small file that
    /// declares huge counts (a "glTF bomb") can make us allocate.
    pub max_decoded_bytes: usize,
    /// The budget every allocation of the import is charged to (the server's per-upload
    /// budget, drawing from its memory pool); `None` makes one of `max_decoded_bytes`.
    pub budget: Option<Arc<Budget>>,
    /// Largest side of a kept texture (`--max-texture-size`): a larger image is halved until
    /// it fits, and the import's notes say so.
    pub max_texture_size: u32,
}

impl ImportOptions {
    /// The budget allocations are charged to.
    pub fn budget(&self) -> Arc<Budget> {
        self.budget.clone().unwrap_or_else(|| {
            Arc::new(Budget::new(
                self.max_decoded_bytes as u64,
                "--max-upload-memory",
                None,
            ))
        })
    }
}

impl Default for ImportOptions {
    fn default() -> Self {
        ImportOptions {
            delta_threshold: DEFAULT_DELTA_THRESHOLD,
            fps: crowdmorph_core::rig::DEFAULT_FPS,
            base_dir: None,
            name: None,
            max_decoded_bytes: 1 << 30,
            budget: None,
            max_texture_size: DEFAULT_MAX_TEXTURE_SIZE,
        }
    }
}

/// Why a file could not be imported.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// File path.
        path: String,
        /// Underlying error.
        source: std::io::Error,
    },
    /// The GLB container is malformed (wrong magic, truncated, bad chunk lengths).
    #[error("invalid GLB: {0}")]
    Glb(String),
    /// The glTF JSON is malformed.
    #[error("invalid glTF JSON: {0}")]
    Json(String),
    /// The glTF document breaks the specification (e.g. dangling references).
    #[error("invalid glTF: {0}")]
    Invalid(String),
    /// The file requires a glTF extension crowdmorph does not implement (for Draco, the
    /// message says how to convert the file).
    #[error("glTF requires unsupported extension {0:?}{hint}", hint = extensions::conversion_hint(.0))]
    UnsupportedExtension(String),
    /// A buffer is missing, refused or shorter than declared.
    #[error("buffer {index}: {problem}")]
    Buffer {
        /// Buffer index.
        index: usize,
        /// What is wrong.
        problem: String,
    },
    /// An accessor cannot be read (out of bounds, bad type, too large).
    #[error("accessor {index}: {problem}")]
    Accessor {
        /// Accessor index.
        index: usize,
        /// What is wrong.
        problem: String,
    },
    /// A mesh is unusable (e.g. primitives disagree on their target count).
    #[error("mesh {mesh:?}: {problem}")]
    Mesh {
        /// Mesh name or index.
        mesh: String,
        /// What is wrong.
        problem: String,
    },
    /// An animation is unusable.
    #[error("animation {animation:?}: {problem}")]
    Animation {
        /// Animation name or index.
        animation: String,
        /// What is wrong.
        problem: String,
    },
    /// An image is unusable (corrupt, truncated, of an unknown format, 0 × 0).
    #[error("image {index}: {problem}")]
    Image {
        /// Index in the file's `images`.
        index: usize,
        /// What is wrong.
        problem: String,
    },
    /// The import would hold more memory than its budget allows (a "glTF bomb", or just a
    /// rig too big for the limits), or the server's memory pool is full.
    #[error(transparent)]
    Budget(#[from] BudgetError),
    /// A clip table is unusable (CSV/JSON shape, ragged rows, bad numbers).
    #[error("clip: {0}")]
    ClipSource(String),
    /// A clip source names targets the rig does not have. The message quotes at most
    /// [`LISTED_NAMES`] of them, each cut as [`crowdmorph_core::rig::quoted_name`] cuts it, and counts
    /// the rest: a header of a million unknown columns is not echoed back whole.
    #[error("unknown target(s) not in the rig: {}", listed(.0))]
    UnknownTargets(Vec<String>),
    /// The imported data breaks a rig invariant (NaN, no vertices, ...).
    #[error(transparent)]
    Rig(#[from] RigError),
    /// The baked clip breaks a clip invariant.
    #[error(transparent)]
    Clip(#[from] ClipError),
}

/// Reads a rig from a `.glb` or `.gltf` file; relative buffer URIs resolve next to the file.
pub fn load_path(path: &Path, options: &ImportOptions) -> Result<Rig, ImportError> {
    let bytes = std::fs::read(path).map_err(|source| ImportError::Io {
        path: path.display().to_string(),
        source,
    })?;
    let mut options = options.clone();
    if options.base_dir.is_none() {
        options.base_dir = Some(path.parent().map(Path::to_path_buf).unwrap_or_default());
    }
    if options.name.is_none() {
        options.name = path.file_stem().map(|s| s.to_string_lossy().into_owned());
    }
    gltf::rig_from_slice(&bytes, &options)
}
