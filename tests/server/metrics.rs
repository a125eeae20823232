//! `/metrics`: one crowd-frame response moves each counter that counts it by exactly one, for
//! a success and for a refusal.

use crowdmorph::server::ServerConfig;
use crowdmorph_client::{Encoding, metric};
use crowdmorph_proto::{CrowdFrameRequest, Format, Head, OutputOptions};

use super::TestServer;

/// Every sample of the family `name` whose labels contain each of `labels`, summed.
fn sum_of(page: &str, name: &str, labels: &[&str]) -> f64 {
    page.lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let rest = l.strip_prefix(name)?;
            let (labelset, value) = rest.rsplit_once(' ')?;
            (labelset.is_empty() || labelset.starts_with('{')).then_some(())?;
            labels
                .iter()
                .all(|want| labelset.contains(want))
                .then(|| value.parse::<f64>().ok())?
        })
        .sum()
}

/// What a crowd-frame response can be counted as: by source and status, and by route and
/// status (all crowd-frame series, whatever their labels, summed in the last two).
fn counts(page: &str, status: u16) -> [f64; 4] {
    let status = format!("status=\"{status}\"");
    [
        sum_of(
            page,
            "crowdmorph_crowd_frames_total",
            &["source=\"api\"", &status],
        ),
        sum_of(
            page,
            "crowdmorph_http_requests_total",
            &["route=\"/v1/crowd/frame\"", &status],
        ),
        sum_of(page, "crowdmorph_crowd_frames_total", &[]),
        sum_of(
            page,
            "crowdmorph_http_requests_total",
            &["route=\"/v1/crowd/frame\""],
        ),
    ]
}

fn request(rig: &str) -> CrowdFrameRequest {
    CrowdFrameRequest {
        heads: vec![Head {
            head: 7,
            rig: rig.into(),
            clip: "talk".into(),
            frame: 3,
            lod: 0,
        }],
        output: OutputOptions {
            normals: false,
            format: Format::F16,
        },
        wrap: true,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_crowd_frame_moves_each_of_its_counters_by_exactly_one() {
    let server = TestServer::start(ServerConfig::default()).await;
    let c = &server.client;
    for (rig, status) in [("default-head", 200u16), ("no-such-rig", 404)] {
        let before = counts(&c.metrics().await.expect("metrics"), status);
        let got = c.crowd_frame(&request(rig), Encoding::Bincode).await;
        assert_eq!(got.is_ok(), status == 200, "{rig}: {:?}", got.err());
        let page = c.metrics().await.expect("metrics");
        let after = counts(&page, status);
        let moved: Vec<f64> = after.iter().zip(&before).map(|(a, b)| a - b).collect();
        assert_eq!(moved, [1.0; 4], "{rig} ({status}): {page}");
    }
    // Two responses in all, each counted once per family.
    let page = c.metrics().await.expect("metrics");
    assert_eq!(sum_of(&page, "crowdmorph_crowd_frames_total", &[]), 2.0);
    assert_eq!(
        metric(&page, "crowdmorph_heads_total{source=\"api\"}"),
        Some(1.0),
        "only the answered head is served"
    );
    server.stop().await;
}
