//! A real avatar, end to end, as a new user brings one: VALID's White_F_1_Casual (MIT; see
//! `tests/data/avatars/valid-white-f-1/SOURCE.txt`), a skinned figure with 96 face and teeth
//! targets, meshopt-compressed and quantized, whose skin, eyes, clothes and hair are 2048²
//! WebP textures. Uploaded as the file is, its images come back byte for byte, and a render
//! framed on its face is a textured face (skin-toned, many colours, filling the picture) whose
//! wink closes one eye.
//!
//! Its first render carries the rig's first GPU upload (three 2048² textures with their mips)
//! and the face region, so the test gives requests a generous deadline: it decides when to give
//! up, never what passes.

use std::collections::HashSet;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use bytes::Bytes;
use crowdmorph::server::ServerConfig;
use crowdmorph_client::Encoding;
use crowdmorph_proto::{CameraFrame, CameraSpec, Head, ImageOptions, LiveWeights, RenderRequest};
use serde_json::Value;

use super::TestServer;
use crate::util::gpu_test;
use crate::util::image::Image;

fn avatar() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/avatars/valid-white-f-1/White_F_1_Casual.glb")
}

/// The GLB's JSON chunk and binary chunk.
fn glb_chunks(glb: &[u8]) -> (Value, &[u8]) {
    let word = |at: usize| u32::from_le_bytes([glb[at], glb[at + 1], glb[at + 2], glb[at + 3]]);
    assert_eq!(&glb[..4], b"glTF");
    let json_len = word(12) as usize;
    let json: Value = serde_json::from_slice(&glb[20..20 + json_len]).expect("JSON chunk");
    let bin_at = 20 + json_len;
    let bin_len = word(bin_at) as usize;
    (json, &glb[bin_at + 8..bin_at + 8 + bin_len])
}

/// Every image's bytes as the file stores them (buffer views of the GLB's binary chunk).
fn file_images(glb: &[u8]) -> Vec<Vec<u8>> {
    let (json, bin) = glb_chunks(glb);
    json["images"]
        .as_array()
        .expect("images")
        .iter()
        .map(|image| {
            let view = &json["bufferViews"][image["bufferView"].as_u64().expect("a view") as usize];
            let at = view["byteOffset"].as_u64().unwrap_or(0) as usize;
            let len = view["byteLength"].as_u64().expect("length") as usize;
            bin[at..at + len].to_vec()
        })
        .collect()
}

/// The render's background, a colour the avatar does not have.
const BACKGROUND: [u8; 3] = [30, 34, 40];

fn drawn(p: &[u8]) -> bool {
    (0..3).any(|c| p[c].abs_diff(BACKGROUND[c]) > 4)
}

async fn render_face(server: &TestServer, weights: &[(&str, f32)]) -> Image {
    let req = RenderRequest {
        heads: vec![Head::live(
            1,
            "avatar",
            LiveWeights::Named(weights.iter().map(|&(n, w)| (n.to_string(), w)).collect()),
        )],
        wrap: true,
        placements: None,
        camera: Some(CameraSpec::framing(CameraFrame::Faces)),
        image: Some(ImageOptions {
            width: 256,
            height: 256,
            background: BACKGROUND,
            ..ImageOptions::default()
        }),
    };
    let start = Instant::now();
    let reply = server
        .client
        .render(&req, Encoding::Json)
        .await
        .expect("render");
    println!(
        "render {weights:?}: {} in {:.1} s",
        reply.status,
        start.elapsed().as_secs_f64()
    );
    assert_eq!(reply.status, 200, "{:?}", reply.error());
    let img = Image::decode_png(&reply.body).expect("a PNG");
    let name = if weights.is_empty() {
        "neutral"
    } else {
        "weighted"
    };
    let file = crate::util::image::failure_dir().join(format!("avatar-faces-{name}.png"));
    img.write_png(&file).expect("write");
    println!("picture: {}", file.display());
    img
}

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_real_avatar_keeps_its_textures_and_renders_a_textured_face() {
        let server = TestServer::start(ServerConfig {
            request_timeout: Duration::from_secs(600),
            ..ServerConfig::default()
        })
        .await;
        let glb = std::fs::read(avatar()).expect("the avatar");
        let start = Instant::now();
        let info = server
            .client
            .upload_rig("avatar", Bytes::from(glb.clone()))
            .await
            .expect("upload");
        println!("upload: {:.1} s", start.elapsed().as_secs_f64());
        // Nothing of it is dropped: meshopt, quantization and WebP are all read.
        assert!(info.import_notes.is_empty(), "{:?}", info.import_notes);
        assert_eq!(info.targets.len(), 96, "{:?}", info.targets);

        // Its images, byte for byte: every one the server lists is one of the file's, and
        // every image the file's materials sample is listed.
        let materials = server.client.materials("avatar").await.expect("materials");
        let served = materials["images"].as_array().expect("images").len();
        let want = file_images(&glb);
        let mut seen = HashSet::new();
        for i in 0..served {
            let (bytes, kind) = server.client.texture("avatar", i).await.expect("texture");
            assert_eq!(kind, "image/webp");
            let k = want
                .iter()
                .position(|w| w[..] == bytes[..])
                .unwrap_or_else(|| panic!("served image {i} is none of the file's"));
            seen.insert(k);
        }
        assert_eq!(seen.len(), want.len(), "every file image is served");
        assert_eq!(materials["materials"].as_array().map(Vec::len), Some(2));

        // A textured face, framed: the figure fills much of the picture, in many colours, with
        // a good share of skin (red over green over blue), which untextured white plaster
        // has none of.
        let neutral = render_face(&server, &[]).await;
        let pixels: Vec<&[u8]> = neutral.rgba.chunks_exact(4).filter(|p| drawn(p)).collect();
        let area = f64::from(neutral.width * neutral.height);
        let fill = pixels.len() as f64 / area;
        let colours: HashSet<[u8; 3]> = pixels
            .iter()
            .map(|p| [p[0] >> 3, p[1] >> 3, p[2] >> 3])
            .collect();
        let skin = pixels
            .iter()
            .filter(|p| p[0] > p[1].saturating_add(20) && p[1] > p[2])
            .count() as f64
            / area;
        println!(
            "faces: {:.0} % drawn, {} colours (5 bits a channel), {:.0} % skin-toned",
            fill * 100.0,
            colours.len(),
            skin * 100.0
        );
        assert!(fill > 0.4, "the figure fills {:.0} %", fill * 100.0);
        assert!(colours.len() > 500, "{} colours", colours.len());
        // Framed on the face (its chin, where the targets stop moving, not the wig's ends at
        // the shoulders), skin is a fifth of the picture; framed on the head joint's whole
        // box it was 12 %.
        assert!(skin > 0.15, "{:.1} % skin-toned", skin * 100.0);

        // A wink: the left eye's target closes one eye. The picture changes, in a small part
        // of it (an eye, not the whole face), and in its upper half.
        let wink = info
            .targets
            .iter()
            .find(|t| t.contains("LeyeClose"))
            .expect("an eye-close target");
        let winked = render_face(&server, &[(wink.as_str(), 1.0)]).await;
        let (mut changed, mut upper) = (0usize, 0usize);
        for (i, (a, b)) in neutral
            .rgba
            .chunks_exact(4)
            .zip(winked.rgba.chunks_exact(4))
            .enumerate()
        {
            if (0..3).any(|c| a[c].abs_diff(b[c]) > 24) {
                changed += 1;
                if (i as u32 / neutral.width) < neutral.height / 2 {
                    upper += 1;
                }
            }
        }
        let share = changed as f64 / f64::from(neutral.width * neutral.height);
        println!(
            "wink: {changed} pixels changed ({:.2} %), {upper} in the upper half",
            share * 100.0
        );
        // At 256², an eye is about 15 × 8 pixels.
        assert!(share > 0.0005 && share < 0.05, "{changed} pixels changed");
        assert!(
            upper * 10 >= changed * 9,
            "{upper} of {changed} in the upper half"
        );
        server.stop().await;
    }
);
