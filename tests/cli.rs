//! The `crowdmorph` command line, run as the real binary: one test per subcommand plus a bad
//! argument.
//!
//! The binary under test is built with debug assertions (the test profile), so clap checks each
//! subcommand's definition when it parses it: a mistake there panics here even when no unit test
//! parses that subcommand. Each test uses the embedded head (7,262 vertices, no files needed) or
//! a small generated rig, and small sizes and durations, so that it takes a few seconds on two
//! cores. Outputs are checked against the library evaluating the same thing in this process.

use crate::util::gpu_test;
use std::path::Path;
use std::process::{Command, Output};

use crowdmorph::engine::{BlendJob, Engine, OutputSpec};
use crowdmorph::server::ServerConfig;
use serde_json::Value;

use crate::server::{TestServer, temp_dir};

/// The embedded head's vertex count, as the README states it.
const EMBEDDED_VERTICES: usize = 7_262;

/// A command running the binary, with the environment variables its flags read removed, so a
/// developer's own settings do not change what the tests see.
fn crowdmorph(args: &[&str]) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_crowdmorph"));
    c.args(args)
        .env_remove("CROWDMORPH_BACKEND")
        .env_remove("CROWDMORPH_SERVER")
        .env_remove("CROWDMORPH_ADMIN_TOKEN")
        .env("RUST_LOG", "warn")
        .env("NO_COLOR", "1");
    c
}

/// Runs the command and requires exit status 0; returns its output.
fn success(mut command: Command) -> Output {
    let out = command.output().expect("run crowdmorph");
    assert!(
        out.status.success(),
        "{command:?} exited with {:?}\nstdout:\n{}\nstderr:\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Runs the binary with `args` (which include `--json`), requires success, and parses stdout.
fn json(args: &[&str]) -> Value {
    let out = success(crowdmorph(args));
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "{args:?}: stdout is not JSON ({e}):\n{}",
            String::from_utf8_lossy(&out.stdout)
        )
    })
}

fn f64_of(v: &Value, key: &str) -> f64 {
    v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("{key} is not a number in {v}"))
}

fn usize_of(v: &Value, key: &str) -> usize {
    v[key]
        .as_u64()
        .unwrap_or_else(|| panic!("{key} is not a whole number in {v}")) as usize
}

fn strings(v: &Value) -> Vec<String> {
    v.as_array()
        .unwrap_or_else(|| panic!("not an array: {v}"))
        .iter()
        .map(|s| s.as_str().expect("string").to_string())
        .collect()
}

fn path_str(p: &Path) -> &str {
    p.to_str().expect("temporary paths are UTF-8")
}

#[test]
fn inspect_describes_the_embedded_head_as_text_and_json() {
    let rig = crowdmorph::embedded::default_rig();
    assert_eq!(rig.vertex_count(), EMBEDDED_VERTICES);

    // Text, on the default backend, with Mesa's device-select layer free to complain: the
    // binary turns it off itself, so its XDG_RUNTIME_DIR message never appears.
    let mut command = crowdmorph(&["inspect"]);
    command
        .env_remove("NODEVICE_SELECT")
        .env_remove("XDG_RUNTIME_DIR");
    let out = success(command);
    let text = String::from_utf8(out.stdout).expect("UTF-8");
    let first = text.lines().next().expect("a first line");
    assert!(
        first.starts_with(&format!(
            "rig \"default-head\": {EMBEDDED_VERTICES} vertices, {} triangles, {} targets, {} clips",
            rig.triangle_count(),
            rig.targets.len(),
            rig.clips.len()
        )),
        "{text}"
    );
    for clip in &rig.clips {
        assert!(text.contains(&format!("  {:<24}", clip.name)), "{text}");
    }
    assert!(text.contains("LOD levels (shapes):") && text.contains("backend: "));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("XDG_RUNTIME_DIR"), "{stderr}");

    let s = json(&["inspect", "--json", "--backend", "cpu"]);
    assert_eq!(s["name"], "default-head");
    assert_eq!(usize_of(&s, "vertices"), EMBEDDED_VERTICES);
    assert_eq!(usize_of(&s, "triangles"), rig.triangle_count());
    assert_eq!(
        s["primitives"].as_array().expect("primitives").len(),
        rig.primitives.len()
    );
    let targets = s["targets"].as_array().expect("targets");
    assert_eq!(targets.len(), rig.targets.len());
    assert!(targets.iter().all(|t| usize_of(t, "nnz") > 0));
    let clips: Vec<&str> = s["clips"]
        .as_array()
        .expect("clips")
        .iter()
        .map(|c| c["name"].as_str().expect("name"))
        .collect();
    let want: Vec<&str> = rig.clips.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(clips, want);
    assert_eq!(s["backend"]["kind"], "cpu");
    assert!(usize_of(&s["memory"], "host_bytes") > 0);
    assert_eq!(usize_of(&s["memory"], "device_bytes"), 0);
    // Which adapter renders, or why none can.
    if cfg!(crowdmorph_gpu_driver) {
        let r = s["renderer"]
            .as_str()
            .expect("a renderer with a Vulkan driver");
        assert!(text.contains(&format!("renderer: {r}")), "{text}");
    } else {
        assert!(
            s["renderer"].is_string() || s["renderer_error"].is_string(),
            "{s}"
        );
        assert!(text.contains("renderer: "), "{text}");
    }
}

/// `inspect` of a skinned rig lists every node of its skeleton (what joint overrides may name)
/// and counts each bone once: the robot's four skins list the same 43 joints.
#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
fn inspect_lists_a_skeletons_nodes_and_counts_each_bone_once() {
    let path = crate::util::data_dir().join("robot-expressive/RobotExpressive.glb");
    let doc = crate::util::RefDoc::load(&path);
    let followed = crate::util::skin::followed_nodes(&doc.json);
    let s = json(&["inspect", path_str(&path), "--json", "--backend", "cpu"]);
    let k = &s["skeleton"];
    assert_eq!(usize_of(k, "bones"), followed.len(), "{k}");
    let names = strings(&k["node_names"]);
    assert_eq!(names.len(), usize_of(k, "nodes"));
    for n in &followed {
        let name = doc.json["nodes"][*n]["name"].as_str().expect("named");
        assert!(names.iter().any(|x| x == name), "{name}: {names:?}");
    }
    let text = String::from_utf8(success(crowdmorph(&["inspect", path_str(&path)])).stdout)
        .expect("UTF-8");
    let line = text
        .lines()
        .find(|l| l.trim_start().starts_with("nodes: "))
        .expect("a nodes line");
    assert_eq!(line.trim_start()["nodes: ".len()..], names.join(", "));
}

#[test]
fn eval_writes_obj_and_bin_files_of_the_frame_the_library_computes() {
    let dir = temp_dir("cli-eval");
    let (obj, bin) = (dir.join("head.obj"), dir.join("head.bin"));
    let common = ["eval", "--clip", "talk", "--frame", "12", "--lod", "1"];
    for out in [&obj, &bin] {
        let mut args = common.to_vec();
        args.extend(["--backend", "cpu", "--out", path_str(out)]);
        let done = success(crowdmorph(&args));
        let stderr = String::from_utf8_lossy(&done.stderr);
        assert!(
            stderr.contains(&format!("({EMBEDDED_VERTICES} vertices, clip \"talk\"")),
            "{stderr}"
        );
    }

    // What the library computes for the same frame.
    let rig = std::sync::Arc::new(crowdmorph::embedded::default_rig());
    let engine = Engine::cpu();
    let prepared = engine.prepare(rig.clone()).expect("prepare");
    let job = BlendJob::frame(rig.clip_index("talk").expect("talk") as u32, 12, 1);
    let want = engine
        .evaluate(&prepared, &[job], OutputSpec::default())
        .expect("evaluate")
        .output
        .job_positions(0);
    assert_eq!(want.len(), EMBEDDED_VERTICES * 3);

    // .bin: raw little-endian f32 xyz, exactly those positions.
    let bytes = std::fs::read(&bin).expect("read .bin");
    assert_eq!(bytes.len(), EMBEDDED_VERTICES * 12);
    let got: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    assert_eq!(got, want);

    // .obj: a vertex and a normal per vertex, every triangle, one object per primitive; the
    // vertices print the same f32 values (Rust prints floats so that they read back exactly).
    let text = std::fs::read_to_string(&obj).expect("read .obj");
    let count = |prefix: &str| text.lines().filter(|l| l.starts_with(prefix)).count();
    assert_eq!(count("v "), EMBEDDED_VERTICES);
    assert_eq!(count("vn "), EMBEDDED_VERTICES);
    assert_eq!(count("f "), rig.triangle_count());
    assert_eq!(count("o "), rig.primitives.len());
    let obj_positions: Vec<f32> = text
        .lines()
        .filter_map(|l| l.strip_prefix("v "))
        .flat_map(|l| l.split(' ').map(|x| x.parse::<f32>().expect("float")))
        .collect();
    assert_eq!(obj_positions, want);

    // Another extension is refused before anything is written.
    let bad = dir.join("head.txt");
    let mut args = common.to_vec();
    args.extend(["--out", path_str(&bad)]);
    let out = crowdmorph(&args).output().expect("run");
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("must end in .obj or .bin"));
    assert!(!bad.exists());
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn lod_order_ranks_every_target_of_the_embedded_head_with_pins_first() {
    let rig = crowdmorph::embedded::default_rig();
    let o = json(&[
        "lod",
        "order",
        "--size",
        "64",
        "--pin",
        "eyeBlink_R",
        "--json",
    ]);
    assert_eq!(o["rig"], "default-head");
    assert_eq!(o["method"], "combined");
    assert_eq!(strings(&o["pinned"]), ["eyeBlink_R"]);
    let order = strings(&o["order"]);
    assert_eq!(order[0], "eyeBlink_R");
    let mut sorted = order.clone();
    sorted.sort();
    let mut all = rig.targets.clone();
    all.sort();
    assert_eq!(sorted, all, "the order is a permutation of the targets");
    let metrics = o["metric_orders"].as_array().expect("metric orders");
    assert_eq!(metrics.len(), 5, "five metrics");
    for m in metrics {
        assert_eq!(strings(&m[1]).len(), rig.targets.len(), "{}", m[0]);
    }
    let seconds = f64_of(&o, "seconds");
    assert!(seconds > 0.0 && seconds < 60.0, "{seconds}");
}

#[test]
fn lod_report_gives_every_order_its_error_over_a_clip_and_a_plot() {
    let rig = crowdmorph::embedded::default_rig();
    let dir = temp_dir("cli-lod-report");
    let png = dir.join("report.png");
    let r = json(&[
        "lod",
        "report",
        "--clip",
        "talk",
        "--size",
        "64",
        "--out",
        path_str(&png),
        "--json",
    ]);
    assert_eq!(r["clip"], "talk");
    let talk = &rig.clips[rig.clip_index("talk").expect("talk")];
    assert_eq!(r["frames"].as_u64(), Some(u64::from(talk.frames)));
    assert_eq!(usize_of(&r, "vertices"), EMBEDDED_VERTICES);
    let orders = r["orders"].as_array().expect("orders");
    let methods: Vec<&str> = orders
        .iter()
        .map(|o| o["method"].as_str().expect("method"))
        .collect();
    assert!(
        methods.contains(&"combined") && methods.contains(&"file-order"),
        "{methods:?}"
    );
    for o in orders {
        let levels = o["levels"].as_array().expect("levels");
        assert_eq!(levels.len(), rig.lod.levels.len());
        // Level 0 keeps every shape: no error. The last keeps none: some.
        assert_eq!(f64_of(&levels[0], "max"), 0.0, "{o}");
        let last = levels.last().expect("a level");
        assert!(f64_of(last, "rms") > 0.0 && f64_of(last, "max") >= f64_of(last, "rms"));
    }
    let bytes = std::fs::read(&png).expect("the plot");
    assert!(bytes.starts_with(b"\x89PNG\r\n\x1a\n"));
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn lod_mesh_builds_smaller_levels_that_keep_the_feature_points() {
    let rig = crowdmorph::embedded::default_rig();
    let dir = temp_dir("cli-lod-mesh");
    let m = json(&[
        "lod",
        "mesh",
        "--fractions",
        "0.5,0.25",
        "--obj-dir",
        path_str(&dir),
        "--json",
    ]);
    let full = m["full"].as_array().expect("full");
    assert_eq!(full[0].as_u64(), Some(EMBEDDED_VERTICES as u64));
    assert_eq!(full[1].as_u64(), Some(rig.triangle_count() as u64));
    let f = &m["features"];
    let mut features: Vec<u64> = f["landmarks"]
        .as_array()
        .expect("landmarks")
        .iter()
        .map(|l| l["vertex"].as_u64().expect("vertex"))
        .chain(
            f["lip_line"]
                .as_array()
                .expect("lip line")
                .iter()
                .map(|v| v.as_u64().expect("vertex")),
        )
        .chain(
            f["motion_peaks"]
                .as_array()
                .expect("peaks")
                .iter()
                .map(|v| v.as_u64().expect("vertex")),
        )
        .collect();
    features.sort_unstable();
    features.dedup();
    assert!(!features.is_empty());
    let levels = m["levels"].as_array().expect("levels");
    assert_eq!(levels.len(), 2);
    let mut previous = EMBEDDED_VERTICES;
    for (level, (fraction, name)) in levels.iter().zip([(0.5, "mesh_50"), (0.25, "mesh_25")]) {
        assert_eq!(f64_of(level, "fraction"), fraction);
        let (vertices, triangles) = (usize_of(level, "vertices"), usize_of(level, "triangles"));
        assert!(vertices < previous, "{level}");
        previous = vertices;
        let asked = fraction * rig.triangle_count() as f64;
        assert!(
            (triangles as f64) < asked * 1.1,
            "{triangles} triangles for {fraction}"
        );
        assert_eq!(usize_of(level, "features_kept"), features.len());
        // Each level's neutral mesh as OBJ, and a render of it.
        let obj = std::fs::read_to_string(dir.join(format!("{name}.obj"))).expect("obj");
        assert_eq!(
            obj.lines().filter(|l| l.starts_with("v ")).count(),
            vertices
        );
        assert_eq!(
            obj.lines().filter(|l| l.starts_with("f ")).count(),
            triangles
        );
        let png = std::fs::read(dir.join(format!("{name}.png"))).expect("png");
        assert!(png.starts_with(b"\x89PNG"));
    }
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn bench_cpu_reports_plausible_json() {
    let r = json(&[
        "bench",
        "cpu",
        "--heads",
        "20",
        "--unique",
        "10",
        "--batches",
        "1,3,10",
        "--mesh-fractions",
        "0.5",
        "--seconds",
        "0.05",
        "--json",
    ]);
    assert_eq!(usize_of(&r, "vertices"), EMBEDDED_VERTICES);
    assert_eq!(usize_of(&r, "targets"), 51);
    assert_eq!((usize_of(&r, "heads"), usize_of(&r, "unique")), (20, 10));
    assert_eq!(r["precision"], "f32");
    for key in [
        "eval_ms",
        "crowd_ms",
        "unique_heads_per_s",
        "heads_per_s",
        "dense_baseline_ms",
        "dense_gemm_ms",
        "dense_matrixmultiply_ms",
        "memcpy_ms",
        "speedup_vs_dense",
        "one_head_ms",
    ] {
        let v = f64_of(&r, key);
        assert!(v.is_finite() && v > 0.0, "{key} = {v}");
    }
    // The roofline terms are measured, and the kernel cannot beat its own FMA bound.
    let machine = &r["machine"];
    assert!(f64_of(machine, "fma_peak_gflops") > 0.0 && f64_of(machine, "copy_gb_per_s") > 0.0);
    let roof = &r["roofline"];
    assert!(f64_of(roof, "useful_gflop") <= f64_of(roof, "sparse_gflop"));
    assert!(f64_of(roof, "sparse_gflop") <= f64_of(roof, "dense_gflop"));
    assert_eq!(usize_of(roof, "output_bytes"), 10 * EMBEDDED_VERTICES * 12);
    // Every wire format, at its size.
    let formats: Vec<(String, usize)> = r["formats"]
        .as_array()
        .expect("formats")
        .iter()
        .map(|f| {
            (
                f["format"].as_str().expect("name").to_string(),
                usize_of(f, "bytes_per_head"),
            )
        })
        .collect();
    let v3 = EMBEDDED_VERTICES * 3;
    assert_eq!(
        formats,
        [
            ("f32".into(), v3 * 4),
            ("f16".into(), v3 * 2),
            ("q16".into(), v3 * 2)
        ]
    );
    let batches: Vec<usize> = r["batches"]
        .as_array()
        .expect("batches")
        .iter()
        .map(|b| usize_of(b, "unique"))
        .collect();
    assert_eq!(batches, [1, 3, 10]);
    // The simplified mesh's output shrinks with its vertices.
    let meshes = r["mesh_levels"].as_array().expect("mesh levels");
    assert_eq!(meshes.len(), 1);
    let m = &meshes[0];
    assert!(usize_of(m, "vertices") < EMBEDDED_VERTICES);
    assert_eq!(
        usize_of(m, "output_bytes"),
        10 * usize_of(m, "vertices") * 12
    );
    // Ten unique heads evaluate in well under a second on any machine this runs on.
    assert!(f64_of(&r, "eval_ms") < 1000.0, "{r}");
    let scaling = r["lod_scaling"].as_array().expect("lod scaling");
    assert!(!scaling.is_empty());
    assert_eq!(usize_of(&scaling[0], "shapes"), 51);
    assert_eq!(f64_of(&scaling[0], "delta_fraction"), 1.0);
}

gpu_test!(
    #[test]
    fn bench_gpu_measures_the_scenes_on_a_gpu_and_the_cpu() {
        // `bench gpu` always includes the paper-scale rig unless told not to, and that takes
        // seconds per scene on lavapipe: a tiny generated rig keeps this fast. `--backend gpu`
        // (the default) takes software adapters such as lavapipe; auto would not.
        let dir = temp_dir("cli-bench-gpu");
        let rig = dir.join("triangle.glb");
        std::fs::write(&rig, crate::util::builder::triangle_rig().to_glb()).expect("write rig");
        let plot = dir.join("gpu.png");
        let reports = json(&[
            "bench",
            "gpu",
            "--backend",
            "gpu",
            "--no-paper",
            "--rig",
            path_str(&rig),
            "--seconds",
            "0.01",
            "--with-cpu",
            "--plot",
            path_str(&plot),
            "--json",
        ]);
        let reports = reports.as_array().expect("one report per engine");
        assert_eq!(reports.len(), 2);
        assert_eq!(
            reports[0]["backend"]["kind"], "gpu",
            "{}",
            reports[0]["backend"]
        );
        assert_eq!(reports[0]["backend"]["degraded"], false);
        assert_eq!(reports[1]["backend"]["kind"], "cpu");
        for r in reports {
            let scenes = r["scenes"].as_array().expect("scenes");
            let names: Vec<&str> = scenes
                .iter()
                .map(|s| s["scene"].as_str().expect("scene"))
                .collect();
            for (scene, _, _) in crowdmorph::bench::gpu::SCENES {
                assert!(names.contains(&scene), "{scene} missing: {names:?}");
            }
            for s in scenes {
                assert!(
                    f64_of(s, "round_trip_ms") > 0.0 && f64_of(s, "heads_per_s") > 0.0,
                    "{s}"
                );
            }
        }
        assert!(std::fs::read(&plot).expect("plot").starts_with(b"\x89PNG"));
        let _ = std::fs::remove_dir_all(dir);
    }
);

/// Counts pixels of a PNG that are not the default background.
fn drawn_pixels(img: &crate::util::image::Image) -> usize {
    let bg = crowdmorph_proto::DEFAULT_BACKGROUND;
    img.rgba
        .chunks_exact(4)
        .filter(|p| p[..3] != bg[..])
        .count()
}

gpu_test!(
    #[test]
    fn render_writes_a_picture_of_a_crowd_of_the_embedded_head() {
        let dir = temp_dir("cli-render");
        let out = dir.join("crowd.png");
        let report = json(&[
            "render",
            "--clip",
            "talk",
            "--frame",
            "12",
            "--heads",
            "4",
            "--spread",
            "--width",
            "160",
            "--height",
            "120",
            "--out",
            path_str(&out),
            "--json",
        ]);
        assert_eq!(usize_of(&report, "heads"), 4);
        assert_eq!(
            usize_of(&report, "unique"),
            4,
            "--spread: one frame per head"
        );
        assert!(report["adapter"].as_str().is_some_and(|a| !a.is_empty()));
        let img = crate::util::image::Image::read_png(&out).expect("a PNG");
        assert_eq!((img.width, img.height), (160, 120));
        let drawn = drawn_pixels(&img);
        assert!(
            drawn > 160 * 120 / 10,
            "only {drawn} pixels are not background"
        );
        // The corner is background: the crowd is framed, not cut.
        let bg = crowdmorph_proto::DEFAULT_BACKGROUND;
        assert_eq!(img.pixel(0, 0), [bg[0], bg[1], bg[2], 255]);
        // Clones by default; the format follows the extension.
        let jpeg = dir.join("crowd.jpg");
        let report = json(&[
            "render",
            "--heads",
            "3",
            "--width",
            "64",
            "--height",
            "48",
            "--out",
            path_str(&jpeg),
            "--json",
        ]);
        assert_eq!(usize_of(&report, "unique"), 1);
        assert_eq!(report["format"], "jpeg");
        assert!(
            std::fs::read(&jpeg)
                .expect("jpeg")
                .starts_with(&[0xFF, 0xD8])
        );
        let _ = std::fs::remove_dir_all(dir);
    }
);

#[test]
fn render_without_a_vulkan_driver_says_what_to_install() {
    // No Vulkan driver to load and no other backend: nothing can render.
    let dir = temp_dir("cli-render-none");
    let out = dir.join("crowd.png");
    let mut c = crowdmorph(&["render", "--out", path_str(&out)]);
    c.env("VK_DRIVER_FILES", dir.join("none.json"))
        .env_remove("VK_ICD_FILENAMES")
        .env_remove("VK_ADD_DRIVER_FILES")
        .env("WGPU_BACKEND", "vulkan");
    let o = c.output().expect("run crowdmorph");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "rendered without a driver? {stderr}");
    assert!(stderr.contains("mesa-vulkan-drivers"), "{stderr}");
    assert!(!out.exists(), "no file is written when nothing renders");
    let _ = std::fs::remove_dir_all(dir);
}

gpu_test!(
    #[test]
    fn bench_render_reports_each_stage() {
        let r = json(&[
            "bench",
            "render",
            "--heads",
            "4",
            "--width",
            "64",
            "--height",
            "48",
            "--seconds",
            "0",
            "--json",
        ]);
        assert_eq!(usize_of(&r, "heads"), 4);
        assert_eq!(usize_of(&r, "unique"), 4, "every head a different frame");
        assert!(usize_of(&r, "runs") >= 5);
        assert!(usize_of(&r, "bytes") > 0);
        let t = &r["times"];
        for stage in ["compute_ms", "render_ms", "readback_ms", "encode_ms"] {
            assert!(f64_of(t, stage) >= 0.0, "{stage}: {t}");
        }
        assert!(
            f64_of(t, "render_ms") > 0.0 && f64_of(t, "total_ms") > 0.0,
            "{t}"
        );
    }
);

gpu_test!(
    #[test]
    fn bench_render_compares_the_crowd_without_and_with_textures() {
        let r = json(&[
            "bench",
            "render",
            "--heads",
            "2",
            "--width",
            "64",
            "--height",
            "48",
            "--seconds",
            "0",
            "--textures",
            "both",
            "--json",
        ]);
        // The embedded head has no textures: "on" generates four slots' worth.
        assert_eq!(usize_of(&r["untextured"], "texture_slots"), 0);
        assert_eq!(usize_of(&r["textured"], "texture_slots"), 4);
        assert!(usize_of(&r["textured"], "texture_bytes") > 3 * 512 * 512 * 4);
        assert!(f64_of(&r, "render_ratio") > 0.0, "{r}");
        assert!(f64_of(&r["textured"]["times"], "render_ms") > 0.0);
    }
);

#[test]
fn bench_http_reports_plausible_json() {
    let r = json(&[
        "bench",
        "http",
        "--heads",
        "10",
        "--unique",
        "5",
        "--clients",
        "2",
        "--seconds",
        "0.2",
        "--backend",
        "cpu",
        "--format",
        "f16",
        "--json",
    ]);
    assert_eq!(r["backend"]["kind"], "cpu");
    assert_eq!(usize_of(&r, "vertices"), EMBEDDED_VERTICES);
    assert_eq!((usize_of(&r, "heads"), usize_of(&r, "unique")), (10, 5));
    assert_eq!(r["format"], "f16");
    for key in [
        "inprocess_heads_per_s",
        "http_heads_per_s",
        "loopback_bytes_per_s",
        "response_bytes_per_head",
        "saturation_p50_ms",
        "half_load_p50_ms",
        "engine_cpu_s_per_request",
        "socket_cpu_s_per_byte",
        "socket_cpu_s_per_response",
        "http_cpu_s_per_request",
        "ceiling_heads_per_s",
        "http_fraction_of_ceiling",
        "http_cpu_fraction_of_ceiling",
    ] {
        let v = f64_of(&r, key);
        assert!(v.is_finite() && v > 0.0, "{key} = {v}");
    }
    // The ceiling is what any server could reach from the CPU the engine and the socket copies
    // cost: HTTP, which pays both plus HTTP itself, cannot be far above it, and it is built
    // from its parts as documented.
    let ceiling = f64_of(&r, "ceiling_heads_per_s");
    let http = f64_of(&r, "http_heads_per_s");
    assert!(ceiling >= http * 0.5, "ceiling {ceiling} vs HTTP {http}");
    let cores = usize_of(&r, "cores");
    assert!(cores >= 1);
    let per_request =
        f64_of(&r, "socket_cpu_s_per_response") + f64_of(&r, "engine_cpu_s_per_request");
    let expected = cores as f64 / per_request * 10.0;
    assert!(
        (ceiling - expected).abs() <= expected * 1e-9,
        "ceiling {ceiling} vs {expected}"
    );
    assert!((f64_of(&r, "http_fraction_of_ceiling") - http / ceiling).abs() < 1e-9);
    // The socket copies' CPU per response is the per-byte cost times the response bytes.
    let per_response =
        f64_of(&r, "socket_cpu_s_per_byte") * f64_of(&r, "response_bytes_per_head") * 10.0;
    assert!((f64_of(&r, "socket_cpu_s_per_response") - per_response).abs() <= per_response * 1e-9);
    assert_eq!(r["saturation_errors"], 0);
    assert_eq!(r["half_load_errors"], 0);
    assert!(f64_of(&r, "half_load_p99_ms") >= f64_of(&r, "half_load_p50_ms"));
    // JSON, measured beside bincode in the same run.
    assert_eq!(r["json_errors"], 0);
    let json_rate = f64_of(&r, "json_heads_per_s");
    assert!(json_rate > 0.0);
    assert!((f64_of(&r, "json_over_bincode") - json_rate / http).abs() < 1e-9);
    assert!(f64_of(&r, "json_bytes_per_head") > f64_of(&r, "response_bytes_per_head"));
    assert!(r["python"].is_null(), "no Python peer unless asked for");
    // Half the heads are clones: an f16 response carries five unique buffers of 6 bytes per
    // vertex for ten heads, so about 3 bytes per vertex per head.
    let per_head = f64_of(&r, "response_bytes_per_head");
    let floor = (EMBEDDED_VERTICES * 3) as f64;
    assert!(
        per_head > floor && per_head < floor * 1.2,
        "{per_head} bytes per head"
    );
    assert!(!r["sizes"].as_array().expect("sizes").is_empty());
}

/// Rows of `report` on `route`, by their name field `key`.
fn rows_on<'a>(report: &'a Value, route: &str, key: &str) -> Vec<(String, &'a Value)> {
    report["rows"]
        .as_array()
        .expect("rows")
        .iter()
        .filter(|r| r["route"] == route)
        .map(|r| (r[key].as_str().expect("a name").to_string(), r))
        .collect()
}

/// The namespaces of `report`'s links that are still there (none once the benchmark ended).
fn leftover_links(report: &Value) -> Vec<String> {
    let out = Command::new("ip")
        .args(["netns", "list"])
        .output()
        .expect("ip netns list");
    let listed = String::from_utf8_lossy(&out.stdout).into_owned();
    let made: Vec<String> = report["routes"]
        .as_array()
        .expect("routes")
        .iter()
        .filter_map(|r| r["namespace"].as_str().map(str::to_string))
        .collect();
    assert!(!made.is_empty(), "the report names no namespace");
    made.into_iter()
        .filter(|ns| {
            listed
                .lines()
                .any(|l| l.split_whitespace().next() == Some(ns))
        })
        .collect()
}

#[test]
#[cfg_attr(
    not(crowdmorph_shaped_links),
    ignore = "needs root, iproute2 and leave to make network namespaces, veth pairs and tbf (build.rs tries)"
)]
fn bench_http_link_measures_each_encoding_on_loopback_and_a_shaped_link() {
    let r = json(&[
        "bench",
        "http",
        "--link",
        "100mbit",
        "--heads",
        "4",
        "--clients",
        "2",
        "--seconds",
        "0.4",
        "--backend",
        "cpu",
        "--json",
    ]);
    assert!(r["skipped"].is_null(), "{}", r["skipped"]);
    assert_eq!(strings(&r["clips"]), ["idle", "talk", "smile", "surprise"]);
    let routes = r["routes"].as_array().expect("routes");
    assert_eq!(routes.len(), 2);
    assert_eq!(
        (routes[0]["name"].as_str(), routes[1]["name"].as_str()),
        (Some("loopback"), Some("100mbit"))
    );
    // The link carries what tbf lets through: most of 12.5 MB/s, never more.
    let link = f64_of(&routes[1], "tcp_bytes_per_s");
    assert!(
        link > 6e6 && link < 12.5e6 * 1.05,
        "{link} bytes/s over the 100mbit link"
    );
    for route in ["loopback", "100mbit"] {
        let rows = rows_on(&r, route, "encoding");
        let names: Vec<&str> = rows.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(
            names,
            [
                "f32",
                "q16",
                "q16 + zstd",
                "q16r",
                "q16r + gzip",
                "q16r + zstd"
            ]
        );
        let bytes = |name: &str| {
            let row = rows.iter().find(|(n, _)| n == name).expect("row").1;
            assert_eq!(row["errors"], 0, "{route} {name}");
            assert!(f64_of(row, "heads_per_s") > 0.0, "{route} {name}");
            f64_of(row, "bytes_per_head")
        };
        let q16 = bytes("q16");
        // Uncompressed, bytes follow the format: q16 is 6 bytes a vertex, f32 twice that,
        // q16r's planes as long as q16 (response framing adds a little).
        let floor = (EMBEDDED_VERTICES * 6) as f64;
        assert!(q16 > floor && q16 < floor * 1.05, "{route}: q16 {q16}");
        assert!((bytes("f32") / q16 - 2.0).abs() < 0.05, "{route}");
        assert!((bytes("q16r") / q16 - 1.0).abs() < 0.01, "{route}");
        // Residuals on real clips compress (the 3x goal is checked by the bytes tests).
        assert!(bytes("q16r + zstd") * 3.0 < q16, "{route}");
        assert!(bytes("q16r + gzip") * 3.0 < q16, "{route}");
        assert!(bytes("q16 + zstd") < q16, "{route}");
    }
    // Over the link no encoding moves more bytes a second than the link carries.
    for (name, row) in rows_on(&r, "100mbit", "encoding") {
        let rate = f64_of(row, "heads_per_s") * f64_of(row, "bytes_per_head");
        assert!(rate < 12.5e6 * 1.05, "{name}: {rate} bytes/s");
    }
    assert_eq!(leftover_links(&r), Vec::<String>::new());
}

#[test]
#[cfg_attr(
    not(crowdmorph_shaped_links),
    ignore = "needs root, iproute2 and leave to make network namespaces, veth pairs and tbf (build.rs tries)"
)]
fn bench_sessions_link_gives_each_viewer_mode_its_turn_on_each_route() {
    let r = json(&[
        "bench",
        "sessions",
        "--link",
        "100mbit",
        "--heads",
        "8",
        "--animations",
        "8",
        "--seconds",
        "0.5",
        "--backend",
        "cpu",
        "--json",
    ]);
    assert!(r["skipped"].is_null(), "{}", r["skipped"]);
    assert!(f64_of(&r, "jobs_per_tick") > 0.0);
    for route in ["loopback", "100mbit"] {
        let rows = rows_on(&r, route, "mode");
        let names: Vec<&str> = rows.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(
            names,
            [
                "f32",
                "q16",
                "q16 + zstd",
                "temporal",
                "temporal + deflate",
                "temporal + zstd"
            ]
        );
        let bytes = |name: &str| {
            let row = rows.iter().find(|(n, _)| n == name).expect("row").1;
            assert!(f64_of(row, "heads_per_s") > 0.0, "{route} {name}");
            f64_of(row, "bytes_per_head")
        };
        let q16 = bytes("q16");
        assert!((bytes("f32") / q16 - 2.0).abs() < 0.05, "{route}");
        // Against the viewer's previous buffer, compressed: well under a third of q16 even
        // with the join keyframes in the window.
        assert!(bytes("temporal + zstd") * 3.0 < q16, "{route}");
        assert!(bytes("temporal + deflate") * 3.0 < q16, "{route}");
    }
    assert_eq!(leftover_links(&r), Vec::<String>::new());
}

#[test]
fn bench_sessions_modes_are_checked_before_anything_starts() {
    let out = crowdmorph(&[
        "bench", "sessions", "--link", "1gbit", "--modes", "q16,q16r",
    ])
    .output()
    .expect("runs");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("unknown viewer mode \"q16r\""), "{err}");
    assert!(err.contains("temporal+zstd"), "{err}");
}

#[test]
fn bench_codecs_codes_real_frames_losslessly_each_way() {
    let r = json(&[
        "bench",
        "codecs",
        "--frames",
        "24",
        "--zstd-levels",
        "-5,1",
        "--json",
    ]);
    assert_eq!(r["vertices"].as_u64(), Some(EMBEDDED_VERTICES as u64));
    assert_eq!(r["frames"].as_u64(), Some(24));
    let rows = r["rows"].as_array().expect("rows");
    let row = |reference: &str, coding: &str, entropy: &str| {
        rows.iter()
            .find(|x| {
                x["reference"] == reference && x["coding"] == coding && x["entropy"] == entropy
            })
            .unwrap_or_else(|| panic!("no row {reference} {coding} {entropy}: {rows:?}"))
    };
    // Plain q16 is 6 bytes a vertex; the command refuses to report a row that does not decode
    // to q16 bit for bit, so every row here round-tripped.
    let q16 = f64_of(row("none", "q16", "none"), "bytes_per_head");
    assert_eq!(q16, (EMBEDDED_VERTICES * 6) as f64);
    for reference in ["neutral", "previous"] {
        for (coding, entropy) in [
            ("planes", "zstd -5"),
            ("planes", "zstd 1"),
            ("planes", "zlib 1"),
            ("meshopt", "none"),
            ("meshopt", "zstd 1"),
            ("meshopt", "zlib 1"),
        ] {
            let x = row(reference, coding, entropy);
            assert!(
                f64_of(x, "bytes_per_head") < q16 / 3.0,
                "{reference} {coding} {entropy}"
            );
            assert!(f64_of(x, "encode_us") > 0.0 && f64_of(x, "decode_us") > 0.0);
        }
    }
    // The previous frame predicts better than the neutral, and zstd's fast mode gives up bytes.
    let b = |r: &str, c: &str, e: &str| f64_of(row(r, c, e), "bytes_per_head");
    assert!(b("previous", "planes", "zstd 1") < b("neutral", "planes", "zstd 1"));
    assert!(b("previous", "planes", "zstd 1") < b("previous", "planes", "zstd -5"));
}

#[test]
fn bench_link_rates_are_checked_before_anything_starts() {
    let out = crowdmorph(&["bench", "http", "--link", "1gb"])
        .output()
        .expect("runs");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("<n>kbit, <n>mbit or <n>gbit"), "{err}");
}

#[test]
#[cfg_attr(
    not(crowdmorph_python_peer),
    ignore = "needs /usr/bin/python3 with numpy and aiohttp: apt-get install python3-numpy python3-aiohttp"
)]
fn bench_http_and_cpu_measure_the_python_peers_on_the_same_work() {
    let r = json(&[
        "bench",
        "http",
        "--heads",
        "10",
        "--unique",
        "5",
        "--clients",
        "2",
        "--seconds",
        "0.3",
        "--backend",
        "cpu",
        "--python-peer",
        "--json",
    ]);
    let p = &r["python"];
    assert_eq!(p["python"], "/usr/bin/python3");
    assert_eq!(p["compute"], "thread");
    assert!(!p["blas"].as_str().expect("blas").is_empty());
    assert!(f64_of(p, "max_error") <= f64_of(p, "tolerance"));
    assert_eq!(p["errors"], 0);
    let rate = f64_of(p, "heads_per_s");
    assert!(rate > 0.0);
    let ratio = f64_of(p, "crowdmorph_over_python");
    assert!((ratio - f64_of(&r, "http_heads_per_s") / rate).abs() <= ratio * 1e-9);
    let bound = f64_of(p, "ceiling_over_python");
    assert!((bound - f64_of(&r, "ceiling_heads_per_s") / rate).abs() <= bound * 1e-9);

    let c = json(&[
        "bench",
        "cpu",
        "--unique",
        "10",
        "--heads",
        "10",
        "--batches",
        "10",
        "--mesh-fractions",
        "none",
        "--seconds",
        "0.05",
        "--numpy",
        "--json",
    ]);
    let n = &c["numpy"];
    let warm = f64_of(n, "warm_ms");
    assert!(warm > 0.0 && f64_of(n, "alloc_ms") > 0.0);
    assert!((f64_of(n, "kernel_speedup") - warm / f64_of(&c, "eval_ms")).abs() < 1e-9);
    assert!(
        (f64_of(n, "dense_baseline_speedup") - warm / f64_of(&c, "dense_baseline_ms")).abs() < 1e-9
    );
}

#[test]
fn bench_sessions_reports_shared_blends_and_the_bytes_viewers_got() {
    let r = json(&[
        "bench",
        "sessions",
        "--heads",
        "40",
        "--animations",
        "8",
        "--viewers",
        "3",
        "--fps",
        "10",
        "--seconds",
        "1.5",
        "--backend",
        "cpu",
        "--format",
        "q16",
        "--json",
    ]);
    assert_eq!(usize_of(&r, "vertices"), EMBEDDED_VERTICES);
    assert_eq!((usize_of(&r, "heads"), usize_of(&r, "viewers")), (40, 3));
    let ticks = usize_of(&r, "ticks");
    assert!(ticks >= 5, "{r}");
    // 40 heads over 8 animations: 8 blends a tick, shared by the three viewers.
    assert_eq!(f64_of(&r, "jobs_per_tick"), 8.0);
    // Every message carries 8 q16 buffers (6 bytes a vertex) and about as many messages
    // arrive per viewer as ticks were computed.
    let per_message =
        f64_of(&r, "bytes_per_viewer_per_s") / f64_of(&r, "messages_per_viewer_per_s");
    let payload = (8 * EMBEDDED_VERTICES * 6) as f64;
    assert!(
        per_message > payload && per_message < payload * 1.05,
        "{per_message} bytes a message"
    );
    assert!(f64_of(&r, "cpu_ms_per_tick") > 0.0);
}

#[test]
fn bench_sessions_weights_viewers_get_poses_and_submit_no_blend() {
    let r = json(&[
        "bench",
        "sessions",
        "--heads",
        "40",
        "--animations",
        "8",
        "--viewers",
        "3",
        "--fps",
        "10",
        "--seconds",
        "1.5",
        "--backend",
        "cpu",
        "--weights",
        "--json",
    ]);
    assert_eq!(r["format"], "weights", "{r}");
    assert!(usize_of(&r, "ticks") >= 5, "{r}");
    assert_eq!(f64_of(&r, "jobs_per_tick"), 0.0, "no engine work: {r}");
    // 8 distinct poses a tick (51 binary16 weights, about 105 bytes each) and 40 head
    // entries, far from 8 buffers of 6 bytes a vertex.
    let per_message =
        f64_of(&r, "bytes_per_viewer_per_s") / f64_of(&r, "messages_per_viewer_per_s");
    assert!(
        per_message > 8.0 * 104.0 && per_message < 3000.0,
        "{per_message} bytes a message"
    );
}

#[test]
fn bench_sessions_long_clip_offers_more_unique_heads_than_the_rigs_clips() {
    // The embedded head's clips hold 465 frames in all: 480 animations of them could not all
    // be distinct, 480 offsets into one 600-frame clip are.
    let r = json(&[
        "bench",
        "sessions",
        "--long-clip",
        "600",
        "--heads",
        "480",
        "--animations",
        "480",
        "--viewers",
        "1",
        "--fps",
        "5",
        "--seconds",
        "1",
        "--backend",
        "cpu",
        "--json",
    ]);
    assert!(usize_of(&r, "ticks") >= 2, "{r}");
    assert_eq!(f64_of(&r, "jobs_per_tick"), 480.0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lod_set_changes_the_lod_a_running_server_serves() {
    let server = TestServer::start(ServerConfig {
        admin_token: Some("secret".into()),
        ..ServerConfig::default()
    })
    .await;
    let url = format!("http://{}", server.addr);
    let args = |extra: &[&str]| -> Vec<String> {
        [
            "lod",
            "set",
            "default-head",
            "--server",
            &url,
            "--method",
            "file-order",
            "--pin",
            "jawOpen",
            "--level",
            "51",
            "--level",
            "12:0",
            "--level",
            "0:1",
            "--mesh-fractions",
            "0.5,0.2",
        ]
        .iter()
        .chain(extra)
        .map(|s| s.to_string())
        .collect()
    };
    // The binary blocks on its own runtime: off this test's async threads.
    let run = |args: Vec<String>, token: Option<&'static str>| {
        tokio::task::spawn_blocking(move || {
            let args: Vec<&str> = args.iter().map(String::as_str).collect();
            let mut c = crowdmorph(&args);
            if let Some(t) = token {
                // The token from the environment, as an operator would pass it.
                c.env("CROWDMORPH_ADMIN_TOKEN", t);
            }
            c.output().expect("run crowdmorph")
        })
    };

    let refused = run(args(&[]), None).await.expect("join");
    assert_eq!(refused.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("401"),
        "{}",
        String::from_utf8_lossy(&refused.stderr)
    );

    let out = run(args(&["--json"]), Some("secret")).await.expect("join");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let info: crowdmorph_proto::RigInfo = serde_json::from_slice(&out.stdout).expect("RigInfo");
    assert_eq!(info.lod.method, "file-order+pinned");
    assert_eq!(info.lod.order[0], "jawOpen");
    let table: Vec<(u32, Option<u32>)> =
        info.lod.levels.iter().map(|l| (l.shapes, l.mesh)).collect();
    assert_eq!(table, [(51, None), (12, Some(0)), (0, Some(1))]);
    assert!(info.lod.levels[2].vertices < info.lod.levels[1].vertices);
    assert_eq!(
        server.client.lod("default-head").await.expect("lod"),
        info.lod,
        "what the command set is what the server serves"
    );

    // Without --json, the table as text.
    let out = run(args(&[]), Some("secret")).await.expect("join");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && text.contains("level 1:  12 shapes"),
        "{text}"
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn load_sends_the_planned_requests_and_reports_them() {
    let server = TestServer::start(ServerConfig::default()).await;
    let url = format!("http://{}", server.addr);
    // 0.5 s at 60 requests/s: requests 0..30 fall in the window; the warm-up sends 6 more.
    let args: Vec<String> = [
        "load",
        "--url",
        &url,
        "--rate",
        "60",
        "--duration",
        "0.5",
        "--warmup",
        "0.1",
        "--connections",
        "2",
        "--heads",
        "4",
        "--unique",
        "0.5",
        "--clip",
        "talk:3",
        "--clip",
        "smile",
        "--lod",
        "0",
        "--lod",
        "2:1",
        "--format",
        "q16",
        "--json",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let out = tokio::task::spawn_blocking(move || {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        success(crowdmorph(&args))
    })
    .await
    .expect("join");
    let r: crowdmorph::load::LoadReport = serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "not a report ({e}): {}",
            String::from_utf8_lossy(&out.stdout)
        )
    });
    assert_eq!(
        (r.sent, r.ok, r.errors, r.unfinished),
        (30, 30, 0, 0),
        "{r:?}"
    );
    assert_eq!((r.lanes, r.heads_per_request), (2, 4));
    assert_eq!(r.latency_ms.count, 30);
    assert!((r.heads_per_s - 30.0 * 4.0 / 0.5).abs() < 1e-9, "{r:?}");
    // Two unique q16 jobs of the embedded head per response.
    let payload = 2.0 * (EMBEDDED_VERTICES * 3 * 2) as f64;
    assert!(r.bytes_per_s >= payload * 30.0 / 0.5, "{r:?}");
    let timings = r.server_ms.expect("Server-Timing was read");
    assert_eq!(timings.compute_ms.count, 30);
    // The server saw the warm-up too, as client traffic.
    let page = server.client.metrics().await.expect("metrics");
    assert_eq!(
        crowdmorph_client::metric(
            &page,
            "crowdmorph_crowd_frames_total{source=\"api\",status=\"200\"}"
        ),
        Some(36.0),
        "{page}"
    );
    assert_eq!(
        crowdmorph_client::metric(&page, "crowdmorph_heads_total{source=\"api\"}"),
        Some(36.0 * 4.0)
    );

    // A shape the server cannot serve is named before any load is sent.
    let url = format!("http://{}", server.addr);
    let out = tokio::task::spawn_blocking(move || {
        crowdmorph(&[
            "load",
            "--url",
            &url,
            "--clip",
            "dance",
            "--duration",
            "0.1",
        ])
        .output()
        .expect("run")
    })
    .await
    .expect("join");
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("no rig of the load has a clip \"dance\""),
        "{stderr}"
    );
    server.stop().await;
}

/// Runs `crowdmorph load --url URL` with `args` off the async workers; returns its output.
async fn load_output(url: &str, args: &[&str]) -> Output {
    let mut all = vec!["load".to_string(), "--url".into(), url.to_string()];
    all.extend(args.iter().map(|s| s.to_string()));
    tokio::task::spawn_blocking(move || {
        let all: Vec<&str> = all.iter().map(String::as_str).collect();
        crowdmorph(&all).output().expect("run crowdmorph")
    })
    .await
    .expect("join")
}

/// Runs `crowdmorph load --url URL` with `args` (which include `--json`), requires success,
/// and parses its report.
async fn load_report(url: &str, args: &[&str]) -> crowdmorph::load::LoadReport {
    let out = load_output(url, args).await;
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "not a report ({e}): {}",
            String::from_utf8_lossy(&out.stdout)
        )
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn load_session_watches_every_tick_with_three_viewers() {
    let server = TestServer::start(ServerConfig::default()).await;
    let url = format!("http://{}", server.addr);
    // 6 heads over 3 animations (clip and offset pairs) of the embedded head, 30 ticks/s like
    // its clips, so every tick every animation moves to its next frame: 3 buffers and 6
    // changed heads in every message.
    let r = load_report(
        &url,
        &[
            "--session",
            "--viewers",
            "3",
            "--fps",
            "30",
            "--heads",
            "6",
            "--unique",
            "0.5",
            "--format",
            "f16",
            "--duration",
            "2",
            "--warmup",
            "0.5",
            "--grace",
            "5",
            "--json",
        ],
    )
    .await;
    let s = r.session.clone().expect("a sessions report");
    assert!(s.created);
    assert_eq!((s.viewers, s.heads, s.fps), (3, 6, 30.0), "{s:?}");
    assert_eq!((r.lanes, r.heads_per_request, r.rate), (3, 6, 90.0));
    // 2 s at 30 ticks/s, counted from the session's own clock.
    assert!((59..=61).contains(&s.ticks_due), "{s:?}");
    assert_eq!(r.sent, 3 * s.ticks_due);
    assert_eq!(r.errors, 0, "{r:?}");
    assert!(r.errors_by.is_empty(), "{r:?}");
    assert_eq!(r.ok, s.ticks_received);
    assert_eq!(r.unfinished, r.sent - r.ok);
    assert_eq!(s.per_viewer.len(), 3);
    for v in &s.per_viewer {
        // A loose lower bound: a loaded machine may skip ticks, but not most of them.
        assert!(
            v.received >= s.ticks_due / 2 && v.received <= s.ticks_due,
            "{v:?} of {}",
            s.ticks_due
        );
        assert!(v.received + v.missed <= s.ticks_due, "{v:?}");
        assert_eq!(v.heads, 6 * v.received, "{v:?}");
        assert_eq!(v.close_code, None);
        assert!(v.latency_max_ms >= v.latency_mean_ms && v.latency_mean_ms > 0.0);
    }
    // Heads and bytes follow the session's head count and the format.
    assert_eq!(s.changed_heads_per_message, 6.0);
    assert!(
        (r.heads_per_s - r.ok as f64 * 6.0 / r.duration_s).abs() < 1e-6,
        "{r:?}"
    );
    let payload = (3 * EMBEDDED_VERTICES * 3 * 2) as f64;
    assert!(
        s.bytes_per_message > payload && s.bytes_per_message < payload + 1024.0,
        "{} bytes a message for {payload} bytes of f16 positions",
        s.bytes_per_message
    );
    assert!((r.bytes_per_s - s.bytes_per_message * r.achieved_rate).abs() < 1e-3 * r.bytes_per_s);
    assert_eq!(r.latency_ms.count, r.ok);
    let t = r.server_ms.expect("the messages' timings were read");
    assert_eq!((t.total_ms.count, t.compute_ms.count), (r.ok, r.ok));
    // The session the run created is gone.
    let list = server
        .client
        .send(
            crowdmorph_client::Method::GET,
            "/v1/sessions",
            None,
            None,
            bytes::Bytes::new(),
        )
        .await
        .expect("list sessions");
    let list: crowdmorph_proto::SessionList = serde_json::from_slice(&list.body).expect("list");
    assert!(list.sessions.is_empty(), "{list:?}");

    // Attached to an existing session, the run reads its heads and leaves it in place.
    let created = server
        .client
        .send(
            crowdmorph_client::Method::POST,
            "/v1/sessions",
            Some("application/json"),
            None,
            bytes::Bytes::from(
                serde_json::json!({"fps": 20, "heads": [
                    {"head": 7, "rig": "default-head", "clip": "talk"},
                    {"head": 8, "rig": "default-head", "clip": "talk"}]})
                .to_string(),
            ),
        )
        .await
        .expect("create a session");
    assert_eq!(created.status, 201);
    let info: crowdmorph_proto::SessionInfo =
        serde_json::from_slice(&created.body).expect("SessionInfo");
    let r = load_report(
        &url,
        &[
            "--session-id",
            &info.id,
            "--viewers",
            "2",
            "--duration",
            "1",
            "--warmup",
            "0.3",
            "--json",
        ],
    )
    .await;
    let s = r.session.expect("a sessions report");
    assert!(!s.created);
    assert_eq!(
        (s.id.as_str(), s.heads, s.fps, s.viewers),
        (info.id.as_str(), 2, 20.0, 2)
    );
    // Two clones: one buffer, both heads changed, in every message.
    assert_eq!(s.changed_heads_per_message, 2.0);
    assert!(s.ticks_received >= s.ticks_due, "{s:?}");
    let still = server
        .client
        .send(
            crowdmorph_client::Method::GET,
            &format!("/v1/sessions/{}", info.id),
            None,
            None,
            bytes::Bytes::new(),
        )
        .await
        .expect("get the session");
    assert_eq!(still.status, 200, "an attached session is not deleted");

    // An unknown session, and a ramp, are refused with a reason before any load.
    for (args, says) in [
        (&["--session-id", "nope"], "has no session \"nope\""),
        (&["--session", "--ramp"], "--ramp"),
    ] {
        let out = load_output(&url, args).await;
        assert_eq!(out.status.code(), Some(1));
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(stderr.contains(says), "{stderr}");
    }
    server.stop().await;
}

#[test]
fn serve_help_lists_every_flag_with_its_environment_variable() {
    let mut command = crowdmorph(&["serve", "--help"]);
    command.env("CROWDMORPH_ADMIN_TOKEN", "do-not-print-me");
    let out = success(command);
    let help = String::from_utf8(out.stdout).expect("UTF-8");
    for (flag, env) in [
        ("--addr", "CROWDMORPH_ADDR"),
        ("--data-dir", "CROWDMORPH_DATA_DIR"),
        ("--backend", "CROWDMORPH_BACKEND"),
        ("--admin-token", "CROWDMORPH_ADMIN_TOKEN"),
        ("--max-heads", "CROWDMORPH_MAX_HEADS"),
        ("--batch-delay-us", "CROWDMORPH_BATCH_DELAY_US"),
        ("--no-auto-lod", "CROWDMORPH_NO_AUTO_LOD"),
        ("--batch-hold-when-idle", "CROWDMORPH_BATCH_HOLD_WHEN_IDLE"),
        (
            "--loadtest-max-duration-s",
            "CROWDMORPH_LOADTEST_MAX_DURATION_S",
        ),
        ("--loadtest-max-rate", "CROWDMORPH_LOADTEST_MAX_RATE"),
    ] {
        assert!(
            help.contains(flag) && help.contains(env),
            "{flag} / {env}:\n{help}"
        );
    }
    assert!(help.contains("127.0.0.1:8080"), "the default address");
    assert!(
        !help.contains("do-not-print-me"),
        "the token's value is hidden"
    );
}

/// The subcommands a `--help` lists under "Commands:" (without `help`).
fn subcommands(args: &[&str]) -> Vec<String> {
    let mut a = args.to_vec();
    a.push("--help");
    let help = String::from_utf8(success(crowdmorph(&a)).stdout).expect("UTF-8");
    help.lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| !l.trim().is_empty())
        .filter_map(|l| l.split_whitespace().next())
        .filter(|c| *c != "help")
        .map(str::to_string)
        .collect()
}

/// README's "Command line" lists every subcommand the binary has, nested ones too (`lod
/// order|report|mesh` lists three), so none is left for users to find by chance.
#[test]
fn the_readme_command_list_has_every_subcommand() {
    let readme =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/README.md")).expect("README");
    let start = readme.find("## Command line").expect("the section");
    let section = &readme[start..start + readme[start..].find("\n## ").expect("its end")];
    // What each `crowdmorph X Y...` line names: (X, the alternatives of Y).
    let listed: Vec<(&str, Vec<&str>)> = section
        .lines()
        .filter_map(|l| l.trim().strip_prefix("crowdmorph "))
        .map(|l| {
            let mut words = l.split_whitespace();
            let top = words.next().unwrap_or("");
            let sub = words.next().unwrap_or("").split('|').collect();
            (top, sub)
        })
        .collect();
    let top = subcommands(&[]);
    assert!(top.len() >= 8, "{top:?}");
    for t in &top {
        assert!(
            listed.iter().any(|(x, _)| x == t),
            "README's command list lacks `crowdmorph {t}`"
        );
        for sub in subcommands(&[t.as_str()]) {
            assert!(
                listed
                    .iter()
                    .any(|(x, subs)| x == t && subs.contains(&sub.as_str())),
                "README's command list lacks `crowdmorph {t} {sub}`"
            );
        }
    }
}

#[test]
fn a_bad_argument_exits_with_status_2_and_says_why() {
    let out = crowdmorph(&["bench", "http", "--no-such-flag"])
        .output()
        .expect("run");
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("unexpected argument '--no-such-flag'") && stderr.contains("Usage:"),
        "{stderr}"
    );
    assert!(out.stdout.is_empty());

    let out = crowdmorph(&["eval", "--frame", "twelve"])
        .output()
        .expect("run");
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("invalid value 'twelve' for '--frame <FRAME>'"),
        "{stderr}"
    );
}

#[test]
fn clips_compress_meets_its_budget_checked_from_the_decoded_csv() {
    let dir = temp_dir("compress");
    let csv = dir.join("decoded.csv");
    let report = json(&[
        "clips",
        "compress",
        "--max-error",
        "3e-4",
        "--out",
        path_str(&csv),
        "--json",
    ]);
    let rig = crowdmorph::embedded::default_rig();
    assert_eq!(report["clips"].as_array().unwrap().len(), rig.clips.len());
    assert!(f64_of(&report, "ratio") > 1.0, "{report}");
    // The decoded weights, read back and blended by the f64 oracle, against the original
    // frames: every vertex within the budget.
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(header.len(), 2 + rig.targets.len());
    let diag = f64::from(rig.bbox().diagonal());
    let mut checked = 0;
    for (i, line) in lines.enumerate() {
        if i % 17 != 0 {
            continue;
        }
        let cells: Vec<&str> = line.split(',').collect();
        let clip = &rig.clips[rig.clip_index(cells[0]).unwrap()];
        let frame: u32 = cells[1].parse().unwrap();
        let decoded: Vec<f64> = cells[2..].iter().map(|c| c.parse().unwrap()).collect();
        let original: Vec<f64> = (0..rig.targets.len())
            .map(|t| f64::from(clip.weight(t, frame)))
            .collect();
        let (a, _) = crate::util::rig_oracle(&rig, &decoded);
        let (b, _) = crate::util::rig_oracle(&rig, &original);
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (*x - *y).length())
            .fold(0.0, f64::max);
        assert!(
            worst <= 3e-4 * diag,
            "{} frame {frame}: {worst} > budget {}",
            clip.name,
            3e-4 * diag
        );
        checked += 1;
    }
    assert!(checked > 10);
    let _ = std::fs::remove_dir_all(&dir);
}

/// `clips compress --clip`: the real Live Link Face capture kept with the tests, on the embedded
/// head, reported per clip, and its decoded frames checked by the f64 oracle against the noisy
/// original (the head and eye angle columns are skipped by the CSV reader).
#[test]
fn clips_compress_codes_a_real_capture_within_its_budget() {
    let dir = temp_dir("compress-capture");
    let csv = dir.join("decoded.csv");
    let capture = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/live-link-face/MySlate_3_Jason_Millers_iPhone.csv");
    let report = json(&[
        "clips",
        "compress",
        "--clip",
        path_str(&capture),
        "--out",
        path_str(&csv),
        "--json",
    ]);
    let rig = crowdmorph::embedded::default_rig();
    let rows = report["clips"].as_array().unwrap();
    assert_eq!(rows.len(), rig.clips.len() + 1);
    let row = &rows[rig.clips.len()];
    assert_eq!(row["frames"], 328, "{row}");
    assert!(f64_of(row, "max") <= 3e-4, "{row}");
    let options = crowdmorph::import::clips::ClipOptions {
        fps: 60.0,
        ignore_unknown: true,
        budget: None,
    };
    let bytes = std::fs::read(&capture).unwrap();
    let name = row["clip"].as_str().unwrap();
    let original = crowdmorph::import::clip_from_csv(&rig, name, &bytes, &options)
        .unwrap()
        .clip;
    let diag = f64::from(rig.bbox().diagonal());
    let mut checked = 0;
    for line in std::fs::read_to_string(&csv).unwrap().lines().skip(1) {
        let cells: Vec<&str> = line.split(',').collect();
        if cells[0] != name {
            continue;
        }
        let frame: u32 = cells[1].parse().unwrap();
        if !frame.is_multiple_of(7) {
            continue;
        }
        let decoded: Vec<f64> = cells[2..].iter().map(|c| c.parse().unwrap()).collect();
        let want: Vec<f64> = (0..rig.targets.len())
            .map(|t| f64::from(original.weight(t, frame)))
            .collect();
        let (a, _) = crate::util::rig_oracle(&rig, &decoded);
        let (b, _) = crate::util::rig_oracle(&rig, &want);
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (*x - *y).length())
            .fold(0.0, f64::max);
        assert!(worst <= 3e-4 * diag, "frame {frame}: {worst}");
        checked += 1;
    }
    assert_eq!(checked, 47);
    let _ = std::fs::remove_dir_all(&dir);
}

/// `clips compress-texture`: a PNG sequence in, the byte form of the animated texture out, and
/// each region's reported error equal to the error of the file's decode, measured here.
#[test]
fn clips_compress_texture_writes_a_texture_whose_error_it_reports() {
    use crowdmorph::render::brdf::{linear_to_srgb8, srgb8_to_linear};
    let dir = temp_dir("cli-compress-texture");
    let frames_dir = dir.join("frames");
    std::fs::create_dir_all(&frames_dir).unwrap();
    let (w, h, n) = (16u32, 20u32, 6u32);
    let mut frames: Vec<Vec<u8>> = Vec::new();
    for f in 0..n {
        // A blink in the eye band (rows 4–8 of 20) and a changing mouth below it.
        let rgb: Vec<u8> = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .flat_map(|(x, y)| {
                let eye = (4..9).contains(&y) && (f % 3 == 0) && x % 4 < 2;
                let mouth = y >= 14 && (x + f) % 5 == 0;
                let base = [180u8, 120, 100];
                base.map(|c| {
                    if eye {
                        c / 3
                    } else if mouth {
                        c.saturating_add(40)
                    } else {
                        c.saturating_add((x + y) as u8)
                    }
                })
            })
            .collect();
        let path = frames_dir.join(format!("frame{f:03}.png"));
        let file = std::fs::File::create(&path).unwrap();
        let mut e = png::Encoder::new(std::io::BufWriter::new(file), w, h);
        e.set_color(png::ColorType::Rgb);
        e.set_depth(png::BitDepth::Eight);
        e.write_header().unwrap().write_image_data(&rgb).unwrap();
        frames.push(rgb);
    }
    let out = dir.join("talk.cmat");
    let report = json(&[
        "clips",
        "compress-texture",
        "--frames",
        path_str(&frames_dir),
        "--clip",
        "talk",
        "-o",
        path_str(&out),
        "--json",
    ]);
    assert_eq!(usize_of(&report, "frames"), n as usize);
    let bytes = std::fs::read(&out).unwrap();
    assert_eq!(usize_of(&report, "bytes"), bytes.len());
    let t = crowdmorph::rig::AnimatedTexture::from_bytes("talk", &bytes).expect("the byte form");
    assert_eq!((t.width, t.height, t.frames), (w, h, n));
    let regions = report["regions"].as_array().unwrap();
    let names: Vec<&str> = regions.iter().filter_map(|r| r["name"].as_str()).collect();
    assert_eq!(names, ["eyes", "rest"], "the default regions");
    // The eyes' and the rest's RMS error over all frames, in linear, from the file.
    let mut sq = [0f64; 2];
    let mut count = [0f64; 2];
    let mut worst8 = 0u8;
    for (f, rgb) in frames.iter().enumerate() {
        let d = t.decode(f as u32);
        for (i, &c) in rgb.iter().enumerate() {
            let p = (i / 3) as u32;
            let (x, y) = (p % w, p / w);
            let r = crowdmorph::rig::AnimatedTexture::region_of(&t.regions, x, y).unwrap();
            let e = d[i] - f64::from(srgb8_to_linear(c));
            sq[r] += e * e;
            count[r] += 1.0;
            worst8 = worst8.max(linear_to_srgb8(d[i] as f32).abs_diff(c));
        }
    }
    for (r, row) in regions.iter().enumerate() {
        let rms = (sq[r] / count[r]).sqrt();
        let reported = f64_of(row, "rms_linear");
        assert!(
            (rms - reported).abs() <= 1e-6 + 1e-3 * rms,
            "{row}: measured {rms}"
        );
    }
    // Six frames, at most five directions per region, and 8 + 4 components: near exact.
    assert!(worst8 <= 1, "worst 8-bit error {worst8}");
}
