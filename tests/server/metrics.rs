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
            ..Default::default()
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

/// A family listed in README.md's "### Metrics" table: its name as queried (counters with
/// `_total`), its type and its label names.
#[derive(Debug)]
struct Documented {
    name: String,
    kind: String,
    labels: Vec<String>,
}

impl Documented {
    /// The OpenMetrics family name: a counter's `# TYPE` line names it without `_total`.
    fn family(&self) -> &str {
        match self.kind.as_str() {
            "counter" => self.name.strip_suffix("_total").unwrap_or(&self.name),
            _ => &self.name,
        }
    }
}

fn readme() -> String {
    std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/README.md")).expect("README.md")
}

/// The rows of the table under README.md's `### Metrics` heading.
fn documented(readme: &str) -> Vec<Documented> {
    let section = readme
        .split("\n### Metrics\n")
        .nth(1)
        .expect("README.md has a ### Metrics section");
    let code = |cell: &str| cell.trim().trim_matches('`').to_string();
    section
        .lines()
        .skip_while(|l| !l.starts_with('|'))
        .take_while(|l| l.starts_with('|'))
        .skip(2) // the header and its rule
        .map(|row| {
            let cells: Vec<&str> = row.trim().trim_matches('|').split('|').collect();
            let [name, kind, labels] = cells[..] else {
                panic!("README.md metrics row {row:?}: expected name | type | labels");
            };
            Documented {
                name: code(name),
                kind: kind.trim().to_string(),
                labels: labels
                    .split(',')
                    .map(code)
                    .filter(|l| !l.is_empty() && l != "—")
                    .collect(),
            }
        })
        .collect()
}

/// `/metrics` after some traffic, parsed by a real OpenMetrics parser (`openmetrics-parser`,
/// which checks the exposition grammar and each family's samples): every family of README.md's
/// metrics table is there with its type and labels, every family the server exports is in the
/// table, and every metric README.md names elsewhere is in it too.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_parse_as_openmetrics_and_match_the_readme() {
    use openmetrics_parser::OpenMetricsType;
    use std::collections::BTreeSet;

    let readme = readme();
    let docs = documented(&readme);
    assert!(docs.len() >= 50, "README.md lists {} families", docs.len());
    let mut names = BTreeSet::new();
    for d in &docs {
        assert!(names.insert(d.family()), "{} listed twice", d.name);
    }
    // Every metric named anywhere in README.md is a row of the table.
    for word in readme.split(|c: char| !(c.is_ascii_alphanumeric() || c == '_')) {
        if word.starts_with("crowdmorph_") && !word.ends_with('_') {
            assert!(
                docs.iter().any(|d| d.name == word),
                "README.md names {word}, which its metrics table does not list"
            );
        }
    }

    let server = TestServer::start(ServerConfig::default()).await;
    let c = &server.client;
    for rig in ["default-head", "no-such-rig"] {
        let _ = c.crowd_frame(&request(rig), Encoding::Bincode).await;
    }
    let reply = c
        .send(
            crowdmorph_client::Method::GET,
            "/metrics",
            None,
            None,
            bytes::Bytes::new(),
        )
        .await
        .expect("metrics");
    assert_eq!(reply.status, 200);
    assert_eq!(
        reply.content_type.as_deref(),
        Some("application/openmetrics-text; version=1.0.0; charset=utf-8")
    );
    let page = String::from_utf8(reply.body.to_vec()).expect("utf-8");
    if std::env::var_os("CROWDMORPH_PRINT_METRICS").is_some() {
        eprintln!("{page}");
    }
    assert!(page.ends_with("# EOF\n"), "{page}");
    let parsed = openmetrics_parser::openmetrics::parse_openmetrics(&page)
        .unwrap_or_else(|e| panic!("not OpenMetrics: {e:?}\n{page}"));

    let mut labelled = 0;
    for d in &docs {
        let family = parsed
            .families
            .get(d.family())
            .unwrap_or_else(|| panic!("{} (README.md) is not in /metrics:\n{page}", d.name));
        let kind = match family.family_type {
            OpenMetricsType::Counter => "counter",
            OpenMetricsType::Gauge => "gauge",
            OpenMetricsType::Histogram => "histogram",
            other => panic!("{}: unexpected type {other:?}", d.name),
        };
        assert_eq!(kind, d.kind, "{}: type", d.name);
        // Each family has its series by now: those of known label values are made at start,
        // the rest by the traffic above.
        assert!(
            family.iter_samples().next().is_some(),
            "{}: no samples:\n{page}",
            d.name
        );
        let mut got = family.get_label_names().to_vec();
        got.sort();
        let mut want = d.labels.clone();
        want.sort();
        assert_eq!(got, want, "{}: labels", d.name);
        labelled += usize::from(!want.is_empty());
    }
    for name in parsed.families.keys() {
        assert!(
            names.contains(name.as_str()),
            "/metrics exports {name}, which README.md's metrics table does not list"
        );
    }
    eprintln!(
        "{} families in README.md and /metrics, {labelled} with labelled samples",
        docs.len()
    );
    server.stop().await;
}
