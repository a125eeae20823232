//! Golden bytes of the server's own bincode encoder for crowd frames: the aligned layout that
//! `proto/README.md` documents (payloads at 16-byte offsets), pinned in
//! `tests/golden/crowd_frame_aligned.bin`. Set `CROWDMORPH_BLESS=1` to rewrite the file after
//! an intended change of the protocol (and bump the protocol version).

use bytes::Bytes;
use crowdmorph::codec::{FrameBufferParts, FrameResponseEncoder, response_from_wire};
use crowdmorph_proto::{
    BLOB_ALIGN, CrowdFrameResponse, Format, FrameTimings, HeadBuffer, Quantization,
};

fn sample() -> Vec<Bytes> {
    let positions: Vec<u8> = (0..9)
        .flat_map(|i: i16| (i * 1000 - 4000).to_le_bytes())
        .collect();
    let normals: Vec<u8> = (0..9).flat_map(|i: i16| (i * 3000).to_le_bytes()).collect();
    let parts = [FrameBufferParts {
        rig: "default-head",
        clip: "talk",
        frame: 12,
        lod: 1,
        vertices: 3,
        quantization: Some(Quantization {
            min: [-1.0, -2.0, -0.5],
            step: [3.0e-5, 6.0e-5, 1.5e-5],
            max_error: [1.5e-5, 3.0e-5, 7.5e-6],
        }),
        positions: Bytes::from(positions),
        normals: Some(Bytes::from(normals)),
    }];
    let heads = [
        HeadBuffer { head: 7, buffer: 0 },
        HeadBuffer {
            head: 300,
            buffer: 0,
        },
    ];
    let timings = FrameTimings {
        queue_us: 120,
        compute_us: 900,
        total_us: 1500,
        gpu_us: None,
    };
    FrameResponseEncoder::encode(Format::Q16, true, &parts, &heads, &timings)
}

#[test]
fn crowd_frame_encoding_is_pinned_and_aligned() {
    let chunks = sample();
    let body: Vec<u8> = chunks.iter().flat_map(|c| c.iter().copied()).collect();
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden/crowd_frame_aligned.bin");
    if std::env::var_os("CROWDMORPH_BLESS").is_some() {
        std::fs::write(&path, &body).unwrap();
    }
    let golden = std::fs::read(&path).expect("golden file (CROWDMORPH_BLESS=1 writes it)");
    assert_eq!(body, golden, "the wire encoding changed");
    // It is a valid bincode CrowdFrameResponse...
    let resp: CrowdFrameResponse = response_from_wire(&body).unwrap();
    assert_eq!(resp.heads.len(), 2);
    assert_eq!(resp.buffers[0].positions.to_i16()[8], 4000);
    // ...whose two payloads start on 16-byte boundaries, right after their length bytes.
    let mut offset = 0;
    let mut aligned = 0;
    for c in &chunks {
        if c.len() == 18 {
            assert_eq!(offset % BLOB_ALIGN, 0);
            aligned += 1;
        }
        offset += c.len();
    }
    assert_eq!(aligned, 2);
}
