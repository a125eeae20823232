//! The record layout's tests: every record type round trips with and without each optional
//! section, what the pre-section writer wrote (kinds 6–11, kept below as it was) still reads to
//! the same value, and bad sections are refused with a problem, never a panic.

use std::sync::Arc;

use super::*;
use crate::sections::{OPTIONAL, SECTION_HEADER};

// The writer of kinds 6–11 as it was before sections: its types, then its body.

/// Borrowed mirrors of the stored records: same fields in the same order, so the same bytes.
#[derive(Serialize)]
struct StoredRigRef<'a> {
    id: &'a str,
    rig: RigRecordRef<'a>,
}

/// Kind 9: kind 6 and what a rig with a skeleton adds (serde skips it inside the rig).
#[derive(Serialize)]
struct StoredSkinnedRef<'a> {
    id: &'a str,
    rig: RigRecordRef<'a>,
    skin: SkinRecordRef<'a>,
}

/// The skeleton, each primitive's influences, and the joint tables of the record's clips by
/// clip name (a compressed clip that does not decode is skipped alone, so not by position).
#[derive(Serialize)]
struct SkinRecordRef<'a> {
    skeleton: &'a Skeleton,
    influences: Vec<Option<&'a Influences>>,
    clip_joints: Vec<(&'a str, &'a JointTable)>,
    notes: &'a [String],
}

/// Kind 10: kind 9 and the rig's own joint map.
#[derive(Serialize)]
struct StoredSkinnedMapRef<'a> {
    id: &'a str,
    rig: RigRecordRef<'a>,
    skin: SkinRecordRef<'a>,
    map: &'a JointMap,
}

/// The borrowed mirror of [`RigRecordV6`] used for writing.
#[derive(Serialize)]
struct RigRecordRef<'a> {
    name: &'a str,
    targets: &'a [String],
    default_weights: &'a [f32],
    primitives: &'a [crowdmorph_core::rig::Primitive],
    clips: Vec<ClipRecordRef<'a>>,
    lod_json: String,
    /// Per primitive (kind 5 on): serde skips it inside [`crowdmorph_core::rig::Primitive`].
    base_colors: Vec<[f32; 4]>,
}

impl<'a> RigRecordRef<'a> {
    /// The record of `rig` holding `clips` (the rest of its clips are in clip files).
    fn new(rig: &'a Rig, clips: &'a [Clip], max_error: Option<f32>) -> Result<Self, StoreError> {
        // Exhaustive on purpose: a new Rig field must be added to the stored record.
        let Rig {
            name,
            targets,
            default_weights,
            primitives,
            clips: _,
            lod,
            // Kind 9's `SkinRecordRef`.
            skeleton: _,
            import_notes: _,
            // Section 10 only: no legacy kind stores it.
            appearance: _,
        } = rig;
        Ok(RigRecordRef {
            name,
            targets,
            default_weights,
            primitives: primitives.as_slice(),
            clips: clip_records(clips, rig, max_error)?,
            lod_json: lod_to_json(lod)?,
            base_colors: primitives.iter().map(|p| p.base_color).collect(),
        })
    }
}

/// Kind 7 (kind 3 with [`ClipRecord`]s). The LOD goes as JSON for the reason given at
/// [`RigRecord`].
#[derive(Serialize)]
struct StoredBuiltinRef<'a> {
    id: &'a str,
    clips: Vec<ClipRecordRef<'a>>,
    lod_json: String,
    geometry: u32,
}

/// Kind 8: clips added to a rig.
#[derive(Serialize)]
struct StoredClipsRef<'a> {
    id: &'a str,
    seq: u64,
    clips: Vec<ClipRecordRef<'a>>,
}

/// Kind 11: kind 8 and its clips' joint tables by clip name.
#[derive(Serialize)]
struct StoredClipsJointsRef<'a> {
    id: &'a str,
    seq: u64,
    clips: Vec<ClipRecordRef<'a>>,
    clip_joints: Vec<(&'a str, &'a JointTable)>,
}

/// The kind and payload the pre-section writer made of `record` (kinds 6–11).
fn legacy_payload(
    record: RecordRef<'_>,
    clip_error: Option<f32>,
) -> Result<(u32, Vec<u8>), StoreError> {
    let mut w = Vec::new();
    let kind = match record {
        RecordRef::Rig { id, rig, clips } => {
            let record = RigRecordRef::new(rig, clips, clip_error)?;
            if let Some(skeleton) = rig.skeleton.as_deref() {
                let skin = SkinRecordRef {
                    skeleton,
                    influences: rig.primitives.iter().map(|p| p.skin.as_ref()).collect(),
                    clip_joints: clips
                        .iter()
                        .filter_map(|c| c.joints.as_deref().map(|t| (c.name.as_str(), t)))
                        .collect(),
                    notes: &rig.import_notes,
                };
                if let Some(map) = &skeleton.map {
                    let r = StoredSkinnedMapRef {
                        id,
                        rig: record,
                        skin,
                        map,
                    };
                    codec::to_stored_writer(&r, &mut w)
                        .map_err(|e| StoreError::Encode(e.to_string()))?;
                    KIND_RIG_SKINNED_MAP_V10
                } else {
                    let r = StoredSkinnedRef {
                        id,
                        rig: record,
                        skin,
                    };
                    codec::to_stored_writer(&r, &mut w)
                        .map_err(|e| StoreError::Encode(e.to_string()))?;
                    KIND_RIG_SKINNED_V9
                }
            } else {
                let r = StoredRigRef { id, rig: record };
                codec::to_stored_writer(&r, &mut w)
                    .map_err(|e| StoreError::Encode(e.to_string()))?;
                KIND_RIG_V6
            }
        }
        RecordRef::Builtin { id, clips, rig } => {
            let r = StoredBuiltinRef {
                id,
                clips: clip_records(clips, rig, clip_error)?,
                lod_json: lod_to_json(&rig.lod)?,
                geometry: geometry_fingerprint(rig),
            };
            codec::to_stored_writer(&r, &mut w).map_err(|e| StoreError::Encode(e.to_string()))?;
            KIND_BUILTIN_V7
        }
        RecordRef::Clips {
            id,
            seq,
            clips,
            rig,
        } => {
            let clip_joints: Vec<(&str, &JointTable)> = clips
                .iter()
                .filter_map(|c| c.joints.as_deref().map(|t| (c.name.as_str(), t)))
                .collect();
            let clips = clip_records(clips, rig, clip_error)?;
            if clip_joints.is_empty() {
                codec::to_stored_writer(&StoredClipsRef { id, seq, clips }, &mut w)
                    .map_err(|e| StoreError::Encode(e.to_string()))?;
                KIND_CLIPS_V8
            } else {
                let r = StoredClipsJointsRef {
                    id,
                    seq,
                    clips,
                    clip_joints,
                };
                codec::to_stored_writer(&r, &mut w)
                    .map_err(|e| StoreError::Encode(e.to_string()))?;
                KIND_CLIPS_JOINTS_V11
            }
        }
    };
    Ok((kind, w))
}

/// A record file: header and payload.
fn file_bytes(kind: u32, payload: &[u8]) -> Vec<u8> {
    let mut out = MAGIC.to_vec();
    out.extend_from_slice(&kind.to_le_bytes());
    out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    out.extend_from_slice(&crc32fast::hash(payload).to_le_bytes());
    out.extend_from_slice(payload);
    out
}

/// The file this build writes of `record`.
fn encode(record: RecordRef<'_>, clip_error: Option<f32>) -> Vec<u8> {
    let mut payload = Vec::new();
    let kind = write_sections(&mut payload, record, clip_error).expect("encode");
    file_bytes(kind, &payload)
}

fn kind_of(file: &[u8]) -> u32 {
    u32::from_le_bytes([file[8], file[9], file[10], file[11]])
}

/// The sections of a well-formed payload, in order.
fn split(payload: &[u8]) -> Vec<(u32, Vec<u8>)> {
    let mut out = Vec::new();
    let mut at = 0;
    while at < payload.len() {
        let tag = u32::from_le_bytes(payload[at..at + 4].try_into().expect("4 bytes"));
        let len = u64::from_le_bytes(payload[at + 4..at + 12].try_into().expect("8 bytes"));
        let start = at + SECTION_HEADER;
        out.push((tag, payload[start..start + len as usize].to_vec()));
        at = start + len as usize;
    }
    out
}

fn join(sections: &[(u32, Vec<u8>)]) -> Vec<u8> {
    let mut out = Vec::new();
    for (tag, bytes) in sections {
        out.extend_from_slice(&tag.to_le_bytes());
        out.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
        out.extend_from_slice(bytes);
    }
    out
}

/// The file name a record of `id` (a clip file when `seq` is given) is read under.
fn name_of(id: &str, seq: Option<u64>) -> PathBuf {
    match seq {
        None => PathBuf::from(format!("{id}.{EXT}")),
        Some(seq) => PathBuf::from(format!("{id}@{seq:010}.{CLIPS_EXT}")),
    }
}

/// Reads `file` as if it were named `name`; the clips it left out must be none.
fn decode(name: &Path, file: &[u8]) -> Result<Record, StoreError> {
    let mut skipped = Vec::new();
    let r = Store::decode_file(name, file, &mut skipped);
    assert!(skipped.is_empty(), "{skipped:?}");
    r
}

/// The problem `file` is refused with.
fn problem(name: &Path, file: &[u8]) -> String {
    match Store::decode_file(name, file, &mut Vec::new()) {
        Err(StoreError::Corrupt { path, problem }) => {
            assert_eq!(path, name.display().to_string());
            problem
        }
        other => panic!("not refused as corrupt: {other:?}"),
    }
}

/// The skinned head, with its own joint map and import notes when asked.
fn skinned(map: bool, notes: bool) -> Rig {
    let mut rig = crowdmorph_core::synthetic::skinned_head();
    if notes {
        rig.import_notes = vec!["a note".into(), "another note".into()];
    }
    if map {
        let mut skeleton = rig.skeleton.as_deref().expect("a skeleton").clone();
        let mut m = JointMap::defaults(&skeleton);
        assert!(!m.channels.is_empty());
        for c in &mut m.channels {
            c.scale = 0.5;
        }
        skeleton.map = Some(m);
        rig.skeleton = Some(Arc::new(skeleton));
    }
    assert!(rig.clips.iter().all(|c| c.joints.is_some()));
    rig.validate().expect("valid");
    rig
}

fn rig_record(id: &str, rig: &Rig) -> Record {
    Record::Rig(Box::new(StoredRig {
        id: id.into(),
        rig: rig.clone(),
    }))
}

fn builtin_record(id: &str, rig: &Rig, clips: &[Clip]) -> Record {
    Record::Builtin(StoredBuiltin {
        id: id.into(),
        clips: clips.to_vec(),
        lod: Some((rig.lod.clone(), geometry_fingerprint(rig))),
    })
}

fn clips_record(id: &str, seq: u64, clips: &[Clip]) -> Record {
    Record::Clips(StoredClips {
        id: id.into(),
        seq,
        clips: clips.to_vec(),
    })
}

/// The embedded head with every part of an appearance: both texture coordinate sets and
/// colours on one primitive, a material with a transformed texture on each, an image.
fn dressed() -> Rig {
    use crowdmorph_core::rig::{
        AlphaMode, Filter, ImageData, ImageMime, Material, Sampler, TexRef, Texture, UvTransform,
        Wrap,
    };
    let mut rig = crowdmorph_core::embedded::default_rig();
    let mut prims = rig.primitives.as_ref().clone();
    for (i, p) in prims.iter_mut().enumerate() {
        let n = p.positions.len();
        p.look.uv0 = Some(
            (0..n)
                .map(|v| glam::Vec2::new(v as f32 / n as f32, 0.5))
                .collect(),
        );
        p.look.material = Some((i % 2) as u32);
        if i == 0 {
            p.look.uv1 = Some(vec![glam::Vec2::new(0.25, 0.75); n]);
            p.look.colors = Some(vec![glam::Vec4::new(1.0, 0.5, 0.25, 1.0); n]);
        }
    }
    rig.primitives = Arc::new(prims);
    let tex = |texture, tex_coord| TexRef {
        texture,
        tex_coord,
        transform: Some(UvTransform {
            offset: [0.5, 0.0],
            rotation: 0.25,
            scale: [2.0, 1.0],
        }),
    };
    rig.appearance = Some(Arc::new(Appearance {
        materials: vec![
            Material {
                name: Some("skin".into()),
                base_color_texture: Some(tex(0, 0)),
                occlusion_texture: Some(tex(1, 1)),
                alpha_mode: AlphaMode::Mask,
                alpha_cutoff: 0.3,
                ..Material::untextured([0.9, 0.7, 0.6, 1.0])
            },
            Material {
                unlit: true,
                double_sided: true,
                emissive_strength: 4.0,
                ..Material::default()
            },
        ],
        textures: vec![
            Texture {
                sampler: Some(0),
                image: Some(0),
            },
            Texture {
                sampler: None,
                image: None,
            },
        ],
        samplers: vec![Sampler {
            mag: Filter::Nearest,
            min: Filter::Linear,
            mipmap: None,
            wrap_s: Wrap::ClampToEdge,
            wrap_t: Wrap::MirroredRepeat,
        }],
        images: vec![ImageData {
            mime: ImageMime::Png,
            bytes: Arc::from(&b"not decoded by the store"[..]),
            width: 3,
            height: 2,
            downscaled_from: Some([6, 4]),
            pixels: None,
        }],
        notes: vec!["material 1: KHR_materials_sheen not drawn".into()],
        ..Appearance::default()
    }));
    rig.validate().expect("a valid dressed rig");
    rig
}

/// [`dressed`] with a wrinkle map on material 0 and an animated texture on its first clip.
fn dressed_layers() -> Rig {
    use crowdmorph_core::rig::{AnimatedTexture, TargetTexture, TexRef, TextureRegion};
    let mut rig = dressed();
    let mut a = rig.appearance.as_deref().cloned().expect("an appearance");
    a.target_textures.push(TargetTexture {
        material: 0,
        target: rig.targets[0].clone(),
        texture: TexRef {
            texture: 0,
            tex_coord: 0,
            transform: None,
        },
    });
    let clip = &rig.clips[0];
    let frames = clip.frames;
    a.clip_textures.push(Arc::new(AnimatedTexture {
        clip: clip.name.clone(),
        material: 1,
        width: 2,
        height: 1,
        frames,
        regions: vec![TextureRegion {
            name: "all".into(),
            rect: [0, 0, 2, 1],
            components: 1,
        }],
        mean: vec![0.25, 0.5, 0.75, 0.125, 0.0, 1.0],
        components: vec![vec![0.5, 0.0, -0.5, 0.0, 0.25, 0.0]],
        component_region: vec![0],
        coefficients: (0..frames).map(|f| f as f32 * 0.01).collect(),
    }));
    rig.appearance = Some(Arc::new(a));
    rig.validate().expect("a valid rig with layers");
    rig
}

#[test]
fn every_record_type_round_trips_with_and_without_each_optional_section() {
    let plain = crowdmorph_core::embedded::default_rig();
    let mut no_clips = plain.clone();
    no_clips.clips.clear();
    let skin = skinned(false, false);
    let full = skinned(true, true);
    let mut no_tables = skinned(false, true);
    for c in &mut no_tables.clips {
        c.joints = None;
    }
    no_tables.validate().expect("valid without tables");
    let dressed = dressed();
    let layered = dressed_layers();
    let rig = |id, rig| RecordRef::Rig {
        id,
        rig,
        clips: &rig.clips,
    };
    // The record, its clip file's number, what it reads back to, its kind and its sections.
    type Case<'a> = (RecordRef<'a>, Option<u64>, Record, u32, Vec<u32>);
    let cases: Vec<Case<'_>> = vec![
        (
            rig("a", &plain),
            None,
            rig_record("a", &plain),
            12,
            vec![1, 3, 4],
        ),
        (
            rig("b", &no_clips),
            None,
            rig_record("b", &no_clips),
            12,
            vec![1, 3, 4],
        ),
        (
            rig("c", &skin),
            None,
            rig_record("c", &skin),
            12,
            vec![1, 3, 4, 5, 6],
        ),
        (
            rig("d", &full),
            None,
            rig_record("d", &full),
            12,
            vec![1, 3, 4, 5, 6, 7],
        ),
        (
            rig("e", &no_tables),
            None,
            rig_record("e", &no_tables),
            12,
            vec![1, 3, 4, 6],
        ),
        (
            rig("l", &dressed),
            None,
            rig_record("l", &dressed),
            12,
            vec![1, 3, 4, 9, 10],
        ),
        (
            rig("m", &layered),
            None,
            rig_record("m", &layered),
            12,
            vec![1, 3, 4, 9, 10, 11],
        ),
        (
            RecordRef::Builtin {
                id: "f",
                clips: &plain.clips[1..],
                rig: &plain,
            },
            None,
            builtin_record("f", &plain, &plain.clips[1..]),
            13,
            vec![1, 4, 8],
        ),
        (
            RecordRef::Builtin {
                id: "g",
                clips: &skin.clips,
                rig: &skin,
            },
            None,
            builtin_record("g", &skin, &skin.clips),
            13,
            vec![1, 4, 5, 8],
        ),
        (
            RecordRef::Builtin {
                id: "h",
                clips: &[],
                rig: &plain,
            },
            None,
            builtin_record("h", &plain, &[]),
            13,
            vec![1, 4, 8],
        ),
        (
            RecordRef::Clips {
                id: "i",
                seq: 3,
                clips: &plain.clips[2..],
                rig: &plain,
            },
            Some(3),
            clips_record("i", 3, &plain.clips[2..]),
            14,
            vec![1, 2, 4],
        ),
        (
            RecordRef::Clips {
                id: "j",
                seq: 0,
                clips: &full.clips[..1],
                rig: &full,
            },
            Some(0),
            clips_record("j", 0, &full.clips[..1]),
            14,
            vec![1, 2, 4, 5],
        ),
    ];
    for (record, seq, want, kind, tags) in cases {
        let file = encode(record, None);
        assert_eq!(kind_of(&file), kind, "{want:?}");
        let found: Vec<u32> = split(&file[HEADER..]).iter().map(|s| s.0).collect();
        assert_eq!(found, tags);
        let id = match &want {
            Record::Rig(r) => r.id.clone(),
            Record::Builtin(b) => b.id.clone(),
            Record::Clips(c) => c.id.clone(),
        };
        let got = decode(&name_of(&id, seq), &file).expect("reads back");
        assert!(got == want, "{id}: what was written reads back");
    }

    // A built-in rig's record without its LOD section has no LOD (as kind 2).
    let file = encode(
        RecordRef::Builtin {
            id: "k",
            clips: &plain.clips,
            rig: &plain,
        },
        None,
    );
    let sections: Vec<_> = split(&file[HEADER..])
        .into_iter()
        .filter(|s| s.0 != S_LOD.tag)
        .collect();
    let got = decode(&name_of("k", None), &file_bytes(13, &join(&sections))).expect("reads");
    assert_eq!(
        got,
        Record::Builtin(StoredBuiltin {
            id: "k".into(),
            clips: plain.clips.clone(),
            lod: None,
        })
    );
}

#[test]
fn the_store_writes_sections_and_reads_them_back_from_its_files() {
    let dir = std::env::temp_dir().join(format!(
        "crowdmorph-store-sections-{}-{}",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0)
    ));
    let store = Store::open(&dir).expect("open");
    let rig = skinned(true, true);
    let record = RecordRef::Rig {
        id: "s",
        rig: &rig,
        clips: &rig.clips,
    };
    store.put(record).expect("put");
    let written = fs::read(store.path_of("s")).expect("read");
    assert_eq!(
        written,
        encode(record, None),
        "put writes this build's layout"
    );
    let clips = RecordRef::Clips {
        id: "s",
        seq: 1,
        clips: &rig.clips[1..],
        rig: &rig,
    };
    store.put(clips).expect("put");
    assert_eq!(
        kind_of(&fs::read(store.clips_path("s", 1)).expect("read")),
        14
    );
    let loaded = store.load_all().expect("load");
    assert!(loaded.skipped.is_empty(), "{:?}", loaded.skipped);
    assert_eq!(
        loaded.records,
        [rig_record("s", &rig), clips_record("s", 1, &rig.clips[1..])]
    );
    let _ = fs::remove_dir_all(&dir);
}

/// Each record kind 6–11, as the pre-section writer wrote it, reads to the same value as this
/// build's record of the same rig; with compression too where the clips are in stored form.
#[test]
fn records_older_builds_wrote_read_as_before() {
    let plain = crowdmorph_core::embedded::default_rig();
    let mut compressed = plain.clone();
    for c in &mut compressed.clips {
        *c = crowdmorph_anim::compress::stored_form(&plain, c, 3e-4)
            .expect("stored form")
            .1;
    }
    let skin = skinned(false, true);
    let full = skinned(true, true);
    let mut checked = std::collections::BTreeSet::new();
    for (rig, clip_error) in [
        (&plain, None),
        (&compressed, Some(3e-4)),
        (&skin, None),
        (&full, None),
    ] {
        let records = [
            (
                RecordRef::Rig {
                    id: "r",
                    rig,
                    clips: &rig.clips,
                },
                None,
                rig_record("r", rig),
            ),
            (
                RecordRef::Builtin {
                    id: "r",
                    clips: &rig.clips[1..],
                    rig,
                },
                None,
                builtin_record("r", rig, &rig.clips[1..]),
            ),
            (
                RecordRef::Clips {
                    id: "r",
                    seq: 7,
                    clips: &rig.clips,
                    rig,
                },
                Some(7),
                clips_record("r", 7, &rig.clips),
            ),
        ];
        for (record, seq, want) in records {
            let name = name_of("r", seq);
            let (kind, payload) = legacy_payload(record, clip_error).expect("old encoding");
            let old = decode(&name, &file_bytes(kind, &payload)).expect("old kind reads");
            let new = decode(&name, &encode(record, clip_error)).expect("new kind reads");
            assert!(new == want, "kind {kind}'s record in sections reads back");
            let mut want_old = want;
            if let Record::Builtin(b) = &mut want_old {
                // Kind 7 kept no joint tables (a built-in rig has no skeleton); sections do.
                for c in &mut b.clips {
                    c.joints = None;
                }
            }
            assert!(old == want_old, "kind {kind} reads to what was stored");
            checked.insert(kind);
        }
    }
    // Every kind the old writer wrote was read.
    assert_eq!(
        checked.into_iter().collect::<Vec<_>>(),
        [
            KIND_RIG_V6,
            KIND_BUILTIN_V7,
            KIND_CLIPS_V8,
            KIND_RIG_SKINNED_V9,
            KIND_RIG_SKINNED_MAP_V10,
            KIND_CLIPS_JOINTS_V11
        ]
    );
}

/// A rig record with every section, for the tests that break one.
fn full_rig_file() -> (Rig, Vec<u8>) {
    let rig = skinned(true, true);
    let file = encode(
        RecordRef::Rig {
            id: "x",
            rig: &rig,
            clips: &rig.clips,
        },
        None,
    );
    (rig, file)
}

#[test]
fn an_unknown_optional_section_is_skipped_wherever_it_is() {
    let (rig, file) = full_rig_file();
    let name = name_of("x", None);
    let mut sections = split(&file[HEADER..]);
    sections.insert(0, (OPTIONAL | 99, vec![7; 100]));
    sections.insert(3, (OPTIONAL | 1, Vec::new()));
    sections.push((u32::MAX, b"a later build's".to_vec()));
    let got = decode(&name, &file_bytes(12, &join(&sections))).expect("reads");
    assert_eq!(got, rig_record("x", &rig));
    // So in the other kinds.
    let plain = crowdmorph_core::embedded::default_rig();
    for (record, seq) in [
        (
            RecordRef::Builtin {
                id: "x",
                clips: &plain.clips,
                rig: &plain,
            },
            None,
        ),
        (
            RecordRef::Clips {
                id: "x",
                seq: 2,
                clips: &plain.clips,
                rig: &plain,
            },
            Some(2),
        ),
    ] {
        let file = encode(record, None);
        let mut sections = split(&file[HEADER..]);
        sections.push((OPTIONAL | 5, vec![1, 2, 3]));
        let name = name_of("x", seq);
        let with = decode(&name, &file_bytes(kind_of(&file), &join(&sections))).expect("reads");
        assert_eq!(with, decode(&name, &file).expect("reads"));
    }
}

#[test]
fn broken_sections_are_refused_with_a_problem() {
    let (_, file) = full_rig_file();
    let name = name_of("x", None);
    let sections = split(&file[HEADER..]);
    let payload = join(&sections);
    let without = |tag: u32| -> Vec<u8> {
        let kept: Vec<_> = sections.iter().filter(|s| s.0 != tag).cloned().collect();
        file_bytes(12, &join(&kept))
    };
    let with = |extra: (u32, Vec<u8>)| -> Vec<u8> {
        let mut all = sections.clone();
        all.push(extra);
        file_bytes(12, &join(&all))
    };
    let id_section = sections[0].clone();
    assert_eq!(id_section.0, S_ID.tag);
    let mut past_end = payload.clone();
    // The last section's length, one more than the payload holds.
    let last = payload.len() - SECTION_HEADER - sections.last().expect("sections").1.len();
    let len = (payload.len() - last - SECTION_HEADER + 1) as u64;
    past_end[last + 4..last + 12].copy_from_slice(&len.to_le_bytes());
    let mut huge = payload.clone();
    huge[4..12].copy_from_slice(&(u64::MAX - 3).to_le_bytes());
    let cases: Vec<(&str, Vec<u8>, String)> = vec![
        (
            "no id",
            without(S_ID.tag),
            "rig record: no id section".into(),
        ),
        (
            "no rig",
            without(S_RIG.tag),
            "rig record: no rig section".into(),
        ),
        (
            "no clips",
            without(S_CLIPS.tag),
            "rig record: no clips section".into(),
        ),
        (
            "a joint map without its skin",
            without(S_SKIN.tag),
            "joint map section without a skin section".into(),
        ),
        (
            "the id twice",
            with(id_section),
            "section 0x1 appears twice".into(),
        ),
        (
            "an unknown required section",
            with((99, vec![0; 8])),
            "unknown section 0x63 that is not optional".into(),
        ),
        (
            "a clip file's section in a rig record",
            with((S_SEQ.tag, vec![1])),
            "unknown section 0x2".into(),
        ),
        (
            "the last section cut short",
            file_bytes(12, &payload[..payload.len() - 1]),
            "after its header".into(),
        ),
        (
            "a header cut short",
            file_bytes(12, &[&payload[..], &[1, 0, 0, 0, 0]].concat()),
            "truncated section header".into(),
        ),
        (
            "a length past the end",
            file_bytes(12, &past_end),
            "after its header".into(),
        ),
        (
            "a length near 2^64",
            file_bytes(12, &huge),
            format!("says {} bytes", u64::MAX - 3),
        ),
        (
            "clips that are not clips",
            {
                let mut bad = sections.clone();
                for s in &mut bad {
                    if s.0 == S_CLIPS.tag {
                        s.1 = vec![3, 1, 2];
                    }
                }
                file_bytes(12, &join(&bad))
            },
            "rig record: clips section".into(),
        ),
        (
            "an empty payload",
            file_bytes(12, &[]),
            "no id section".into(),
        ),
        (
            "an unknown kind",
            file_bytes(15, &payload),
            "unknown record kind 15".into(),
        ),
    ];
    for (what, bytes, want) in cases {
        let got = problem(&name, &bytes);
        assert!(got.contains(&want), "{what}: {got:?} does not say {want:?}");
    }
    // A clip file needs its sequence number; a built-in rig's record its clips.
    let plain = crowdmorph_core::embedded::default_rig();
    let clips = encode(
        RecordRef::Clips {
            id: "x",
            seq: 4,
            clips: &plain.clips,
            rig: &plain,
        },
        None,
    );
    let kept: Vec<_> = split(&clips[HEADER..])
        .into_iter()
        .filter(|s| s.0 != S_SEQ.tag)
        .collect();
    let got = problem(&name_of("x", Some(4)), &file_bytes(14, &join(&kept)));
    assert!(
        got.contains("clip file: no sequence number section"),
        "{got}"
    );
    let builtin = encode(
        RecordRef::Builtin {
            id: "x",
            clips: &plain.clips,
            rig: &plain,
        },
        None,
    );
    let kept: Vec<_> = split(&builtin[HEADER..])
        .into_iter()
        .filter(|s| s.0 != S_CLIPS.tag)
        .collect();
    let got = problem(&name, &file_bytes(13, &join(&kept)));
    assert!(
        got.contains("built-in rig record: no clips section"),
        "{got}"
    );
}

/// Truncations and bit flips of valid records, with the checksum made to match so that the
/// sections and their values are what is tested: each is read or refused, never a panic.
#[test]
fn damaged_records_never_panic() {
    let plain = crowdmorph_core::embedded::default_rig();
    let full = skinned(true, true);
    let files = [
        (
            name_of("x", None),
            encode(
                RecordRef::Rig {
                    id: "x",
                    rig: &full,
                    clips: &full.clips[..1],
                },
                None,
            ),
        ),
        (
            name_of("x", None),
            encode(
                RecordRef::Builtin {
                    id: "x",
                    clips: &plain.clips[..1],
                    rig: &plain,
                },
                None,
            ),
        ),
        (
            name_of("x", Some(1)),
            encode(
                RecordRef::Clips {
                    id: "x",
                    seq: 1,
                    clips: &full.clips[..1],
                    rig: &full,
                },
                None,
            ),
        ),
    ];
    let mut rng = crowdmorph_core::rng::SplitMix64(0x5ec7_1045);
    let (mut read, mut refused) = (0, 0);
    let mut tally = |r: Result<Record, StoreError>| match r {
        Ok(_) => read += 1,
        Err(StoreError::Corrupt { .. }) => refused += 1,
        Err(e) => panic!("not a problem with the record: {e}"),
    };
    for (name, file) in &files {
        let payload = &file[HEADER..];
        let kind = kind_of(file);
        let step = (payload.len() / 400).max(1);
        for cut in (0..payload.len()).step_by(step) {
            tally(Store::decode_file(
                name,
                &file_bytes(kind, &payload[..cut]),
                &mut Vec::new(),
            ));
            // And the header's own truncation, checksum unchanged.
            tally(Store::decode_file(
                name,
                &file[..HEADER + cut],
                &mut Vec::new(),
            ));
        }
        for round in 0..600 {
            let mut bad = payload.to_vec();
            let flips = 1 + round % 4;
            for _ in 0..flips {
                let at = rng.below(bad.len());
                bad[at] ^= 1 << rng.below(8);
            }
            // Now and then a section header of random bytes.
            if round % 50 == 0 {
                let at = rng.below(bad.len().saturating_sub(SECTION_HEADER).max(1));
                for b in bad.iter_mut().skip(at).take(SECTION_HEADER) {
                    *b = rng.next_u64() as u8;
                }
            }
            tally(Store::decode_file(
                name,
                &file_bytes(kind, &bad),
                &mut Vec::new(),
            ));
        }
    }
    assert!(refused > 1000 && read > 0, "{read} read, {refused} refused");
}
