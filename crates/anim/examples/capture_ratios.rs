//! Ratios of the clip codecs on a rig's clips and CSV captures:
//! `cargo run --example capture_ratios -p crowdmorph-anim -- [RIG.glb] [--max-error E] [CAPTURE.csv ...] [--synthetic N]`
//! (what `crowdmorph clips compress` reports, without building the server).

use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let mut take = |flag: &str| -> Option<String> {
        let i = args.iter().position(|a| a == flag)?;
        let v = args.get(i + 1).cloned();
        args.drain(i..(i + 2).min(args.len()));
        v
    };
    let budget: f32 = take("--max-error").map_or(Ok(3e-4), |v| v.parse())?;
    let synthetic: Option<usize> = take("--synthetic").map(|v| v.parse()).transpose()?;
    let mut rig = match args.first().filter(|a| !a.ends_with(".csv")) {
        Some(p) => crowdmorph_import::load_path(
            std::path::Path::new(p),
            &crowdmorph_import::ImportOptions::default(),
        )?,
        None => crowdmorph_core::embedded::default_rig(),
    };
    let options = crowdmorph_import::clips::ClipOptions {
        fps: 60.0,
        ignore_unknown: true,
        budget: None,
    };
    for p in args.iter().filter(|a| a.ends_with(".csv")) {
        let bytes = std::fs::read(p)?;
        let name = std::path::Path::new(p)
            .file_stem()
            .map_or("capture".into(), |s| s.to_string_lossy().into_owned());
        rig.clips
            .push(crowdmorph_import::clip_from_csv(&rig, &name, &bytes, &options)?.clip);
    }
    if let Some(n) = synthetic {
        let names = crowdmorph_core::synthetic::ARKIT_NAMES;
        let table = crowdmorph_core::synthetic::face_capture(n, 48);
        let mut csv = names.join(",");
        csv.push('\n');
        for f in 0..n {
            let row: Vec<String> = (0..names.len())
                .map(|k| table[k * n + f].to_string())
                .collect();
            csv.push_str(&row.join(","));
            csv.push('\n');
        }
        rig.clips.push(
            crowdmorph_import::clip_from_csv(&rig, "synthetic-capture", csv.as_bytes(), &options)?
                .clip,
        );
    }
    println!(
        "rig {:?}: {} targets, diagonal {:.3}, budget {budget:e}",
        rig.name,
        rig.targets.len(),
        rig.bbox().diagonal()
    );
    let t = Instant::now();
    let metric = crowdmorph_anim::transform::Metric::of(&rig);
    println!("metric {:.2} s", t.elapsed().as_secs_f64());
    for clip in &rig.clips {
        let f32b = clip.weights.len() * 4;
        let t = Instant::now();
        let curves = crowdmorph_anim::compress::compress(&rig, clip, budget)?;
        let tc = t.elapsed().as_secs_f64();
        let ct = crowdmorph_anim::compress::decode(&curves)?;
        let rc = crowdmorph_anim::compress::measure(&rig, clip, &ct, budget);
        let t = Instant::now();
        let tr = crowdmorph_anim::transform::compress(&rig, &metric, clip, budget)?;
        let tt = t.elapsed().as_secs_f64();
        let (tb, tm, comps) = match &tr {
            Some(c) => {
                let table = crowdmorph_anim::transform::decode(c)?;
                let r = crowdmorph_anim::compress::measure(&rig, clip, &table, budget);
                (c.bytes(), r.max, c.components())
            }
            None => (0, f64::NAN, 0),
        };
        println!(
            "{:>28} {:>5} fr  f32 {:>7}  curves {:>6} B {:>5.1}x max {:.2e} ({:.2} s)  transform {:>6} B {:>5.1}x max {:.2e} {:>2} dirs ({:.2} s)",
            clip.name,
            clip.frames,
            f32b,
            curves.bytes(),
            f32b as f64 / curves.bytes() as f64,
            rc.max,
            tc,
            tb,
            f32b as f64 / tb.max(1) as f64,
            tm,
            comps,
            tt
        );
    }
    Ok(())
}
