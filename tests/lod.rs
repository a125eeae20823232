//! Level of detail: importance metrics and orders, LOD reports, feature-preserving mesh levels.
//!
//! Real-data checks use ICT FaceKit (26,719 vertices × 53 ARKit targets, left/right twins that
//! are near mirror images) and MorphStressTest; the embedded head has exact mirror twins. ICT is
//! scored once per test run and shared.

use crate::util::gpu_test;
use std::sync::{Arc, OnceLock};

use crowdmorph::engine::cpu::CpuRig;
use crowdmorph::engine::gpu::GpuOptions;
use crowdmorph::engine::{
    BackendChoice, BackendKind, BlendJob, Engine, OutputSpec, Precision, WeightBatch,
};
use crowdmorph::import::{ImportOptions, load_path};
use crowdmorph::lod::metrics::{PointIndex, YeeParams, YeeReference, hausdorff, image_mse, ssim};
use crowdmorph::lod::order::{SparseIndex, target_displacement};
use crowdmorph::lod::raster::{Camera, neutral_positions, render_pose};
use crowdmorph::lod::report::{
    Displacements, clip_errors, lod_report, no_worse, report_png, report_text, synthetic_clip,
};
use crowdmorph::lod::{
    LodBuildError, LodSpec, Metric, OrderMethod, Progress, ScoreOptions, Scores, SimplifyOptions,
    build_lod, build_mesh_levels, mesh_level_rig, score_targets,
};
use crowdmorph::rig::{
    MeshLevel, Primitive, Rig, VertexLook, default_lod_levels, sparsify, vertex_normals,
};
use glam::{Vec2, Vec3};

use crate::util::{max_abs_diff, open_gpu, rig_files, rig_oracle};

/// One of the shared rigs, by file name.
fn rig_file(name: &str) -> std::path::PathBuf {
    rig_files()
        .into_iter()
        .find(|f| f.ends_with(name))
        .expect("a shared rig")
}

/// ICT FaceKit (from ../shared/data), loaded once per run.
fn ict() -> &'static Rig {
    static RIG: OnceLock<Rig> = OnceLock::new();
    RIG.get_or_init(|| {
        load_path(&rig_file("ict_facekit_53.glb"), &ImportOptions::default())
            .expect("ICT FaceKit loads")
    })
}

/// ICT FaceKit's scores, computed once per run.
fn ict_scores() -> &'static Scores {
    static SCORES: OnceLock<Scores> = OnceLock::new();
    SCORES.get_or_init(|| score_targets(ict(), &ScoreOptions::default(), None).expect("ICT scores"))
}

/// MorphStressTest (from ../shared/data).
fn morph_stress_test() -> Rig {
    load_path(&rig_file("MorphStressTest.gltf"), &ImportOptions::default())
        .expect("MorphStressTest loads")
}

/// Relative difference of two scores.
fn rel(a: f64, b: f64) -> f64 {
    if a == b {
        0.0
    } else {
        (a - b).abs() / a.abs().max(b.abs())
    }
}

/// Checks that every `_L` target and its `_R` twin score within 5 % under the geometric metrics
/// and SSIM (as dissimilarity, 1 − SSIM); returns the worst relative difference seen.
fn check_mirror_twins(rig: &Rig, scores: &Scores) -> f64 {
    let mut pairs = 0;
    let mut worst: f64 = 0.0;
    for (i, name) in rig.targets.iter().enumerate() {
        let Some(stem) = name.strip_suffix("_L") else {
            continue;
        };
        let twin = rig
            .target_id(&format!("{stem}_R"))
            .unwrap_or_else(|| panic!("{name} has no _R twin"));
        let (l, r) = (&scores.targets[i], &scores.targets[twin as usize]);
        for m in [Metric::GeometricMse, Metric::Hausdorff, Metric::Ssim] {
            let d = rel(l.importance(m), r.importance(m));
            assert!(
                d <= 0.05,
                "{name} vs {stem}_R under {}: {} vs {} ({:.1} %)",
                m.name(),
                l.importance(m),
                r.importance(m),
                d * 100.0
            );
            worst = worst.max(d);
        }
        pairs += 1;
    }
    assert!(pairs >= 15, "only {pairs} left/right pairs");
    worst
}

#[test]
fn orders_are_deterministic() {
    let rig = crowdmorph::embedded::default_rig();
    let opts = ScoreOptions {
        image_size: 160,
        ..ScoreOptions::default()
    };
    let a = score_targets(&rig, &opts, None).expect("scores");
    // Another thread count must not change a bit of it.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    let b = pool.install(|| score_targets(&rig, &opts, None).expect("scores"));
    assert_eq!(a, b);
    for m in OrderMethod::all() {
        let o = a.order(m);
        assert_eq!(o, b.order(m), "{}", m.name());
        let mut sorted = o.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..rig.targets.len() as u32).collect::<Vec<_>>());
    }
    // The metrics see what a face does: opening the jaw matters more than a dimple.
    let rank = |name: &str| {
        let id = rig.target_id(name).expect("target");
        a.combined_order()
            .iter()
            .position(|&t| t == id)
            .expect("ranked")
    };
    assert!(rank("jawOpen") < rank("mouthDimple_L"));
}

#[test]
fn mirrored_targets_score_alike_on_the_embedded_head() {
    let rig = crowdmorph::embedded::default_rig();
    let scores = score_targets(&rig, &ScoreOptions::default(), None).expect("scores");
    let worst = check_mirror_twins(&rig, &scores);
    // Exact mirror twins on a mirror-symmetric mesh, camera and light: (almost) identical.
    assert!(worst < 1e-3, "worst left/right difference {worst}");
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn mirrored_targets_score_alike_on_ict_facekit() {
    let (rig, scores) = (ict(), ict_scores());
    let worst = check_mirror_twins(rig, scores);
    eprintln!(
        "ICT FaceKit: worst left/right difference {:.2} %",
        worst * 100.0
    );
}

#[test]
fn identical_images_score_perfect() {
    let rig = crowdmorph::embedded::default_rig();
    let camera = Camera::for_rig(&rig, 200);
    let neutral = neutral_positions(&rig);
    let a = render_pose(&rig, &neutral, &camera);
    let b = render_pose(&rig, &neutral, &camera);
    assert_eq!(a, b, "rendering is deterministic");
    let px = &a.image.pixels;
    assert!(
        px.iter().filter(|&&v| v > 0.0).count() > 10_000,
        "the head is drawn"
    );
    assert_eq!(image_mse(px, &b.image.pixels), 0.0);
    assert_eq!(ssim(px, &b.image.pixels, 200, 200), 1.0);
    let yee = YeeReference::new(px, 200, 200, YeeParams::default());
    assert_eq!(yee.failing_pixels(&b.image.pixels), 0);
    // And an expression is not perfect.
    let (v, d) = target_displacement(
        &rig,
        &rig.vertex_offsets(),
        rig.target_id("jawOpen").expect("jaw"),
    );
    let mut posed = neutral.clone();
    for (&i, &d) in v.iter().zip(&d) {
        posed[i as usize] += d;
    }
    let c = render_pose(&rig, &posed, &camera);
    assert!(image_mse(px, &c.image.pixels) > 0.0);
    assert!(ssim(px, &c.image.pixels, 200, 200) < 1.0);
    assert!(yee.failing_pixels(&c.image.pixels) > 0);
}

#[test]
fn hausdorff_with_the_index_equals_brute_force() {
    let rig = crowdmorph::embedded::default_rig();
    let neutral = neutral_positions(&rig);
    let index = PointIndex::new(&neutral);
    let offsets = rig.vertex_offsets();
    for name in ["jawOpen", "eyeBlink_L", "mouthSmile_R", "browInnerUp"] {
        let (v, d) = target_displacement(&rig, &offsets, rig.target_id(name).expect("target"));
        let mut posed = neutral.clone();
        for (&i, &d) in v.iter().zip(&d) {
            posed[i as usize] += d;
        }
        let one_way = |a: &[Vec3], b: &[Vec3]| -> f32 {
            a.iter()
                .map(|p| {
                    b.iter()
                        .map(|q| p.distance(*q))
                        .fold(f32::INFINITY, f32::min)
                })
                .fold(0.0, f32::max)
        };
        let brute = one_way(&neutral, &posed).max(one_way(&posed, &neutral));
        let fast = hausdorff(&neutral, &index, &v, &d);
        assert!(
            (fast - f64::from(brute)).abs() <= 1e-6 * f64::from(brute).max(1.0),
            "{name}: {fast} vs brute force {brute}"
        );
    }
}

/// On the embedded head's speech and expression clips the combined order is no worse than
/// file order at every level, and clearly better somewhere. (Its `idle` and `smile` clips are
/// not asserted: they animate mostly gaze, blinks and small shapes that a clip-independent
/// importance order ranks low, and the file order happens to list those first — the paper's
/// reason for pinning.)
#[test]
fn ordered_lod_beats_unordered_truncation_on_the_embedded_head() {
    let rig = crowdmorph::embedded::default_rig();
    let scores = score_targets(&rig, &ScoreOptions::default(), None).expect("scores");
    for name in ["talk", "surprise"] {
        let ci = rig.clip_index(name).expect("clip");
        let report = lod_report(&rig, ci, &scores, &[]).expect("report");
        let file = report.order("file-order").expect("file order");
        let combined = report.order("combined").expect("combined");
        for (a, b) in combined.levels.iter().zip(&file.levels) {
            assert!(
                no_worse(a, b),
                "clip {name}: level {} combined {a:?} vs file order {b:?}",
                a.level
            );
        }
        // Level 0 is exact, and somewhere ordering strictly helps.
        assert_eq!((combined.levels[0].max, combined.levels[0].rms), (0.0, 0.0));
        assert!(
            combined
                .levels
                .iter()
                .zip(&file.levels)
                .any(|(a, b)| a.rms < b.rms * 0.5),
            "clip {name}: ordering never helps much"
        );
    }
}

/// MorphStressTest's eight targets are one bump at eight places: every order is as good as
/// any other. The combined and geometric orders are no worse than file order at every level of
/// every clip; the image orders agree with it to 1e-6 (the bumps differ only by f32 rounding of
/// the file's deltas, which is all an order can exploit there).
#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn ordered_lod_is_no_worse_than_unordered_truncation_on_morph_stress_test() {
    let rig = morph_stress_test();
    let scores = score_targets(&rig, &ScoreOptions::default(), None).expect("scores");
    let disp = Displacements::new(&rig);
    let levels = default_lod_levels(rig.targets.len());
    let file: Vec<u32> = (0..rig.targets.len() as u32).collect();
    for ci in 0..rig.clips.len() {
        let base = clip_errors(&rig, &disp, ci, &file, &levels).expect("file order");
        for m in OrderMethod::all() {
            let got = clip_errors(&rig, &disp, ci, &scores.order(m), &levels).expect("errors");
            let strict = matches!(
                m,
                OrderMethod::Combined
                    | OrderMethod::Metric(Metric::GeometricMse | Metric::Hausdorff)
            );
            for (a, b) in got.iter().zip(&base) {
                let close = a.max <= b.max * (1.0 + 1e-6) && a.rms <= b.rms * (1.0 + 1e-6);
                assert!(
                    if strict { no_worse(a, b) } else { close },
                    "{} clip {}: level {} {a:?} vs file order {b:?}",
                    m.name(),
                    rig.clips[ci].name,
                    a.level
                );
            }
        }
    }
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn ordered_lod_beats_unordered_truncation_on_ict_facekit() {
    let (rig, scores) = (ict(), ict_scores());
    let mut rig = rig.clone();
    rig.clips
        .push(synthetic_clip(&rig, "random", 60, 7).expect("synthetic clip"));
    let ci = rig.clips.len() - 1;
    let report = lod_report(&rig, ci, scores, &[]).expect("report");
    let file = report.order("file-order").expect("file order");
    for o in &report.orders {
        for (a, b) in o.levels.iter().zip(&file.levels) {
            if o.method == "combined" || o.method == "geometric-mse" {
                assert!(no_worse(a, b), "{}: {a:?} vs {b:?}", o.method);
            }
        }
    }
    // The paper's claim, measured: half the shapes in combined order lose a fraction of what
    // half in file order lose.
    let (c1, f1) = (
        &report.order("combined").expect("combined").levels[1],
        &file.levels[1],
    );
    assert!(c1.rms < 0.6 * f1.rms, "{c1:?} vs {f1:?}");
    let text = report_text(&report);
    assert!(text.contains("combined") && text.contains("file-order"));
    let png = report_png(&report).expect("png");
    assert!(png.starts_with(b"\x89PNG"));
}

#[test]
fn synthetic_clips_are_deterministic_and_plausible() {
    let rig = crowdmorph::embedded::default_rig();
    let a = synthetic_clip(&rig, "random", 150, 1).expect("clip");
    assert_eq!(a, synthetic_clip(&rig, "random", 150, 1).expect("clip"));
    assert_ne!(a, synthetic_clip(&rig, "random", 150, 2).expect("clip"));
    assert!(a.weights.iter().all(|w| (0.0..=1.0).contains(w)));
    let active = a.weights.iter().filter(|&&w| w > 1e-6).count() as f64 / a.weights.len() as f64;
    assert!((0.1..0.6).contains(&active), "{active}");
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn ict_feature_points_survive_at_ten_percent() {
    let rig = ict();
    let (levels, features) =
        build_mesh_levels(rig, &[0.1], &SimplifyOptions::default(), None).expect("levels");
    for name in [
        "nose_tip",
        "nose_top",
        "nose_bottom",
        "nose_bottom_L",
        "nose_bottom_R",
        "eye_socket_L",
        "eye_socket_R",
        "lip_top",
        "lip_bottom",
        "chin",
        "mouth_corner_L",
        "mouth_corner_R",
    ] {
        assert!(features.landmark(name).is_some(), "{name} not found");
    }
    // The anatomy is where an upright ICT head has it: the nose tip is the front-most point on
    // the mid-plane, the mouth corners are mirror images below it, the chin below the lips.
    let pos = neutral_positions(rig);
    let at = |n: &str| pos[features.landmark(n).expect("landmark") as usize];
    assert!(at("nose_tip").x.abs() < 1e-3);
    let (l, r) = (at("mouth_corner_L"), at("mouth_corner_R"));
    assert!(l.x > 1.0 && r.x < -1.0 && (l.x + r.x).abs() < 0.2 && (l.y - r.y).abs() < 0.2);
    assert!(at("lip_top").y > at("lip_bottom").y && at("lip_bottom").y > at("chin").y);
    assert!(at("nose_bottom").y > at("lip_top").y);
    assert!(
        features.lip_line.len() >= 10,
        "{} lip line vertices",
        features.lip_line.len()
    );
    assert!(!features.motion_peaks.is_empty());

    let level = &levels[0];
    let tris = level.triangle_count();
    assert!(
        tris <= rig.triangle_count() / 10 + rig.triangle_count() / 50,
        "{tris} triangles"
    );
    let map = level.vertex_map(&rig.vertex_offsets());
    let mut used = vec![false; map.len()];
    let mut base = 0;
    for p in level.primitives.iter() {
        for &i in &p.indices {
            used[base + i as usize] = true;
        }
        base += p.vertices.len();
    }
    for v in features.vertices() {
        let k = map
            .binary_search(&v)
            .unwrap_or_else(|_| panic!("feature vertex {v} was removed"));
        assert!(used[k], "feature vertex {v} kept but on no triangle");
    }
}

/// Evaluates `rig` at `weights` (by target id) with the CPU engine: positions and normals.
fn cpu_eval(rig: &Rig, weights: &[Vec<f32>]) -> Vec<(Vec<f32>, Vec<f32>)> {
    let batch = WeightBatch::from_target_weights(rig, weights, 0).expect("batch");
    let spec = OutputSpec {
        normals: true,
        ..OutputSpec::default()
    };
    let out = CpuRig::new(rig).evaluate(&batch, spec).expect("evaluate");
    (0..weights.len())
        .map(|j| (out.job_positions(j), out.job_normals(j).expect("normals")))
        .collect()
}

/// Mesh levels of `rig` evaluate through the CPU engine as their derived rigs, match the
/// derived rig's f64 oracle, and every kept vertex lands exactly where the full rig puts it.
fn check_mesh_levels(rig: &Rig, fractions: &[f32]) {
    let (levels, _) =
        build_mesh_levels(rig, fractions, &SimplifyOptions::default(), None).expect("levels");
    let diag = f64::from(rig.bbox().diagonal());
    let mut rng = crate::util::Rng(11);
    let weights: Vec<Vec<f32>> = (0..3)
        .map(|_| (0..rig.targets.len()).map(|_| rng.f64() as f32).collect())
        .collect();
    let full = cpu_eval(rig, &weights);
    let mut previous = usize::MAX;
    for level in &levels {
        let derived = mesh_level_rig(rig, level).expect("derived rig");
        assert!(derived.vertex_count() < previous, "levels shrink");
        previous = derived.vertex_count();
        assert_eq!(derived.targets, rig.targets);
        assert_eq!(derived.clips, rig.clips);
        assert_eq!(derived.lod.order, rig.lod.order);
        let map = level.vertex_map(&rig.vertex_offsets());
        let got = cpu_eval(&derived, &weights);
        for (j, w) in weights.iter().enumerate() {
            let w64: Vec<f64> = w.iter().map(|&x| f64::from(x)).collect();
            let (want, want_normals) = rig_oracle(&derived, &w64);
            let err = max_abs_diff(&got[j].0, &want);
            assert!(err <= 1e-5 * diag, "{}: {err} vs oracle", derived.name);
            // Normals too: recomputed from the level's own triangles, which have no folds. A
            // simplified mesh has long thin triangles whose normals the f32 rounding of the
            // blended positions moves more than on the full mesh (≈ 4e-3 on ICT at 50 %), hence
            // 1e-2 where the full rigs' tests allow 1e-3.
            let ntol = if derived.has_normal_deltas() {
                1e-4
            } else {
                1e-2
            };
            let err = max_abs_diff(&got[j].1, &want_normals);
            assert!(err <= ntol, "{}: normals {err} vs oracle", derived.name);
            for (k, &v) in map.iter().enumerate() {
                for c in 0..3 {
                    let (a, b) = (got[j].0[k * 3 + c], full[j].0[v as usize * 3 + c]);
                    assert!(
                        (f64::from(a) - f64::from(b)).abs() <= 1e-5 * diag,
                        "{}: vertex {v} moved differently ({a} vs {b})",
                        derived.name
                    );
                }
            }
        }
    }
}

#[test]
fn mesh_levels_evaluate_through_the_cpu_engine_on_the_embedded_head() {
    let rig = crowdmorph::embedded::default_rig();
    check_mesh_levels(&rig, &[0.5, 0.25, 0.1]);
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn mesh_levels_evaluate_through_the_cpu_engine_on_real_rigs() {
    check_mesh_levels(ict(), &[0.5, 0.1]);
    check_mesh_levels(&morph_stress_test(), &[0.5, 0.25]);
}

/// Mesh levels are ordinary rigs to the engines: the GPU engine (Mesa's lavapipe where there is
/// no hardware GPU) agrees with the CPU engine on every derived rig, positions and normals, at
/// every LOD level. Tolerances as in the GPU engine's own tests.
fn check_mesh_levels_on_the_gpu(rig: &Rig, fractions: &[f32]) {
    let gpu = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
    let cpu = Engine::cpu();
    let (levels, _) =
        build_mesh_levels(rig, fractions, &SimplifyOptions::default(), None).expect("levels");
    for level in &levels {
        let derived = Arc::new(mesh_level_rig(rig, level).expect("derived rig"));
        let mut rng = crate::util::Rng(5);
        let jobs: Vec<BlendJob> = (0..12)
            .map(|k| {
                let clip = rng.below(derived.clips.len());
                BlendJob::frame(
                    clip as u32,
                    rng.below(derived.clips[clip].frames as usize) as u32,
                    (k % derived.lod.levels.len()) as u32,
                )
            })
            .collect();
        let spec = OutputSpec {
            normals: true,
            precision: Precision::F32,
        };
        let g = gpu.prepare(derived.clone()).expect("upload");
        let c = cpu.prepare(derived.clone()).expect("prepare");
        let got = gpu.evaluate(&g, &jobs, spec).expect("gpu");
        let want = cpu.evaluate(&c, &jobs, spec).expect("cpu");
        assert_eq!(got.kind, Some(BackendKind::Gpu), "{}", derived.name);
        let diag = derived.bbox().diagonal();
        let ntol = if derived.has_normal_deltas() {
            1e-4
        } else {
            1e-3
        };
        let diff = |a: &[f32], b: &[f32]| {
            a.iter()
                .zip(b)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0f32, f32::max)
        };
        for j in 0..jobs.len() {
            let d = diff(&got.output.job_positions(j), &want.output.job_positions(j));
            assert!(
                d <= 1e-5 * diag,
                "{} job {j}: positions differ by {d:e}",
                derived.name
            );
            let n = diff(
                &got.output.job_normals(j).expect("normals"),
                &want.output.job_normals(j).expect("normals"),
            );
            assert!(
                n <= ntol,
                "{} job {j}: normals differ by {n:e}",
                derived.name
            );
        }
    }
}

gpu_test!(
    #[test]
    fn mesh_levels_match_on_the_gpu_and_cpu_engines_on_the_embedded_head() {
        check_mesh_levels_on_the_gpu(&crowdmorph::embedded::default_rig(), &[0.5, 0.1]);
    }
);

gpu_test!(
    #[test]
    #[cfg_attr(
        all(crowdmorph_gpu_driver, not(crowdmorph_test_data)),
        ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
    )]
    fn mesh_levels_match_on_the_gpu_and_cpu_engines_on_ict_facekit() {
        let mut rig = ict().clone();
        rig.clips
            .push(synthetic_clip(&rig, "random", 20, 3).expect("synthetic clip"));
        check_mesh_levels_on_the_gpu(&rig, &[0.1]);
    }
);

#[test]
fn a_built_lod_persists_with_the_rig() {
    let mut rig = crowdmorph::embedded::default_rig();
    let progress = Progress::new();
    let spec = LodSpec {
        pinned: vec!["eyeBlink_L".into(), "eyeBlink_R".into()],
        mesh_fractions: vec![0.5, 0.25, 0.1],
        scoring: ScoreOptions {
            image_size: 128,
            ..ScoreOptions::default()
        },
        ..LodSpec::default()
    };
    let lod = build_lod(&rig, &spec, None, Some(&progress)).expect("lod");
    assert_eq!(progress.done(), progress.total());
    assert_eq!(progress.fraction(), 1.0);
    assert_eq!(lod.method, "combined+pinned");
    assert_eq!(lod.meshes.len(), 3);
    let meshes: Vec<Option<u32>> = lod.levels.iter().map(|l| l.mesh).collect();
    assert_eq!(meshes, vec![None, Some(0), Some(1), Some(2), Some(2)]);
    rig.lod = lod;
    rig.validate().expect("valid with its LOD");
    let json = serde_json::to_string(&rig).expect("serialize");
    let mut back: Rig = serde_json::from_str(&json).expect("deserialize");
    back.validate().expect("valid after a round trip");
    // Base colours are not serde fields (the store keeps them beside the primitives), so a
    // serde round trip gives glTF's white: compare everything else.
    let colors: Vec<[f32; 4]> = rig.primitives.iter().map(|p| p.base_color).collect();
    assert!(back.primitives.iter().all(|p| p.base_color == [1.0; 4]));
    for (p, c) in Arc::make_mut(&mut back.primitives).iter_mut().zip(colors) {
        p.base_color = c;
    }
    assert_eq!(back, rig);
    // A tampered mesh level is refused by the rig's own validation.
    let mut bad = back.clone();
    bad.lod.meshes[0].primitives[0].vertices.push(u32::MAX);
    assert!(bad.validate().is_err());

    let cancelled = Progress::new();
    cancelled.cancel();
    assert_eq!(
        build_lod(&rig, &LodSpec::default(), None, Some(&cancelled)),
        Err(LodBuildError::Cancelled)
    );
}

/// The embedded head with mesh levels at 50 and 25 % of its triangles (file order: no scoring).
fn head_with_mesh_levels() -> Arc<Rig> {
    let mut rig = crowdmorph::embedded::default_rig();
    let spec = LodSpec {
        method: OrderMethod::FileOrder,
        mesh_fractions: vec![0.5, 0.25],
        ..LodSpec::default()
    };
    rig.lod = build_lod(&rig, &spec, None, None).expect("lod");
    rig.validate().expect("valid");
    Arc::new(rig)
}

#[test]
fn mesh_levels_share_the_clip_tables_and_count_them_once() {
    let rig = head_with_mesh_levels();
    let prepared = Engine::cpu().prepare(rig.clone()).expect("prepare");
    assert_eq!(prepared.mesh_levels().len(), 2);
    let mut expected = rig.host_bytes() + prepared.cpu().bytes();
    for level in prepared.mesh_levels() {
        for (c, full) in level.rig().clips.iter().zip(&rig.clips) {
            assert!(
                Arc::ptr_eq(&c.weights, &full.weights),
                "mesh level copied clip {:?}",
                c.name
            );
        }
        expected += level.rig().geometry_bytes() + level.cpu().bytes();
    }
    // The clip tables are in the rig's bytes once, not again per level.
    assert_eq!(prepared.memory().host_bytes, expected);
    assert!(rig.clip_bytes() > 0);
}

gpu_test!(
    #[test]
    fn mesh_levels_share_one_device_buffer_of_clip_tables() {
        let rig = head_with_mesh_levels();
        let engine = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        let prepared = engine.prepare(rig).expect("prepare");
        let full = prepared.gpu().expect("resident");
        let mut expected = full.device_bytes();
        for level in prepared.mesh_levels() {
            let g = level.gpu().expect("resident");
            assert!(
                Arc::ptr_eq(g.tables(), full.tables()),
                "a level has its own tables"
            );
            expected += g.geometry_bytes();
        }
        assert_eq!(prepared.memory().device_bytes as u64, expected);
    }
);

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn indexed_displacements_equal_the_scan_on_real_rigs() {
    // Scoring, motion peaks and reports gather every target through the index; what they
    // gather must be exactly what the per-target scan gathers, bit for bit.
    for rig in [ict(), &morph_stress_test()] {
        let offsets = rig.vertex_offsets();
        let index = SparseIndex::new(rig);
        let bits = |d: &[Vec3]| -> Vec<u32> {
            d.iter()
                .flat_map(|x| x.to_array().map(f32::to_bits))
                .collect()
        };
        let mut moved = 0;
        for t in 0..rig.targets.len() as u32 {
            let (v, d) = index.displacement(rig, t);
            let (sv, sd) = target_displacement(rig, &offsets, t);
            assert_eq!(v, sv, "{}: target {t}", rig.name);
            assert_eq!(bits(&d), bits(&sd), "{}: target {t}", rig.name);
            moved += usize::from(!v.is_empty());
        }
        assert!(moved > 0, "{}: targets move vertices", rig.name);
    }
}

/// Positions of a PCA form at weights `w`: its derived rig's f64 oracle at `w`'s coefficients.
fn form_oracle(form: &crowdmorph::rig::DeltaPca, derived: &Rig, w: &[f32]) -> Vec<glam::DVec3> {
    let coefs: Vec<f64> = form.coefficients(w).iter().map(|&x| f64::from(x)).collect();
    rig_oracle(derived, &coefs).0
}

/// The positions of `job` on `prepared` through the engine (its LOD level's routing).
fn engine_positions(
    engine: &Engine,
    prepared: &crowdmorph::engine::PreparedRig,
    job: BlendJob,
) -> Vec<f32> {
    let spec = OutputSpec {
        normals: true,
        precision: Precision::F32,
    };
    engine
        .evaluate(prepared, &[job], spec)
        .expect("evaluate")
        .output
        .job_positions(0)
}

#[test]
fn pca_levels_are_used_where_they_pay_and_stay_within_their_budget() {
    use crowdmorph::lod::pca;
    use crowdmorph::rig::Pose;
    let mut rig = crowdmorph::embedded::default_rig();
    let spec = LodSpec {
        method: OrderMethod::FileOrder,
        ..LodSpec::default()
    };
    let lod = build_lod(&rig, &spec, None, None).expect("lod");
    let n = rig.targets.len() as u32;
    assert!(lod.levels[0].pca.is_none(), "level 0 stays exact");
    assert!(
        !lod.pca.is_empty(),
        "the embedded head's coarse levels pay: {:?}",
        lod.levels
    );
    // Every level that names a form gains by the cost model; every other full-mesh level does
    // not.
    for l in &lod.levels[1..] {
        let error = pca::level_error(&rig, &lod.order, l.shapes);
        let (madds, bytes) = (
            pca::level_madds(&rig, &lod.order, l.shapes),
            pca::level_bytes(&rig, &lod.order, l.shapes),
        );
        match l.pca {
            Some(p) => {
                let form = &lod.pca[p as usize];
                assert!(pca::pays(form, madds, bytes), "{l:?}");
                assert!((f64::from(form.max_error) - error).abs() <= 1e-6 * error.max(1e-6));
            }
            None if l.shapes < n && error > f64::from(crowdmorph::lod::PCA_FLOOR) => {
                assert!(
                    !pca::pays(&pca::build(&rig, error as f32), madds, bytes),
                    "{l:?}"
                );
            }
            None => {}
        }
    }
    rig.lod = lod;
    rig.validate().expect("valid with its PCA levels");
    let diag = f64::from(rig.bbox().diagonal());
    let engine = Engine::cpu();
    let prepared = engine.prepare(Arc::new(rig.clone())).expect("prepare");
    // The cost model counts the PCA levels' rigs, clip tables and forms.
    let cost = crowdmorph::rig::RigShape::of(&rig).cost(false);
    assert!(
        cost.resident() >= prepared.memory().host_bytes as u64,
        "{} < {}",
        cost.resident(),
        prepared.memory().host_bytes
    );
    let mut checked = 0;
    for (level, l) in rig.lod.levels.iter().enumerate() {
        let Some(p) = l.pca else { continue };
        let form = &rig.lod.pca[p as usize];
        let derived = form.derive_rig(&rig).expect("derived");
        let budget = f64::from(form.max_error) * diag;
        let mut poses: Vec<(Pose, Vec<f32>)> = Vec::new();
        for (c, clip) in rig.clips.iter().enumerate() {
            for frame in [0, clip.frames / 2, clip.frames - 1] {
                let mut w = vec![0f32; rig.targets.len()];
                clip.frame_weights(frame, &mut w);
                poses.push((
                    Pose::Frame {
                        clip: c as u32,
                        frame,
                    },
                    w,
                ));
            }
        }
        // A shape alone at 1 (a test pose), sent as live weights.
        let mut w = vec![0f32; rig.targets.len()];
        w[rig.lod.order[n as usize - 1] as usize] = 1.0;
        poses.push((Pose::live(&w), w));
        // A blend of two frames: weight-space, so coefficient-space.
        let (a, b) = (&rig.clips[0], &rig.clips[1]);
        let mut wa = vec![0f32; rig.targets.len()];
        let mut wb = wa.clone();
        a.frame_weights(3, &mut wa);
        b.frame_weights(5, &mut wb);
        let t = 0.25f32;
        let wt: Vec<f32> = wa
            .iter()
            .zip(&wb)
            .map(|(x, y)| (1.0 - t) * x + t * y)
            .collect();
        poses.push((Pose::blend((0, 3), &[(1, 5, t)]), wt));
        for (pose, w) in poses {
            let got = engine_positions(&engine, &prepared, BlendJob::posed(pose, level as u32));
            // Against the derived rig's f64 oracle: the engine evaluates the form exactly.
            let err = max_abs_diff(&got, &form_oracle(form, &derived, &w));
            assert!(
                err <= 2e-5 * diag,
                "level {level}: {err} vs the form's oracle"
            );
            // Against the exact rig: within the level's budget (test poses; a blend of two
            // is within it by the triangle inequality).
            let w64: Vec<f64> = w.iter().map(|&x| f64::from(x)).collect();
            let (exact, _) = rig_oracle(&rig, &w64);
            let err = max_abs_diff(&got, &exact);
            let allowed = budget + 2e-5 * diag;
            assert!(err <= allowed, "level {level}: {err} > {allowed}");
            checked += 1;
        }
    }
    assert!(checked > 0);

    // A clip added later reaches the PCA levels too (their tables are the clips mapped into
    // their coefficients), with the geometry kept.
    let mut more = rig.clone();
    let k = rig.targets.len();
    let table: Vec<f32> = (0..k * 4)
        .map(|i| ((i * 37) % 100) as f32 / 100.0)
        .collect();
    more.clips
        .push(crowdmorph::rig::Clip::new("late", 30.0, k, 4, table).expect("clip"));
    let c = (more.clips.len() - 1) as u32;
    let updated = engine
        .update_clips(&prepared, Arc::new(more.clone()))
        .expect("update");
    for (level, l) in more.lod.levels.iter().enumerate() {
        let Some(p) = l.pca else { continue };
        let form = &more.lod.pca[p as usize];
        let derived = form.derive_rig(&more).expect("derived");
        let mut w = vec![0f32; k];
        more.clips[c as usize].frame_weights(2, &mut w);
        let got = engine_positions(&engine, &updated, BlendJob::frame(c, 2, level as u32));
        let err = max_abs_diff(&got, &form_oracle(form, &derived, &w));
        assert!(err <= 2e-5 * diag, "level {level} after a clip: {err}");
    }
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (or CROWDMORPH_TEST_DATA)"
)]
fn pca_levels_pay_on_ict_facekits_coarse_levels() {
    use crowdmorph::lod::pca;
    let mut rig = ict().clone();
    let spec = LodSpec {
        method: OrderMethod::FileOrder,
        ..LodSpec::default()
    };
    rig.lod = build_lod(&rig, &spec, None, None).expect("lod");
    // 53 dense-ish FACS shapes: every coarse full-mesh level is cheaper as regional PCA.
    let with: Vec<usize> = (1..rig.lod.levels.len())
        .filter(|&l| rig.lod.levels[l].pca.is_some())
        .collect();
    assert!(with.len() >= 2, "{:?}", rig.lod.levels);
    let diag = f64::from(rig.bbox().diagonal());
    let engine = Engine::cpu();
    let prepared = engine.prepare(Arc::new(rig.clone())).expect("prepare");
    for l in with {
        let form = &rig.lod.pca[rig.lod.levels[l].pca.expect("pca") as usize];
        let shapes = rig.lod.levels[l].shapes;
        assert!(form.madds_per_head() * 2 < pca::level_madds(&rig, &rig.lod.order, shapes));
        // A shape alone at 1, live: within the level's error of the exact rig.
        let t = rig.lod.order[rig.targets.len() - 1] as usize;
        let mut w = vec![0f32; rig.targets.len()];
        w[t] = 1.0;
        let got = engine_positions(
            &engine,
            &prepared,
            BlendJob::posed(crowdmorph::rig::Pose::live(&w), l as u32),
        );
        let w64: Vec<f64> = w.iter().map(|&x| f64::from(x)).collect();
        let (exact, _) = rig_oracle(&rig, &w64);
        let err = max_abs_diff(&got, &exact);
        let allowed = f64::from(form.max_error) * diag + 2e-5 * diag;
        assert!(err <= allowed, "level {l}: {err} > {allowed}");
    }
}

#[test]
fn the_lod_report_states_the_joints_each_level_holds_at_rest() {
    // The skinned face: its far levels hold the eyes at rest. What that costs is measured
    // over a clip with the CPU engine and stays within the bound the levels were cut by.
    let rig = crowdmorph::synthetic::skinned_head();
    let talk = rig.clip_index("talk").expect("talk");
    let levels = crowdmorph::lod::report::joint_levels(&rig, talk).expect("joint levels");
    assert_eq!(levels.len(), rig.lod.levels.len());
    assert!(levels[0].dropped.is_empty() && levels[0].measured == 0.0);
    let last = levels.last().expect("a level");
    assert!(
        last.dropped.contains(&"LeftEye".to_string())
            && last.dropped.contains(&"RightEye".to_string()),
        "{last:?}"
    );
    for l in &levels {
        assert!(!l.dropped.contains(&"Head".to_string()), "{l:?}");
        assert!(
            l.measured <= l.bound * 1.001 + 1e-9,
            "level {}: measured {} over its bound {}",
            l.level,
            l.measured,
            l.bound
        );
        if !l.dropped.is_empty() {
            assert!(l.measured > 0.0, "the eyes move in `talk`: {l:?}");
        }
    }
    // The report's text says so.
    let pins: Vec<u32> = Vec::new();
    let opts = ScoreOptions {
        image_size: 48,
        ..Default::default()
    };
    let scores = score_targets(&rig, &opts, None).expect("scores");
    let report = lod_report(&rig, talk, &scores, &pins).expect("report");
    let text = report.to_string();
    assert!(text.contains("joints held at rest"), "{text}");
    assert!(text.contains("LeftEye"), "{text}");
}

/// MorphPrimitivesTest (from ../shared/data): two primitives, two materials, one border.
fn morph_primitives_test() -> Rig {
    load_path(
        &rig_file("MorphPrimitivesTest.gltf"),
        &ImportOptions::default(),
    )
    .expect("MorphPrimitivesTest loads")
}

/// The mesh levels the project's LOD builder makes for `rig`: the 50/25/10 % meshes an upload
/// gets (file order: no scoring, which the meshes do not depend on).
fn built_mesh_levels(rig: &Rig) -> Vec<MeshLevel> {
    let spec = LodSpec {
        method: OrderMethod::FileOrder,
        mesh_fractions: vec![0.5, 0.25, 0.1],
        ..LodSpec::default()
    };
    let meshes = build_lod(rig, &spec, None, None).expect("lod").meshes;
    assert_eq!(meshes.len(), 3, "{}", rig.name);
    meshes
}

/// One primitive: positions, texture coordinates (set 0), triangles.
type TexturedMesh = (Vec<Vec3>, Vec<Vec2>, Vec<u32>);

/// A rig of one primitive per mesh, each with one target that lifts its upper half (so motion
/// attributes take part beside the UVs) and a random clip.
fn textured_rig(name: &str, meshes: Vec<TexturedMesh>) -> Rig {
    let primitives = meshes
        .into_iter()
        .enumerate()
        .map(|(i, (positions, uv, indices))| {
            let lift: Vec<Vec3> = positions
                .iter()
                .map(|p| Vec3::Y * 0.2 * p.y.max(0.0))
                .collect();
            let target = sparsify(0, &lift, None, None, 1e-6);
            Primitive {
                name: format!("p{i}"),
                normals: vertex_normals(&positions, &indices),
                positions,
                normals_from_file: false,
                tangents: None,
                indices,
                targets: if target.vertices.is_empty() {
                    Vec::new()
                } else {
                    vec![target]
                },
                base_color: Primitive::default_base_color(),
                skin: None,
                look: VertexLook {
                    uv0: Some(uv),
                    ..VertexLook::default()
                },
            }
        })
        .collect();
    let mut rng = crate::util::Rng(46);
    let rig = crate::util::rig_with_random_clip(name.into(), primitives, 1, 4, 3, &mut rng);
    rig.validate().expect("valid textured rig");
    rig
}

/// A UV sphere cut into `charts` charts along meridians, like a texture atlas: each chart has
/// its own vertices (its own poles too), so where two charts meet the positions are the same,
/// bit for bit, and the texture coordinates are not (the charts lie apart in UV space).
fn seamed_sphere(rings: u32, columns: u32, charts: u32) -> TexturedMesh {
    let m = columns * charts;
    let at = |i: u32, j: u32| {
        let th = std::f32::consts::PI * j as f32 / rings as f32;
        let ph = std::f32::consts::TAU * (i % m) as f32 / m as f32;
        Vec3::new(th.sin() * ph.cos(), th.cos(), th.sin() * ph.sin())
    };
    let (mut positions, mut uv, mut indices) = (Vec::new(), Vec::new(), Vec::new());
    for c in 0..charts {
        let base = positions.len() as u32;
        // Chart c spans columns c·columns ..= (c+1)·columns, with a gap in u to the next one.
        let u = |k: u32| (c as f32 * 1.25 + k as f32 / columns as f32) / (charts as f32 * 1.25);
        let v = |j: u32| j as f32 / rings as f32;
        positions.push(at(0, 0));
        uv.push(Vec2::new(u(columns / 2), 0.0));
        for j in 1..rings {
            for k in 0..=columns {
                positions.push(at(c * columns + k, j));
                uv.push(Vec2::new(u(k), v(j)));
            }
        }
        let south = positions.len() as u32;
        positions.push(at(0, rings));
        uv.push(Vec2::new(u(columns / 2), 1.0));
        let idx = |k: u32, j: u32| base + 1 + (j - 1) * (columns + 1) + k;
        for k in 0..columns {
            indices.extend([base, idx(k + 1, 1), idx(k, 1)]);
            for j in 1..rings - 1 {
                let (a, b) = (idx(k, j), idx(k + 1, j));
                let (c2, d) = (idx(k + 1, j + 1), idx(k, j + 1));
                indices.extend([a, b, c2, a, c2, d]);
            }
            indices.extend([south, idx(k, rings - 1), idx(k + 1, rings - 1)]);
        }
    }
    (positions, uv, indices)
}

/// A gently waved grid of `n × n` quads over [0, 1]², split at column `n / 2` into two
/// primitives (two materials) that both have that column's vertices, at bit-equal positions.
fn split_grid(n: u32) -> Vec<TexturedMesh> {
    let at = |i: u32, j: u32| {
        let (x, y) = (i as f32 / n as f32, j as f32 / n as f32);
        Vec3::new(x, y, 0.02 * (3.0 * x).sin() * (2.0 * y).cos())
    };
    [(0, n / 2), (n / 2, n)]
        .into_iter()
        .map(|(i0, i1)| {
            let w = i1 - i0 + 1;
            let (mut positions, mut uv, mut indices) = (Vec::new(), Vec::new(), Vec::new());
            for j in 0..=n {
                for i in i0..=i1 {
                    positions.push(at(i, j));
                    uv.push(Vec2::new(i as f32 / n as f32, j as f32 / n as f32));
                }
            }
            for j in 0..n {
                for k in 0..w - 1 {
                    let a = j * w + k;
                    indices.extend([a, a + 1, a + w + 1, a, a + w + 1, a + w]);
                }
            }
            (positions, uv, indices)
        })
        .collect()
}

/// UV charts of a primitive: connected components of its triangles, joined where they share a
/// vertex index. A seam's two sides are different vertices at one position, so charts part
/// there. Returns each vertex's chart (its component's smallest vertex) and the chart count.
fn uv_charts(p: &Primitive) -> (Vec<u32>, usize) {
    let mut parent: Vec<u32> = (0..p.positions.len() as u32).collect();
    fn find(parent: &mut [u32], mut x: u32) -> u32 {
        while parent[x as usize] != x {
            parent[x as usize] = parent[parent[x as usize] as usize];
            x = parent[x as usize];
        }
        x
    }
    for t in p.indices.chunks_exact(3) {
        for (a, b) in [(t[0], t[1]), (t[1], t[2])] {
            let (ra, rb) = (find(&mut parent, a), find(&mut parent, b));
            parent[ra.max(rb) as usize] = ra.min(rb);
        }
    }
    let roots: Vec<u32> = (0..parent.len() as u32)
        .map(|v| find(&mut parent, v))
        .collect();
    let used: std::collections::HashSet<u32> =
        p.indices.iter().map(|&v| roots[v as usize]).collect();
    (roots, used.len())
}

/// Every level's texture coordinates are its source vertices' own, exactly: `look.uv0[k]` of
/// the derived rig is the full primitive's `uv0[vertices[k]]`, bit for bit. Returns the
/// largest difference seen (0) and the level vertices checked.
fn check_level_uvs(rig: &Rig, levels: &[MeshLevel]) -> (f32, usize) {
    let (mut worst, mut checked) = (0.0f32, 0);
    for level in levels {
        let derived = level.derive_rig(rig).expect("derived rig");
        for ((full, l), d) in rig
            .primitives
            .iter()
            .zip(&level.primitives)
            .zip(derived.primitives.iter())
        {
            let src = full.look.uv0.as_ref().expect("the source has TEXCOORD_0");
            let got = d.look.uv0.as_ref().expect("the level keeps TEXCOORD_0");
            assert_eq!(got.len(), l.vertices.len(), "{}", derived.name);
            for (k, &v) in l.vertices.iter().enumerate() {
                let want = src[v as usize];
                assert_eq!(
                    got[k].to_array().map(f32::to_bits),
                    want.to_array().map(f32::to_bits),
                    "{}: level vertex {k} (source {v})",
                    derived.name
                );
                worst = worst.max((got[k] - want).abs().max_element());
                checked += 1;
            }
        }
    }
    (worst, checked)
}

/// No level triangle joins two UV charts of the full mesh. Returns the triangles checked.
fn check_level_charts(rig: &Rig, levels: &[MeshLevel]) -> usize {
    let charts: Vec<Vec<u32>> = rig.primitives.iter().map(|p| uv_charts(p).0).collect();
    let mut checked = 0;
    for level in levels {
        for (pi, l) in level.primitives.iter().enumerate() {
            for t in l.indices.chunks_exact(3) {
                let t = [t[0], t[1], t[2]];
                let c = t.map(|k| charts[pi][l.vertices[k as usize] as usize]);
                assert!(
                    c[0] == c[1] && c[1] == c[2],
                    "{} at {} %: primitive {pi} triangle {:?} spans charts {c:?}",
                    rig.name,
                    level.triangle_fraction * 100.0,
                    t.map(|k| l.vertices[k as usize])
                );
                checked += 1;
            }
        }
    }
    checked
}

/// Per primitive, the vertices on its open border (an edge of one triangle) at a position some
/// other primitive also has: where two materials meet. Computed here on its own, not with the
/// library's helper.
fn shared_border(rig: &Rig) -> Vec<Vec<u32>> {
    use std::collections::HashMap;
    let key = |v: Vec3| (v + Vec3::ZERO).to_array().map(f32::to_bits);
    rig.primitives
        .iter()
        .enumerate()
        .map(|(pi, p)| {
            let mut uses: HashMap<(u32, u32), u32> = HashMap::new();
            for t in p.indices.chunks_exact(3) {
                for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                    *uses.entry((a.min(b), a.max(b))).or_default() += 1;
                }
            }
            let mut open: Vec<u32> = uses
                .iter()
                .filter(|&(_, &n)| n == 1)
                .flat_map(|(&(a, b), _)| [a, b])
                .collect();
            open.sort_unstable();
            open.dedup();
            open.retain(|&v| {
                let k = key(p.positions[v as usize]);
                rig.primitives
                    .iter()
                    .enumerate()
                    .any(|(qi, q)| qi != pi && q.positions.iter().any(|&w| key(w) == k))
            });
            open
        })
        .collect()
}

/// Every shared border vertex is kept (so it does not move) at every level. Returns how many
/// were checked.
fn check_level_borders(rig: &Rig, levels: &[MeshLevel]) -> usize {
    let border = shared_border(rig);
    let mut checked = 0;
    for level in levels {
        for (pi, (l, b)) in level.primitives.iter().zip(&border).enumerate() {
            for &v in b {
                assert!(
                    l.vertices.binary_search(&v).is_ok(),
                    "{} at {} %: primitive {pi} lost border vertex {v} (of {})",
                    rig.name,
                    level.triangle_fraction * 100.0,
                    b.len()
                );
                checked += 1;
            }
        }
    }
    checked
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn mesh_levels_keep_each_vertex_s_texture_coordinates_on_real_rigs() {
    for rig in [morph_stress_test(), morph_primitives_test()] {
        let levels = built_mesh_levels(&rig);
        assert!(
            levels[2].vertex_count() < rig.vertex_count(),
            "{} simplifies",
            rig.name
        );
        let (worst, checked) = check_level_uvs(&rig, &levels);
        assert_eq!(worst, 0.0, "{}", rig.name);
        assert!(checked > 0, "{}", rig.name);
    }
}

#[test]
fn mesh_levels_never_collapse_across_a_uv_seam_of_a_sphere() {
    let rig = textured_rig("seamed-sphere", vec![seamed_sphere(16, 8, 4)]);
    assert_eq!(uv_charts(&rig.primitives[0]).1, 4, "four charts");
    let levels = built_mesh_levels(&rig);
    assert!(levels[2].triangle_count() * 5 < rig.triangle_count());
    assert!(check_level_charts(&rig, &levels) > 0);
    check_level_uvs(&rig, &levels);
    // A seam is topology, not a cost: it holds with no UVs in the quadric, down to a few
    // triangles per chart.
    check_level_charts(&rig, &levels_without_uv_cost(&rig, &[0.25, 0.1, 0.05]));
}

/// Mesh levels of `rig` simplified with texture coordinates left out of the quadric.
fn levels_without_uv_cost(rig: &Rig, fractions: &[f32]) -> Vec<MeshLevel> {
    let opts = SimplifyOptions {
        uv_weight: 0.0,
        ..SimplifyOptions::default()
    };
    build_mesh_levels(rig, fractions, &opts, None)
        .expect("levels")
        .0
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn mesh_levels_never_collapse_across_a_uv_seam_on_morph_stress_test() {
    let rig = morph_stress_test();
    let charts = uv_charts(&rig.primitives[1]).1;
    assert!(charts > 1, "{charts} charts: the test would prove nothing");
    let levels = built_mesh_levels(&rig);
    assert!(check_level_charts(&rig, &levels) > 0);
    check_level_charts(&rig, &levels_without_uv_cost(&rig, &[0.25, 0.1, 0.05]));
}

#[test]
fn mesh_levels_keep_the_border_between_two_materials() {
    let rig = textured_rig("split-grid", split_grid(16));
    let (levels, features) =
        build_mesh_levels(&rig, &[0.5, 0.25, 0.1], &SimplifyOptions::default(), None)
            .expect("levels");
    assert_eq!(levels, built_mesh_levels(&rig), "the LOD builder's meshes");
    let border = shared_border(&rig);
    assert_eq!(
        border.iter().map(Vec::len).collect::<Vec<_>>(),
        vec![17, 17]
    );
    assert!(levels[2].triangle_count() * 5 < rig.triangle_count());
    assert_eq!(check_level_borders(&rig, &levels), 3 * 2 * 17);
    check_level_charts(&rig, &levels);
    // Feature points still win: every one is on every level.
    let map = levels[2].vertex_map(&rig.vertex_offsets());
    assert!(!features.vertices().is_empty());
    for v in features.vertices() {
        assert!(map.binary_search(&v).is_ok(), "feature vertex {v} removed");
    }
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn mesh_levels_keep_the_border_between_two_materials_on_morph_primitives_test() {
    let rig = morph_primitives_test();
    let levels = built_mesh_levels(&rig);
    assert!(levels[2].vertex_count() < rig.vertex_count());
    assert!(check_level_borders(&rig, &levels) > 0);
    check_level_charts(&rig, &levels);
}

#[test]
fn simplify_options_recorded_before_appearance_still_load() {
    let old = r#"{"facial_landmarks":true,"feature_image_size":512,"peak_fraction":0.95,
        "peaks_per_target":2,"priority_rings":2,"motion_targets":10,"motion_weight":1.0}"#;
    let opts: SimplifyOptions = serde_json::from_str(old).expect("an older record loads");
    assert_eq!(opts, SimplifyOptions::default());
    assert_eq!(opts.uv_weight, 0.5);
    assert!(opts.lock_material_borders);
}
