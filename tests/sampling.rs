//! Keyframe sampling and clip sources.
//!
//! glTF `weights` animations are baked into clips as the glTF 2.0 specification (Appendix C)
//! defines sampling: STEP, LINEAR and CUBICSPLINE at keys and between them, the first value held
//! before the first key and the last after the last, normalized integer outputs, and the frame
//! count `floor(last_key_time × fps) + 1`. Expected values are computed here from the spec
//! formulas, independently of the library, on tiny glTF files made with the test builder.
//!
//! Also covered: `mesh.weights` as the default of targets a clip does not animate, frame wrap
//! and clamp (directly and through `export::eval_to_file`), and the CSV and JSON clip sources.

use std::path::PathBuf;

use crowdmorph::embedded::default_rig;
use crowdmorph::export::eval_to_file;
use crowdmorph::import::clips::ClipOptions;
use crowdmorph::import::gltf::rig_from_slice;
use crowdmorph::import::{ImportOptions, clip_from_csv, clip_from_json};
use crowdmorph::rig::{Clip, ClipError, FrameMode, Rig};

use crate::util::builder::{Builder, Component, TRIANGLE, triangle_rig, triangle_targets};

/// Imports a builder's document as GLB, baking at `fps`.
fn import(b: &Builder, fps: f32) -> Rig {
    let options = ImportOptions {
        fps,
        ..Default::default()
    };
    rig_from_slice(&b.to_glb(), &options).expect("the test document imports")
}

/// The only clip of a rig.
fn only_clip(rig: &Rig) -> &Clip {
    assert_eq!(rig.clips.len(), 1, "expected exactly one clip");
    &rig.clips[0]
}

/// glTF sampler interpolation, for the reference sampler below.
#[derive(Clone, Copy, PartialEq)]
enum Mode {
    Step,
    Linear,
    Cubic,
}

/// Reference sampler written from glTF 2.0 Appendix C, in f64: `values` is key-major with
/// `width` scalars per key (three groups of `width`, in-tangent / value / out-tangent, per key
/// for cubic). Before the first key the first value holds; after the last key the last.
fn reference(times: &[f32], values: &[f32], width: usize, mode: Mode, t: f64) -> Vec<f64> {
    let per_key = if mode == Mode::Cubic {
        3 * width
    } else {
        width
    };
    let value = |k: usize, j: usize| {
        let base = k * per_key + if mode == Mode::Cubic { width } else { 0 };
        f64::from(values[base + j])
    };
    let n = times.len();
    let tk = |k: usize| f64::from(times[k]);
    if t < tk(0) {
        return (0..width).map(|j| value(0, j)).collect();
    }
    if t >= tk(n - 1) {
        return (0..width).map(|j| value(n - 1, j)).collect();
    }
    let k = (0..n - 1)
        .find(|&k| tk(k) <= t && t < tk(k + 1))
        .expect("t lies between two keys");
    let td = tk(k + 1) - tk(k);
    let s = (t - tk(k)) / td;
    (0..width)
        .map(|j| match mode {
            Mode::Step => value(k, j),
            Mode::Linear => value(k, j) * (1.0 - s) + value(k + 1, j) * s,
            Mode::Cubic => {
                let p0 = value(k, j);
                let p1 = value(k + 1, j);
                let m0 = td * f64::from(values[k * per_key + 2 * width + j]);
                let m1 = td * f64::from(values[(k + 1) * per_key + j]);
                let (s2, s3) = (s * s, s * s * s);
                (2.0 * s3 - 3.0 * s2 + 1.0) * p0
                    + (s3 - 2.0 * s2 + s) * m0
                    + (-2.0 * s3 + 3.0 * s2) * p1
                    + (s3 - s2) * m1
            }
        })
        .collect()
}

/// Checks every frame of `clip` (targets `0..width`) against the reference sampler.
fn check_against_reference(
    clip: &Clip,
    fps: f32,
    times: &[f32],
    values: &[f32],
    width: usize,
    mode: Mode,
) {
    for f in 0..clip.frames {
        // The library samples t = f / fps in f32; use the same instant.
        let t = f64::from(f as f32 / fps);
        let want = reference(times, values, width, mode, t);
        for (j, w) in want.iter().enumerate() {
            let got = f64::from(clip.weight(j, f));
            assert!(
                (got - w).abs() < 1e-5,
                "target {j}, frame {f} (t = {t}): got {got}, want {w}"
            );
        }
    }
}

/// Key times shared by the interpolation tests: the first key is after t = 0, and at 4 fps
/// frames land on every key (frames 2, 4 and 8) and between keys (frames 3, 5, 6, 7).
const TIMES: [f32; 3] = [0.5, 1.0, 2.0];

#[test]
fn linear_samples_at_and_between_keys() {
    // Per key: weight of target a, weight of target b.
    let values = [0.2, 1.0, 0.6, 0.0, 1.0, 0.5];
    let mut b = triangle_rig();
    b.animation_weights("lin", 0, &TIMES, &values, "LINEAR");
    let rig = import(&b, 4.0);
    let clip = only_clip(&rig);
    assert_eq!(clip.name, "lin");
    assert_eq!(clip.frames, 9, "floor(2.0 × 4) + 1 frames");
    assert_eq!(clip.fps, 4.0);

    // Values worked out by hand: before the first key (frames 0 and 1) the first key holds.
    let by_hand: [(u32, f32, f32); 7] = [
        (0, 0.2, 1.0),
        (1, 0.2, 1.0),
        (2, 0.2, 1.0),
        (3, 0.4, 0.5),   // halfway between keys 0 and 1
        (5, 0.7, 0.125), // a quarter of the way from key 1 to key 2
        (6, 0.8, 0.25),
        (8, 1.0, 0.5),
    ];
    for (f, a, bw) in by_hand {
        assert!((clip.weight(0, f) - a).abs() < 1e-6, "a at frame {f}");
        assert!((clip.weight(1, f) - bw).abs() < 1e-6, "b at frame {f}");
    }
    check_against_reference(clip, 4.0, &TIMES, &values, 2, Mode::Linear);
}

#[test]
fn step_holds_each_key_until_the_next() {
    let values = [0.2, 1.0, 0.6, 0.0, 1.0, 0.5];
    let mut b = triangle_rig();
    b.animation_weights("step", 0, &TIMES, &values, "STEP");
    let rig = import(&b, 4.0);
    let clip = only_clip(&rig);
    assert_eq!(clip.frames, 9);
    // A key takes effect exactly at its time and holds until the next key.
    let a: Vec<f32> = (0..9).map(|f| clip.weight(0, f)).collect();
    assert_eq!(a, [0.2, 0.2, 0.2, 0.2, 0.6, 0.6, 0.6, 0.6, 1.0]);
    let bw: Vec<f32> = (0..9).map(|f| clip.weight(1, f)).collect();
    assert_eq!(bw, [1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.5]);
    check_against_reference(clip, 4.0, &TIMES, &values, 2, Mode::Step);
}

#[test]
fn cubic_spline_follows_the_hermite_formula() {
    // Per key: in-tangents (a, b), values (a, b), out-tangents (a, b). Tangents differ on both
    // sides of each key so that using the wrong one, or forgetting the × td scaling, shows.
    #[rustfmt::skip]
    let values = [
        9.0, 9.0,    0.0, 1.0,    2.0, -1.0,  // key 0 (its in-tangent is never used)
        -1.0, 0.5,   1.0, 0.0,    0.5, 3.0,   // key 1
        -2.0, 1.0,   0.5, 0.5,    7.0, 7.0,   // key 2 (its out-tangent is never used)
    ];
    let mut b = triangle_rig();
    b.animation_weights("cubic", 0, &TIMES, &values, "CUBICSPLINE");
    let rig = import(&b, 4.0);
    let clip = only_clip(&rig);
    assert_eq!(clip.frames, 9);

    // Frame 3 (t = 0.75) is halfway between keys 0 and 1: s = 0.5, td = 0.5, so
    // h00 = 0.5, h10 = 0.125, h01 = 0.5, h11 = -0.125 and
    // a = 0.5·0 + 0.125·(0.5·2) + 0.5·1 − 0.125·(0.5·−1) = 0.6875,
    // b = 0.5·1 + 0.125·(0.5·−1) + 0.5·0 − 0.125·(0.5·0.5) = 0.40625.
    assert!((clip.weight(0, 3) - 0.6875).abs() < 1e-6);
    assert!((clip.weight(1, 3) - 0.40625).abs() < 1e-6);
    // At keys the spline passes through the key values; before the first key it holds.
    for (f, a, bw) in [(0, 0.0, 1.0), (2, 0.0, 1.0), (4, 1.0, 0.0), (8, 0.5, 0.5)] {
        assert!((clip.weight(0, f) - a).abs() < 1e-6, "a at frame {f}");
        assert!((clip.weight(1, f) - bw).abs() < 1e-6, "b at frame {f}");
    }
    check_against_reference(clip, 4.0, &TIMES, &values, 2, Mode::Cubic);
}

#[test]
fn frame_count_is_floor_of_last_key_times_fps_plus_one() {
    // (last key time, fps, frames). 1.3 s at 10 fps is 13 frames after frame 0 even though
    // 1.3 is not exact in binary; 1.2 s at 4 fps ends between frames 4 and 5.
    for (last, fps, frames) in [
        (2.0, 4.0, 9),
        (1.25, 4.0, 6),
        (1.2, 4.0, 5),
        (1.3, 10.0, 14),
        (0.0, 30.0, 1),
        (1.0, 30.0, 31),
    ] {
        let mut b = triangle_rig();
        let times = if last > 0.0 {
            vec![0.0, last]
        } else {
            vec![0.0]
        };
        let values: Vec<f32> = times.iter().flat_map(|&t| [t, 1.0 - t]).collect();
        b.animation_weights("clip", 0, &times, &values, "LINEAR");
        let rig = import(&b, fps);
        let clip = only_clip(&rig);
        assert_eq!(clip.frames, frames, "last key {last} s at {fps} fps");
        assert_eq!(clip.fps, fps);
        // After the last key the last value holds, so the final frame has it.
        let end = frames - 1;
        assert!((clip.weight(0, end) - last.min(end as f32 / fps)).abs() < 1e-5);
    }
}

/// Spec decoding of normalized integer codes (glTF 2.0 §3.11).
fn decode_normalized(component: Component, c: i64) -> f64 {
    let c = c as f64;
    match component {
        Component::U8 => c / 255.0,
        Component::I8 => (c / 127.0).max(-1.0),
        Component::U16 => c / 65535.0,
        Component::I16 => (c / 32767.0).max(-1.0),
        other => panic!("{other:?} is not a normalized type"),
    }
}

#[test]
fn normalized_integer_outputs_decode_as_the_spec_says() {
    // Three keys at 0, 1 and 2 s baked at 1 fps: each frame is exactly one key, so each weight
    // is exactly one decoded code. Codes include the extremes (−128 and −32768 clamp to −1).
    // The last field is the exact value of the first two codes (frame 0, targets a and b).
    let cases: [(Component, [i64; 6], [f32; 2]); 4] = [
        (Component::U8, [0, 255, 128, 1, 51, 200], [0.0, 1.0]),
        (Component::I8, [-128, -127, 127, 0, 64, -1], [-1.0, -1.0]),
        (
            Component::U16,
            [0, 65535, 32768, 1, 13107, 60000],
            [0.0, 1.0],
        ),
        (
            Component::I16,
            [-32768, -32767, 32767, 0, 16384, -1],
            [-1.0, -1.0],
        ),
    ];
    for (component, codes, extremes) in cases {
        let mut b = triangle_rig();
        b.animation_weights_normalized("q", 0, &[0.0, 1.0, 2.0], component, &codes, "LINEAR");
        let rig = import(&b, 1.0);
        let clip = only_clip(&rig);
        assert_eq!(clip.frames, 3);
        for f in 0..3u32 {
            for j in 0..2 {
                let c = codes[f as usize * 2 + j];
                let want = decode_normalized(component, c);
                let got = f64::from(clip.weight(j, f));
                assert!(
                    (got - want).abs() < 1e-6,
                    "{component:?} code {c}: got {got}, want {want}"
                );
            }
        }
        // The extremes are exactly 0 and ±1; the signed minimum clamps to −1 (not −1.008).
        let frame0 = [clip.weight(0, 0), clip.weight(1, 0)];
        assert_eq!(frame0, extremes, "{component:?}");
    }
}

#[test]
fn mesh_default_weights_fill_targets_the_clip_does_not_animate() {
    // Mesh 0 (targets a, b; defaults 0.25, 0.75) and mesh 1 (target c; default 0.5).
    let mut b = Builder::new();
    let m0 = b.mesh_with_targets(&TRIANGLE, None, &triangle_targets(), Some(&["a", "b"]));
    b.set_mesh_weights(m0, &[0.25, 0.75]);
    let shifted: Vec<[f32; 3]> = TRIANGLE.iter().map(|p| [p[0] + 2.0, p[1], p[2]]).collect();
    let m1 = b.mesh_with_targets(&shifted, None, &[vec![[0.0, 0.0, 0.5]; 3]], Some(&["c"]));
    b.set_mesh_weights(m1, &[0.5]);
    let n0 = b.node(Some(m0));
    let n1 = b.node(Some(m1));
    b.scene(&[n0, n1]);
    // One clip animates only mesh 0, the other only mesh 1.
    b.animation_weights("ab", n0, &[0.0, 1.0], &[0.0, 0.0, 1.0, 1.0], "LINEAR");
    b.animation_weights("c", n1, &[0.0, 1.0], &[1.0, 0.0], "LINEAR");
    let rig = import(&b, 2.0);

    assert_eq!(rig.targets, ["a", "b", "c"]);
    assert_eq!(rig.default_weights, [0.25, 0.75, 0.5]);
    let ab = &rig.clips[rig.clip_index("ab").expect("clip ab")];
    let c = &rig.clips[rig.clip_index("c").expect("clip c")];
    assert_eq!(ab.frames, 3);
    for f in 0..3 {
        // Animated rows follow the keys; the other mesh's rows hold its defaults.
        let s = f as f32 / 2.0;
        assert!((ab.weight(0, f) - s).abs() < 1e-6);
        assert!((ab.weight(1, f) - s).abs() < 1e-6);
        assert_eq!(ab.weight(2, f), 0.5, "c holds its default in clip ab");
        assert_eq!(c.weight(0, f), 0.25, "a holds its default in clip c");
        assert_eq!(c.weight(1, f), 0.75, "b holds its default in clip c");
        assert!((c.weight(2, f) - (1.0 - s)).abs() < 1e-6);
    }
}

/// A triangle rig with a 9-frame linear clip `walk` whose every frame differs.
fn wrap_rig() -> Rig {
    let mut b = triangle_rig();
    // a rises from 0 to 1 over two seconds; b falls from 1 to 0.
    b.animation_weights("walk", 0, &[0.0, 2.0], &[0.0, 1.0, 1.0, 0.0], "LINEAR");
    import(&b, 4.0)
}

#[test]
fn resolve_frame_wraps_clamps_and_refuses() {
    let rig = wrap_rig();
    let clip = only_clip(&rig);
    let n = i64::from(clip.frames);
    assert_eq!(n, 9);
    let wrap = |f| clip.resolve_frame(f, FrameMode::Wrap);
    let clamp = |f| clip.resolve_frame(f, FrameMode::Clamp);
    let strict = |f| clip.resolve_frame(f, FrameMode::Strict);

    assert_eq!(wrap(0), Ok(0));
    assert_eq!(wrap(n - 1), Ok(8));
    assert_eq!(wrap(n), Ok(0));
    assert_eq!(wrap(n + 2), Ok(2));
    assert_eq!(wrap(-1), Ok(8), "negative frames count back from the end");
    assert_eq!(wrap(-n), Ok(0));
    assert_eq!(wrap(-n - 2), Ok(7));
    assert_eq!(wrap(i64::MAX), Ok((i64::MAX % n) as u32));
    assert_eq!(wrap(i64::MIN), Ok(i64::MIN.rem_euclid(n) as u32));

    assert_eq!(clamp(-5), Ok(0));
    assert_eq!(clamp(3), Ok(3));
    assert_eq!(clamp(n + 2), Ok(8));
    assert_eq!(clamp(i64::MAX), Ok(8));

    assert_eq!(strict(n - 1), Ok(8));
    for f in [n, n + 2, -1] {
        assert_eq!(
            strict(f),
            Err(ClipError::FrameOutOfRange {
                clip: "walk".into(),
                frame: f,
                frames: 9
            })
        );
    }
}

/// A scratch directory under the system temp dir, removed when dropped.
struct TempDir(PathBuf);

impl TempDir {
    fn new(tag: &str) -> Self {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let dir = std::env::temp_dir().join(format!(
            "crowdmorph-test-{tag}-{}-{nanos}",
            std::process::id()
        ));
        std::fs::create_dir_all(&dir).expect("create temp dir");
        TempDir(dir)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

#[test]
fn eval_to_file_wraps_and_clamps_frames() {
    let rig = wrap_rig();
    let frames = i64::from(only_clip(&rig).frames);
    let dir = TempDir::new("eval");
    let eval = |frame: i64, mode: FrameMode| -> Vec<u8> {
        let path = dir.0.join(format!("f{frame}-{mode:?}.bin"));
        eval_to_file(&rig, "walk", frame, 0, mode, &path).expect("eval succeeds");
        std::fs::read(&path).expect("read eval output")
    };

    let frame2 = eval(2, FrameMode::Strict);
    let last = eval(frames - 1, FrameMode::Strict);
    // Three vertices, xyz, f32.
    assert_eq!(frame2.len(), 3 * 3 * 4);
    let xyz: Vec<f32> = frame2
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    // At frame 2 (t = 0.5 s) a = 0.25 lifts vertex 1 by 0.25 and b = 0.75 lifts vertex 2 by
    // 0.75 × 2: the .bin holds base + Σ w Δ.
    let want = [0.0, 0.0, 0.0, 1.0, 0.0, 0.25, 0.0, 1.0, 1.5];
    for (g, w) in xyz.iter().zip(want) {
        assert!((g - w).abs() < 1e-6, "{xyz:?} vs {want:?}");
    }
    assert_ne!(frame2, last, "frames 2 and {} must differ", frames - 1);

    assert_eq!(eval(frames + 2, FrameMode::Wrap), frame2);
    assert_eq!(eval(-(frames - 2), FrameMode::Wrap), frame2);
    assert_eq!(eval(frames + 2, FrameMode::Clamp), last);
    assert_eq!(eval(-3, FrameMode::Clamp), eval(0, FrameMode::Strict));
    let path = dir.0.join("strict.bin");
    let err = eval_to_file(&rig, "walk", frames, 0, FrameMode::Strict, &path)
        .expect_err("strict refuses a frame past the end");
    assert!(err.to_string().contains("past the end"), "{err}");
    // An output name that is neither .obj nor .bin is refused before any file is made.
    let bad = dir.0.join("head.txt");
    let err = eval_to_file(&rig, "walk", 0, 0, FrameMode::Strict, &bad).expect_err("bad name");
    assert!(err.to_string().contains(".obj or .bin"), "{err}");
    assert!(!bad.exists(), "no empty file left behind");
}

/// The embedded rig with a non-zero default weight on `cheekPuff`, so that "holds the rig
/// default" is distinguishable from "holds zero".
fn face_rig() -> Rig {
    let mut rig = default_rig();
    let id = rig.target_id("cheekPuff").expect("cheekPuff") as usize;
    rig.default_weights[id] = 0.3;
    rig
}

/// Row of target `name` of a clip of `rig`.
fn row(rig: &Rig, clip: &Clip, name: &str) -> Vec<f32> {
    let t = rig
        .target_id(name)
        .unwrap_or_else(|| panic!("no target {name}")) as usize;
    (0..clip.frames).map(|f| clip.weight(t, f)).collect()
}

#[test]
fn csv_clip_maps_columns_by_loose_name_and_skips_metadata() {
    let rig = face_rig();
    // Live Link Face layout: Timecode and BlendShapeCount are metadata, names are CamelCase
    // with Left/Right suffixes.
    let csv = "Timecode,BlendShapeCount,EyeBlinkLeft,JawOpen,MouthSmileRight\n\
               00:00:00:00.000,3,0.1,0.5,0.25\n\
               00:00:00:01.000,3,0.2,0.6,0\n\
               00:00:00:02.000,3,0.3,0.7,1\n";
    let options = ClipOptions {
        fps: 60.0,
        ..Default::default()
    };
    let imported = clip_from_csv(&rig, "take", csv.as_bytes(), &options).expect("CSV imports");
    assert!(imported.ignored.is_empty());
    let clip = &imported.clip;
    assert_eq!(clip.name, "take");
    assert_eq!(clip.fps, 60.0);
    assert_eq!(clip.frames, 3);
    assert_eq!(clip.targets as usize, rig.targets.len());
    assert_eq!(row(&rig, clip, "eyeBlink_L"), [0.1, 0.2, 0.3]);
    assert_eq!(row(&rig, clip, "jawOpen"), [0.5, 0.6, 0.7]);
    assert_eq!(row(&rig, clip, "mouthSmile_R"), [0.25, 0.0, 1.0]);
    // Targets absent from the source hold the rig default.
    assert_eq!(row(&rig, clip, "cheekPuff"), [0.3; 3]);
    assert_eq!(row(&rig, clip, "eyeBlink_R"), [0.0; 3]);
    assert_eq!(row(&rig, clip, "mouthSmile_L"), [0.0; 3]);
}

#[test]
fn json_clip_lands_in_the_right_rows_and_frames() {
    let rig = face_rig();
    let json = br#"{"fps": 24, "targets": ["jawOpen", "EyeBlinkRight"],
                    "frames": [[0.5, 0.0], [1.0, 0.25], [0.0, 1.0], [0.75, 0.5]]}"#;
    let imported = clip_from_json(&rig, "j", json, &ClipOptions::default()).expect("JSON imports");
    assert!(imported.ignored.is_empty());
    let clip = &imported.clip;
    assert_eq!(clip.fps, 24.0, "the file's fps wins over the option");
    assert_eq!(clip.frames, 4);
    assert_eq!(row(&rig, clip, "jawOpen"), [0.5, 1.0, 0.0, 0.75]);
    assert_eq!(row(&rig, clip, "eyeBlink_R"), [0.0, 0.25, 1.0, 0.5]);
    assert_eq!(row(&rig, clip, "cheekPuff"), [0.3; 4]);
    assert_eq!(row(&rig, clip, "eyeBlink_L"), [0.0; 4]);

    // Without "fps" the option's rate is used.
    let json = br#"{"targets": ["jawOpen"], "frames": [[0.5]]}"#;
    let options = ClipOptions {
        fps: 50.0,
        ..Default::default()
    };
    let clip = clip_from_json(&rig, "k", json, &options)
        .expect("JSON imports")
        .clip;
    assert_eq!(clip.fps, 50.0);
    assert_eq!(row(&rig, &clip, "jawOpen"), [0.5]);
}

/// The keyframes of a rig's own animations are decoded once, to plan the weight channels, and
/// held (charged to the import's budget) until they are baked, then released; a clip whose
/// key times declare their `max` is sized from it, one that does not from its decoded keys.
#[test]
fn import_decodes_keyframes_once_and_holds_them_charged_until_baked() {
    use crowdmorph::budget::Budget;
    use crowdmorph::import::gltf::GltfImport;
    use std::sync::Arc;
    const KEYS: usize = 4000;
    let times: Vec<f32> = (0..KEYS).map(|k| k as f32 / 100.0).collect();
    let values: Vec<f32> = (0..2 * KEYS)
        .map(|i| ((i * 7919) % 1000) as f32 / 1000.0)
        .collect();
    let mut b = triangle_rig();
    b.animation_weights("declared", 0, &times, &values, "STEP");
    let input = b.json_mut()["animations"][0]["samplers"][0]["input"]
        .as_u64()
        .unwrap() as usize;
    b.accessor_mut(input)["min"] = serde_json::json!([0.0]);
    b.accessor_mut(input)["max"] = serde_json::json!([times[KEYS - 1]]);
    b.animation_weights("measured", 0, &times, &values, "STEP");
    let glb = b.to_glb();
    let fps = 30.0;
    let budget = Arc::new(Budget::new(1 << 30, "--max-upload-memory", None));
    let options = ImportOptions {
        fps,
        budget: Some(budget.clone()),
        ..Default::default()
    };
    let import = GltfImport::open(&glb, &options).expect("opens");
    let keyframes = (2 * (times.len() + values.len()) * 4) as u64;
    let held = budget.used();
    assert!(
        held >= keyframes,
        "open holds {held} bytes, less than the {keyframes} of decoded keyframes"
    );
    let frames = (times[KEYS - 1] * fps + 1e-3).floor() as u64 + 1;
    assert_eq!(import.shape().clip_cells, 2 * 2 * frames);
    let ahead = import.import_bytes();
    let rig = import.build(&options).expect("builds");
    // The build stays within what the headers and the held keyframes promised ...
    assert!(
        budget.peak() <= held + ahead,
        "peak {} > {held} + {ahead}",
        budget.peak()
    );
    // ... and gives the keyframes back once baked: what stays is less than the rig's arrays
    // on top of what open held without them.
    assert!(
        budget.used() <= held - keyframes + rig.host_bytes() as u64,
        "{} bytes still held",
        budget.used()
    );
    for clip in &rig.clips {
        assert_eq!(u64::from(clip.frames), frames, "{}", clip.name);
        for f in (0..clip.frames).step_by(97) {
            let t = f as f32 / fps;
            let key = times.partition_point(|&k| k <= t).saturating_sub(1);
            for j in 0..2 {
                assert_eq!(
                    clip.weight(j, f),
                    values[key * 2 + j],
                    "{} frame {f}",
                    clip.name
                );
            }
        }
    }
}

/// Animations that share a name (or take a suffixed name another already has) come out
/// named uniquely, in file order, from the rig's own file and as clips of another rig; each
/// keeps its own curve.
#[test]
fn animations_with_one_name_get_the_first_free_suffixes() {
    let mut b = triangle_rig();
    // Four "talk"s, one of them after an animation that took "talk_3" itself.
    for (k, name) in ["talk", "talk", "talk_3", "talk", "talk", ""]
        .iter()
        .enumerate()
    {
        let w = k as f32 / 10.0;
        b.animation_weights(name, 0, &[0.0], &[w, 0.0], "STEP");
    }
    let want = ["talk", "talk_2", "talk_3", "talk_4", "talk_5", "anim5"];
    let rig = import(&b, 30.0);
    let names: Vec<&str> = rig.clips.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, want);
    for (k, c) in rig.clips.iter().enumerate() {
        assert_eq!(
            c.weights[0],
            k as f32 / 10.0,
            "clip {} keeps its own curve",
            c.name
        );
    }
    let clips = crowdmorph::import::clips_from_gltf(
        &rig,
        &b.to_glb(),
        &ClipOptions {
            fps: 30.0,
            ..ClipOptions::default()
        },
    )
    .expect("the same file imports as clips");
    let names: Vec<&str> = clips.iter().map(|c| c.clip.name.as_str()).collect();
    assert_eq!(names, want);
    assert!(clips.iter().all(|c| c.ignored.is_empty()));
}
