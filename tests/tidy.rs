//! Tidy checks (rust-analyzer's habit): facts about the tree that docs state and nothing else
//! would catch when they drift.

use std::path::{Path, PathBuf};

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Every `.rs` file under `dir`, recursively.
fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).expect("read_dir") {
            let p = e.expect("entry").path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// The string literals that are arguments of the call whose `(` is at `open` (nested calls
/// included), in order.
fn literal_args(src: &str, open: usize) -> Vec<String> {
    let b = src.as_bytes();
    let mut depth = 0i32;
    let mut i = open;
    let mut out = Vec::new();
    while i < b.len() {
        match b[i] {
            b'(' => depth += 1,
            b')' => {
                depth -= 1;
                if depth == 0 {
                    break;
                }
            }
            b'"' => {
                let start = i + 1;
                i += 1;
                while i < b.len() && b[i] != b'"' {
                    if b[i] == b'\\' {
                        i += 1;
                    }
                    i += 1;
                }
                out.push(src[start..i.min(src.len())].to_string());
            }
            _ => {}
        }
        i += 1;
    }
    out
}

/// The error codes the server answers with: the first literal argument of each `ApiError`
/// constructor that takes a code (`new` takes the status first).
fn server_error_codes() -> Vec<(String, String)> {
    let mut codes = Vec::new();
    for file in rust_files(&root().join("src")) {
        let src = read(&file);
        for ctor in [
            "ApiError::new(",
            "ApiError::bad_request(",
            "ApiError::not_found(",
            "ApiError::unavailable(",
        ] {
            for (at, _) in src.match_indices(ctor) {
                let open = at + ctor.len() - 1;
                let Some(code) = literal_args(&src, open).into_iter().next() else {
                    continue;
                };
                let snake = !code.is_empty()
                    && code
                        .chars()
                        .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_');
                if snake {
                    codes.push((code, file.display().to_string()));
                }
            }
        }
    }
    codes.sort();
    codes.dedup();
    codes
}

#[test]
fn every_error_code_the_server_answers_is_in_the_protocols_error_table() {
    let readme = read(&root().join("proto/README.md"));
    let start = readme.find("| status | codes |").expect("the error table");
    let end = start + readme[start..].find("\n\n").expect("the table's end");
    let table = &readme[start..end];
    let codes = server_error_codes();
    assert!(codes.len() > 40, "the scan finds the codes: {codes:?}");
    let missing: Vec<&(String, String)> = codes
        .iter()
        .filter(|(c, _)| !table.contains(&format!("`{c}`")))
        .collect();
    assert!(
        missing.is_empty(),
        "codes the server answers that proto/README.md's error table does not list: {missing:?}"
    );
}

#[test]
fn readme_examples_do_not_hard_code_a_session_id() {
    // Session ids are handed out by the server (s1, s2, ...): an example that names one works
    // once, and a second run gets 404.
    let readme = read(&root().join("README.md"));
    for (n, line) in readme.lines().enumerate() {
        assert!(
            !line.contains("/v1/sessions/s1") && !line.contains("/v1/sessions/s2"),
            "README.md line {}: {line}",
            n + 1
        );
    }
}
