//! Clip sources mapped onto an existing rig: CSV, JSON and glTF animations.
//!
//! Target names are matched exactly first, then loosely, so that face-capture exports work on
//! rigs that spell the same ARKit shape differently: case and underscores are ignored and a
//! trailing `Left`/`Right` equals `_L`/`_R` (`EyeBlinkLeft` ≡ `eyeBlink_L`). Names that match
//! nothing are an [`ImportError::UnknownTargets`] unless the caller asks to ignore them, in
//! which case they are returned in [`ClipImport::ignored`] — reported, never silently dropped.
//!
//! Which weight channels a curve writes depends on the source (see [`crowdmorph_core::rig`]): a CSV or
//! JSON column names a target, and writes every channel of that name (every primitive that
//! has the target moves, as ARKit and Live Link users expect). A glTF animation animates nodes:
//! when the file's scene has the rig's primitives (the same export: the same primitive names
//! and vertex counts in the same order), each node's curve writes that node's channels and the
//! rig's other nodes keep their default weights, as glTF viewers play it; an animation that
//! gives two nodes different curves for a target the rig drives with one channel is refused,
//! naming them. A glTF file with other meshes (an animation-only export) is matched by name.

use std::collections::HashMap;
use std::collections::hash_map::Entry;
use std::sync::Arc;

use serde::Deserialize;

use super::channels::{channel_writers, curves_agree};
use super::gltf::{UniqueNames, bake, parse};
use super::scene::{Instance, MeshNames, scene_instances, tracks_bytes, weight_tracks};
use super::{ImportError, ImportOptions};
use crowdmorph_core::budget::Budget;
use crowdmorph_core::rig::{
    Clip, DEFAULT_FPS, JointMap, JointTable, LIVE_LINK_COLUMNS, MAX_FRAMES, MAX_LIVE_WEIGHT, Rig,
    TargetId, TargetIndex, Trs, map_bytes, quoted_name, rest_rotations,
};

/// Options for reading a clip source.
#[derive(Clone, Debug)]
pub struct ClipOptions {
    /// Frame rate of CSV rows (JSON carries its own), and the baking rate of glTF animations.
    pub fps: f32,
    /// Accept sources that name targets the rig does not have, reporting them instead.
    pub ignore_unknown: bool,
    /// The budget every allocation is charged to (the server's per-upload budget); `None`
    /// makes one of [`ImportOptions::default`]'s size.
    pub budget: Option<Arc<Budget>>,
}

impl Default for ClipOptions {
    fn default() -> Self {
        ClipOptions {
            fps: DEFAULT_FPS,
            ignore_unknown: false,
            budget: None,
        }
    }
}

impl ClipOptions {
    fn import_options(&self) -> ImportOptions {
        ImportOptions {
            fps: self.fps,
            budget: self.budget.clone(),
            ..ImportOptions::default()
        }
    }

    fn budget(&self) -> Arc<Budget> {
        self.import_options().budget()
    }
}

/// A clip read from a source, with the source's target names that matched nothing.
#[derive(Clone, Debug, PartialEq)]
pub struct ClipImport {
    /// The clip, over all the rig's targets.
    pub clip: Clip,
    /// Source target names not in the rig (only when `ignore_unknown` was set). The clips of
    /// one glTF file share one list (it is the file's, not an animation's), so a file of many
    /// animations and many unknown names does not hold a copy per clip.
    pub ignored: Arc<[String]>,
}

/// Columns of face-capture CSVs that are metadata, not targets.
const METADATA_COLUMNS: &[&str] = &["timecode", "time", "timestamp", "frame", "blendshapecount"];

/// Canonical spelling for loose matching: lower case, no separators, `left`/`right` → `l`/`r`.
pub fn loose(name: &str) -> String {
    let mut s: String = name
        .chars()
        .filter(|c| c.is_alphanumeric())
        .flat_map(char::to_lowercase)
        .collect();
    for (long, short) in [("left", "l"), ("right", "r")] {
        if s.ends_with(long) {
            s.truncate(s.len() - long.len());
            s.push_str(short);
        }
    }
    s
}

/// The rig target name a source name refers to, if any: the same name, else the only one
/// that matches loosely.
pub fn match_name<'r>(rig: &'r Rig, name: &str) -> Option<&'r str> {
    if let Some(id) = rig.target_id(name) {
        return rig.targets.get(id as usize).map(String::as_str);
    }
    let want = loose(name);
    let mut hits = rig.target_names().into_iter().filter(|t| loose(t) == want);
    match (hits.next(), hits.next()) {
        (Some(t), None) => Some(t),
        _ => None,
    }
}

/// Every weight channel of the rig target a source name refers to (empty: none).
pub fn match_targets(rig: &Rig, name: &str) -> Vec<TargetId> {
    match_name(rig, name).map_or_else(Vec::new, |n| rig.target_ids(n))
}

/// A rig's targets by exact and by loose name, built once per clip source, so that each
/// source name costs two hash probes rather than a scan (and a loose spelling) of every rig
/// channel: what [`match_targets`] answers, for many names. The server resolves live weights
/// by name with it, so that a weight is matched as a clip's column is.
pub struct Matcher<'r> {
    exact: TargetIndex<'r>,
    /// Loose spelling → the one rig name with it (`None` when several names share it).
    loose: HashMap<String, Option<&'r str>>,
}

impl<'r> Matcher<'r> {
    /// Bytes a matcher of `rig` holds at most: the exact index, and per name a loose spelling
    /// (at most the name's text) in a map allocated once for every name.
    pub fn bytes(rig: &Rig) -> u64 {
        let n = rig.targets.len();
        let text: u64 = rig.targets.iter().map(|t| t.len() as u64).sum();
        TargetIndex::bytes_for(n) + text + map_bytes(n, 24 + 16)
    }

    /// The matcher of `rig`; the caller has charged [`Matcher::bytes`].
    pub fn new(rig: &'r Rig) -> Matcher<'r> {
        let exact = rig.target_index();
        // Sized once for every name at most, so it never grows (what `bytes` counts).
        let mut loose_names: HashMap<String, Option<&'r str>> =
            HashMap::with_capacity(rig.targets.len());
        for name in exact.names() {
            loose_names
                .entry(loose(name))
                .and_modify(|m| *m = None)
                .or_insert(Some(name));
        }
        Matcher {
            exact,
            loose: loose_names,
        }
    }

    /// Every weight channel of the rig target `name` refers to: the same name, else the only
    /// one that matches loosely (empty: none).
    pub fn ids(&self, name: &str) -> &[TargetId] {
        let exact = self.exact.ids(name);
        if !exact.is_empty() {
            return exact;
        }
        match self.loose.get(&loose(name)) {
            Some(Some(n)) => self.exact.ids(n),
            _ => &[],
        }
    }
}

/// What a source's columns write: per column the weight channels, the columns that turn
/// joints instead (by the rig's [`JointMap`]), and the names that matched neither.
struct Columns {
    ids: Vec<Vec<TargetId>>,
    unknown: Vec<String>,
    /// (column, channel of `map`) of each column that turns a joint.
    joints: Vec<(usize, usize)>,
    map: Option<JointMap>,
}

/// Maps source column names to the weight channels they write, collecting the unknown ones;
/// on a rig with a skeleton, names its joint map has (Live Link's `HeadYaw`, ... by default)
/// turn joints. The rig's names are indexed once per source (charged to `budget` while they
/// are).
fn map_names(
    rig: &Rig,
    names: &[String],
    options: &ClipOptions,
    budget: &Budget,
) -> Result<Columns, ImportError> {
    for n in names {
        checked_name(n)
            .map_err(|why| ImportError::ClipSource(format!("column {}: {why}", quoted_name(n))))?;
    }
    let bytes = Matcher::bytes(rig);
    budget.charge(bytes, || format!("the target names of rig {:?}", rig.name))?;
    let matcher = Matcher::new(rig);
    let map = rig.skeleton.as_ref().map(|s| s.joint_map().into_owned());
    let mapped = map_with(&matcher, map.as_ref(), names, options, budget);
    drop(matcher);
    budget.release(bytes);
    let (ids, unknown, joints) = mapped?;
    let columns = Columns {
        ids,
        unknown,
        joints,
        map,
    };
    columns.each_once(rig, names, budget)?;
    Ok(columns)
}

impl Columns {
    /// Refuses two columns that write the same thing: the same target (two spellings that
    /// match one name, `eyeBlink_L` and `EyeBlinkLeft`, or one name twice) or the same joint
    /// channel (`HeadYaw` and `head_yaw`). One of them would otherwise be dropped silently;
    /// live weights and joint maps refuse the same. Unknown columns write nothing and are
    /// reported, not checked. The index this builds is charged to `budget` while it lives.
    fn each_once(&self, rig: &Rig, names: &[String], budget: &Budget) -> Result<(), ImportError> {
        let writers = self.ids.iter().filter(|i| !i.is_empty()).count() + self.joints.len();
        let bytes = map_bytes(writers, 16);
        budget.charge(bytes, || {
            format!("the index of {writers} columns that write the rig")
        })?;
        // What a column writes, as one key: its target's first channel, or past every channel
        // its joint channel.
        let mut seen: HashMap<u64, usize> = HashMap::with_capacity(writers);
        let n = rig.targets.len() as u64;
        let keyed = self
            .ids
            .iter()
            .enumerate()
            .filter_map(|(c, ids)| ids.first().map(|&t| (c, u64::from(t))))
            .chain(self.joints.iter().map(|&(c, ch)| (c, n + ch as u64)));
        let mut twice = None;
        for (c, key) in keyed {
            if let Some(&first) = seen.get(&key) {
                twice = Some((first, c, key));
                break;
            }
            seen.insert(key, c);
        }
        drop(seen);
        budget.release(bytes);
        let Some((a, b, key)) = twice else {
            return Ok(());
        };
        // By name: `names` leaves out metadata columns, so its positions are not the file's.
        let (a, b) = (a.min(b), a.max(b));
        let what = match key.checked_sub(n) {
            None => format!(
                "target {}",
                quoted_name(rig.targets.get(key as usize).map_or("?", String::as_str))
            ),
            Some(ch) => format!(
                "joint channel {}",
                quoted_name(
                    self.map
                        .as_ref()
                        .and_then(|m| m.channels.get(ch as usize))
                        .map_or("?", |c| c.column.as_str())
                )
            ),
        };
        Err(ImportError::ClipSource(format!(
            "columns {} and {} both write {what}: each may appear once (names match exactly or \
             in any loose spelling)",
            quoted_name(&names[a]),
            quoted_name(&names[b]),
        )))
    }
}

/// Why `name` cannot be a column or weight name, if it cannot: a control character (a NUL, a
/// newline, ...) would vanish in the loose spelling and match a name it does not spell.
pub fn checked_name(name: &str) -> Result<(), String> {
    match name.chars().find(|c| c.is_control()) {
        Some(c) => Err(format!(
            "the name has the control character {c:?}; names are matched by their letters and \
             digits, so one with control characters is refused rather than matched loosely"
        )),
        None => Ok(()),
    }
}

/// Whether `name` is one of Live Link Face's head and eye angle columns.
pub fn is_live_link_angle(name: &str) -> bool {
    let l = loose(name);
    LIVE_LINK_COLUMNS.iter().any(|(c, _, _)| loose(c) == l)
}

/// A clip's joint table from its joint columns (`Columns::joints`) and rows: each turned
/// node's local transform per frame ([`JointMap::local`]). Its size is charged first. A value
/// past ±[`MAX_LIVE_WEIGHT`] is refused, naming its column (of `names`) and its row (as
/// `row_label` names row `r`), as the same angle sent as a live weight is.
fn joint_table(
    rig: &Rig,
    map: &JointMap,
    joints: &[(usize, usize)],
    rows: &[Vec<f32>],
    names: &[String],
    row_label: &dyn Fn(usize) -> String,
    budget: &Budget,
) -> Result<Option<JointTable>, ImportError> {
    let Some(sk) = &rig.skeleton else {
        return Ok(None);
    };
    if joints.is_empty() {
        return Ok(None);
    }
    // Checked before anything is charged or built: an angle of 1e30 radians turns the head
    // by an arbitrary amount (f32 cannot tell its multiples of 2π apart).
    for (r, row) in rows.iter().enumerate() {
        for &(c, _) in joints {
            let v = row.get(c).copied().unwrap_or(0.0);
            if v.is_nan() || v.abs() > MAX_LIVE_WEIGHT {
                return Err(ImportError::ClipSource(format!(
                    "{}, column {}: {v} is past ±{MAX_LIVE_WEIGHT}, the most a joint angle \
                     column may hold (as a live weight)",
                    row_label(r),
                    quoted_name(names.get(c).map_or("?", String::as_str))
                )));
            }
        }
    }
    let channels: Vec<usize> = joints.iter().map(|j| j.1).collect();
    let nodes = map.nodes(&channels);
    let floats = rows.len() * nodes.len() * Trs::FLOATS;
    budget.charge(floats as u64 * 4, || {
        format!(
            "joint table of {} nodes × {} frames",
            nodes.len(),
            rows.len()
        )
    })?;
    let rest = rest_rotations(sk);
    let mut values = Vec::with_capacity(floats);
    let mut row_values = vec![0f32; joints.len()];
    for row in rows {
        for (v, &(c, _)) in row_values.iter_mut().zip(joints) {
            *v = row.get(c).copied().unwrap_or(0.0);
        }
        for &n in &nodes {
            let trs = map.local(sk, &rest, n, &channels, &row_values);
            values.extend_from_slice(&trs.floats());
        }
    }
    Ok(Some(JointTable {
        nodes,
        frames: rows.len() as u32,
        values,
    }))
}

/// [`map_names`] with the rig's names already indexed. The id lists (a vector per column)
/// and the unknown names are sized by the source, so they are charged to `budget` first; they
/// are held until the import ends, so the charge is not given back before.
#[allow(clippy::type_complexity)]
fn map_with(
    matcher: &Matcher<'_>,
    map: Option<&JointMap>,
    names: &[String],
    options: &ClipOptions,
    budget: &Budget,
) -> Result<(Vec<Vec<TargetId>>, Vec<String>, Vec<(usize, usize)>), ImportError> {
    let vec_bytes = size_of::<Vec<TargetId>>() as u64;
    let bytes: u64 = names
        .iter()
        .map(|n| match matcher.ids(n) {
            [] => 2 * vec_bytes + n.len() as u64,
            ids => vec_bytes + 4 * ids.len() as u64,
        })
        .sum();
    budget.charge(bytes, || {
        format!("the channel lists of {} source targets", names.len())
    })?;
    let mut ids = Vec::with_capacity(names.len());
    let mut unknown = Vec::new();
    let mut joints = Vec::new();
    // Live Link's angle columns that turn no joint of this rig: reported, not an error (every
    // Live Link recording has them, and a rig without those joints cannot show them).
    let mut angles = Vec::new();
    for (c, n) in names.iter().enumerate() {
        let id = matcher.ids(n);
        if id.is_empty() {
            let channel = map.and_then(|m| {
                let l = loose(n);
                m.channels.iter().position(|ch| loose(&ch.column) == l)
            });
            match channel {
                Some(ch) => joints.push((c, ch)),
                None if is_live_link_angle(n) => angles.push(n.clone()),
                None => unknown.push(n.clone()),
            }
        }
        ids.push(id.to_vec());
    }
    if !unknown.is_empty() && !options.ignore_unknown {
        return Err(ImportError::UnknownTargets(unknown));
    }
    unknown.extend(angles);
    Ok((ids, unknown, joints))
}

/// Builds a clip over all rig channels from frame-major source rows; column `c` writes every
/// channel in `ids[c]`. The table covers every channel whatever the source names, so its size
/// is charged before it is allocated: a one-column CSV of 65,535 rows on a 4,096-target rig
/// asks for a gigabyte.
fn clip_from_rows(
    rig: &Rig,
    name: &str,
    fps: f32,
    ids: &[Vec<TargetId>],
    rows: &[Vec<f32>],
    budget: &Budget,
) -> Result<Clip, ImportError> {
    let n = rig.targets.len();
    let frames = rows.len();
    if frames == 0 {
        return Err(ImportError::ClipSource("no frames".into()));
    }
    if frames > MAX_FRAMES {
        return Err(ImportError::ClipSource(format!(
            "{frames} frames (at most {MAX_FRAMES})"
        )));
    }
    budget.charge((n * frames * 4) as u64, || {
        format!("clip table {name:?} ({n} targets × {frames} frames)")
    })?;
    let mut weights = vec![0.0; n * frames];
    for (t, row) in weights.chunks_exact_mut(frames).enumerate() {
        row.fill(rig.default_weights[t]);
    }
    for (f, row) in rows.iter().enumerate() {
        for (c, &w) in row.iter().enumerate() {
            for &id in ids.get(c).into_iter().flatten() {
                if let Some(x) = weights.get_mut(id as usize * frames + f) {
                    *x = w;
                }
            }
        }
    }
    Ok(Clip::new(name, fps, n, frames, weights)?)
}

fn parse_weight(text: &str, row: usize, column: &str) -> Result<f32, ImportError> {
    let v: f32 = text.trim().parse().map_err(|_| {
        ImportError::ClipSource(format!(
            "row {row}, column {column:?}: {text:?} is not a number"
        ))
    })?;
    if !v.is_finite() {
        return Err(ImportError::ClipSource(format!(
            "row {row}, column {column:?}: {text:?} is not finite"
        )));
    }
    Ok(v)
}

/// Reads a CSV clip: a header row of target names, then one row of weights per frame. Metadata
/// columns such as Live Link Face's `Timecode` and `BlendShapeCount` are skipped.
pub fn clip_from_csv(
    rig: &Rig,
    name: &str,
    bytes: &[u8],
    options: &ClipOptions,
) -> Result<ClipImport, ImportError> {
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(true)
        .flexible(true)
        .trim(csv::Trim::All)
        .from_reader(bytes);
    let header = reader
        .headers()
        .map_err(|e| ImportError::ClipSource(format!("CSV header: {e}")))?
        .clone();
    // The header, its kept columns and their names are copies sized by the source.
    let budget = options.budget();
    budget.charge(
        2 * header.as_byte_record().as_slice().len() as u64 + 56 * header.len() as u64,
        || format!("the CSV header ({} columns)", header.len()),
    )?;
    let mut keep = Vec::with_capacity(header.len());
    let mut names = Vec::with_capacity(header.len());
    for (i, h) in header.iter().enumerate() {
        if !METADATA_COLUMNS.contains(&loose(h).as_str()) {
            keep.push(i);
            names.push(h.to_string());
        }
    }
    if names.is_empty() {
        return Err(ImportError::ClipSource(
            "CSV header names no targets".into(),
        ));
    }
    let columns = map_names(rig, &names, options, &budget)?;
    let ignored = columns.unknown.clone().into();
    // A parsed row: its vector header and weights.
    let row_bytes = 24 + 4 * keep.len() as u64;
    let mut rows = Vec::new();
    for (r, record) in reader.records().enumerate() {
        let row_no = r + 2; // 1-based, after the header.
        let record =
            record.map_err(|e| ImportError::ClipSource(format!("CSV row {row_no}: {e}")))?;
        if record.len() != header.len() {
            return Err(ImportError::ClipSource(format!(
                "CSV row {row_no} has {} fields, the header has {}",
                record.len(),
                header.len()
            )));
        }
        if rows.len() >= MAX_FRAMES {
            return Err(ImportError::ClipSource(format!(
                "more than {MAX_FRAMES} rows"
            )));
        }
        budget.charge(row_bytes, || format!("CSV row {row_no}"))?;
        let mut row = Vec::with_capacity(keep.len());
        for (&c, n) in keep.iter().zip(&names) {
            row.push(parse_weight(&record[c], row_no, n)?);
        }
        rows.push(row);
    }
    let mut clip = clip_from_rows(rig, name, options.fps, &columns.ids, &rows, &budget)?;
    if let Some(map) = &columns.map {
        // Rows counted from 1 with the header, as the other CSV errors count them.
        let row_label = |r: usize| format!("row {}", r + 2);
        clip.joints = joint_table(
            rig,
            map,
            &columns.joints,
            &rows,
            &names,
            &row_label,
            &budget,
        )?
        .map(Arc::new);
    }
    budget.release(rows.len() as u64 * row_bytes);
    Ok(ClipImport { clip, ignored })
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonClip {
    fps: Option<f32>,
    targets: Vec<String>,
    frames: Vec<Vec<f32>>,
}

/// Reads a JSON clip: `{"fps":30,"targets":[names],"frames":[[weights]...]}`.
pub fn clip_from_json(
    rig: &Rig,
    name: &str,
    bytes: &[u8],
    options: &ClipOptions,
) -> Result<ClipImport, ImportError> {
    // Parsed, a JSON table holds at most 4 bytes per weight (each takes at least two
    // characters with its separator) and a 24-byte vector per row (at least three).
    let budget = options.budget();
    let parsed = bytes.len() as u64 * 8;
    budget.charge(parsed, || "the JSON clip".into())?;
    let src: JsonClip =
        serde_json::from_slice(bytes).map_err(|e| ImportError::ClipSource(format!("JSON: {e}")))?;
    let columns = map_names(rig, &src.targets, options, &budget)?;
    let ignored = columns.unknown.clone().into();
    if let Some((f, row)) = src
        .frames
        .iter()
        .enumerate()
        .find(|(_, r)| r.len() != src.targets.len())
    {
        return Err(ImportError::ClipSource(format!(
            "frame {f} has {} weights, there are {} targets",
            row.len(),
            src.targets.len()
        )));
    }
    let fps = src.fps.unwrap_or(options.fps);
    let mut clip = clip_from_rows(rig, name, fps, &columns.ids, &src.frames, &budget)?;
    if let Some(map) = &columns.map {
        let row_label = |f: usize| format!("frame {f}");
        clip.joints = joint_table(
            rig,
            map,
            &columns.joints,
            &src.frames,
            &src.targets,
            &row_label,
            &budget,
        )?
        .map(Arc::new);
    }
    drop(src);
    budget.release(parsed);
    Ok(ClipImport { clip, ignored })
}

/// The rig primitive each primitive of the file's scene is, when the scene has exactly the
/// rig's primitives (same names and vertex counts, same order): the file is the rig's own
/// export, and its nodes can be matched one to one.
fn same_scene(rig: &Rig, instances: &[Instance<'_>]) -> bool {
    let mut rig_prims = rig.primitives.iter();
    for inst in instances {
        let label = inst
            .mesh
            .name()
            .map_or_else(|| format!("#{}", inst.mesh.index()), str::to_string);
        for prim in inst.mesh.primitives() {
            let Some(p) = rig_prims.next() else {
                return false;
            };
            let n = prim
                .get(&gltf::mesh::Semantic::Positions)
                .map_or(0, |a| a.count());
            if p.name != format!("{label}/{}", prim.index()) || p.positions.len() != n {
                return false;
            }
        }
    }
    rig_prims.next().is_none()
}

/// The channels each target of each node of the file's scene writes, node by node: the
/// channels of that name that move the node's own primitives in the rig (the `o`-th of them
/// for the `o`-th target of that name in the mesh). A target that moves none of them writes
/// nothing, which changes nothing.
fn node_channels(
    rig: &Rig,
    instances: &[Instance<'_>],
    names: &MeshNames,
) -> HashMap<usize, Vec<Vec<TargetId>>> {
    let mut out = HashMap::new();
    let mut first_prim = 0;
    for inst in instances {
        let names = names.of(&inst.mesh);
        let n_prims = inst.mesh.primitives().len();
        let prims = rig
            .primitives
            .get(first_prim..first_prim + n_prims)
            .unwrap_or(&[]);
        first_prim += n_prims;
        // The channels that move this node, by name, in channel order.
        let mut by_name: HashMap<&str, Vec<TargetId>> = HashMap::new();
        for p in prims {
            for t in &p.targets {
                if let Some(name) = rig.targets.get(t.target as usize) {
                    let v = by_name.entry(name.as_str()).or_default();
                    if !v.contains(&t.target) {
                        v.push(t.target);
                    }
                }
            }
        }
        for v in by_name.values_mut() {
            v.sort_unstable();
        }
        let mut seen: HashMap<&str, usize> = HashMap::new();
        let ids = names
            .iter()
            .map(|n| {
                let o = seen.entry(n.as_str()).or_default();
                let channels = by_name.get(n.as_str()).map_or(&[][..], Vec::as_slice);
                let ids = match channels.get(*o) {
                    Some(&c) if channels.len() > 1 => vec![c],
                    _ => channels.to_vec(),
                };
                *o += 1;
                ids
            })
            .collect();
        out.insert(inst.node.index(), ids);
    }
    out
}

/// Reads every morph-weight animation of a glTF/GLB file as clips of `rig`. When the file is
/// the rig's own export, each node's curves write that node's channels and the rig's other
/// nodes keep their defaults; otherwise the file's target names are matched to the rig's and
/// write every channel of the name (see the module documentation). Clips are named after the
/// animations.
pub fn clips_from_gltf(
    rig: &Rig,
    bytes: &[u8],
    options: &ClipOptions,
) -> Result<Vec<ClipImport>, ImportError> {
    let import = options.import_options();
    let parsed = parse(bytes, &import)?;
    let instances = scene_instances(&parsed.doc)?;
    let names = MeshNames::read(&parsed.doc, &instances, parsed.source.budget())?;
    let matcher_bytes = Matcher::bytes(rig);
    parsed.source.budget().charge(matcher_bytes, || {
        format!("the target names of rig {:?}", rig.name)
    })?;
    let matcher = Matcher::new(rig);
    let budget = parsed.source.budget();
    let mut ignored = Vec::new();
    let mut ignored_set = std::collections::HashSet::new();
    // Each mesh's names are matched once, however many nodes instance it; a node refers to
    // its mesh's lists (a copy per node would make a file of many instances of a mesh with
    // many targets a multiplier).
    let mut by_mesh: HashMap<usize, Vec<Vec<TargetId>>> = HashMap::new();
    let mut mesh_of: HashMap<usize, usize> = HashMap::with_capacity(instances.len());
    budget.charge(
        map_bytes(instances.len(), 16) + map_bytes(instances.len(), 32),
        || format!("the meshes of {} scene nodes", instances.len()),
    )?;
    for inst in &instances {
        if let Entry::Vacant(e) = by_mesh.entry(inst.mesh.index()) {
            let (ids, unknown, _) =
                map_with(&matcher, None, names.of(&inst.mesh), options, budget)?;
            for u in unknown {
                if !ignored_set.contains(u.as_str()) {
                    // Held twice (the set and the list) for the rest of the import.
                    budget.charge(2 * (u.len() as u64 + 24), || {
                        format!("the unknown target name {u:?}")
                    })?;
                    ignored_set.insert(u.clone());
                    ignored.push(u);
                }
            }
            e.insert(ids);
        }
        mesh_of.insert(inst.node.index(), inst.mesh.index());
    }
    drop(ignored_set);
    let ignored: Arc<[String]> = ignored.into();
    drop(matcher);
    budget.release(matcher_bytes);
    // The rig's own export writes each node's channels; another file writes by name.
    let per_node = same_scene(rig, &instances).then(|| node_channels(rig, &instances, &names));
    drop(names);
    let lists = |node: usize| -> Option<&Vec<Vec<TargetId>>> {
        match &per_node {
            Some(by_node) => by_node.get(&node),
            None => mesh_of.get(&node).and_then(|m| by_mesh.get(m)),
        }
    };
    let width = |node: &gltf::Node<'_>| lists(node.index()).map(Vec::len);
    let channels = |node: usize, k: usize| -> &[TargetId] {
        lists(node)
            .and_then(|ids| ids.get(k))
            .map_or(&[], Vec::as_slice)
    };
    // Pairs writing each channel, counted once for every animation's check.
    let writers = per_node.as_ref().map_or_else(Vec::new, |by_node| {
        channel_writers(by_node, rig.targets.len())
    });
    let mut out: Vec<ClipImport> = Vec::new();
    let mut taken = UniqueNames::new(budget);
    for anim in parsed.doc.animations() {
        let tracks = weight_tracks(&parsed.source, &anim, &width)?;
        if tracks.is_empty() {
            continue;
        }
        let name = anim
            .name()
            .filter(|n| !n.is_empty())
            .map_or_else(|| format!("anim{}", anim.index()), str::to_string);
        if let Some(by_node) = &per_node {
            curves_agree(rig, &tracks, by_node, &writers).map_err(|problem| {
                ImportError::ClipSource(format!("animation {name:?}: {problem}"))
            })?;
        }
        let name = taken.take(name)?;
        let clip = bake(
            &name,
            &tracks,
            channels,
            rig.targets.len(),
            &rig.default_weights,
            options.fps,
            budget,
            0.0,
        )?;
        budget.release(tracks_bytes(&tracks));
        out.push(ClipImport {
            clip,
            ignored: ignored.clone(),
        });
    }
    if out.is_empty() {
        return Err(ImportError::ClipSource(
            "the glTF file has no morph-weight animation".into(),
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::{Matcher, loose, match_targets};

    #[test]
    fn the_matcher_maps_names_as_one_lookup_each_does() {
        let rig = crowdmorph_core::embedded::default_rig();
        let matcher = Matcher::new(&rig);
        let mut names: Vec<String> = rig.targets.clone();
        // Loose spellings, a name no rig target has, and a loose clash made below.
        names.extend(
            ["EyeBlinkLeft", "JAW_OPEN", "mouthSmileRight", "noSuchShape"].map(String::from),
        );
        for n in &names {
            assert_eq!(matcher.ids(n), match_targets(&rig, n), "{n}");
        }
        assert!(!matcher.ids("EyeBlinkLeft").is_empty());
        assert!(matcher.ids("noSuchShape").is_empty());
        // Two rig names with one loose spelling: only exact names match them.
        let mut clash = rig.clone();
        clash.targets[0] = "eye_blink_l".into();
        clash.targets[1] = "EyeBlink_L".into();
        let matcher = Matcher::new(&clash);
        for n in ["eyeblinkl", "eye_blink_l", "EyeBlink_L", "eyeBlinkLeft"] {
            assert_eq!(matcher.ids(n), match_targets(&clash, n), "{n}");
        }
        assert!(matcher.ids("eyeblinkl").is_empty());
    }

    #[test]
    fn loose_names_match_arkit_spellings() {
        assert_eq!(loose("EyeBlinkLeft"), loose("eyeBlink_L"));
        assert_eq!(loose("mouthSmile_R"), loose("MouthSmileRight"));
        assert_eq!(loose("JawOpen"), loose("jawOpen"));
        assert_ne!(loose("browInnerUp_L"), loose("BrowInnerUp"));
    }
}
