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
    for file in rust_files(&root().join("crates/server/src")) {
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

/// Every (method, path, handler) of the router in `crates/server/src/app.rs`: each `.route("PATH",
/// get(routes::x::handler).post(...))` read by its literals.
fn routes() -> Vec<(String, String, String)> {
    let app = read(&root().join("crates/server/src/app.rs"));
    let mut out = Vec::new();
    for (at, _) in app.match_indices(".route(") {
        let open = at + ".route".len();
        let Some(path) = literal_args(&app, open).into_iter().next() else {
            continue;
        };
        // The call's extent: up to its closing parenthesis.
        let mut depth = 0;
        let mut end = open;
        for (i, c) in app[open..].char_indices() {
            match c {
                '(' => depth += 1,
                ')' => {
                    depth -= 1;
                    if depth == 0 {
                        end = open + i;
                        break;
                    }
                }
                _ => {}
            }
        }
        let call = &app[open..end];
        for method in ["get", "post", "put", "patch", "delete"] {
            for (m, _) in call.match_indices(&format!("{method}(")) {
                let before = call[..m].chars().next_back();
                if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
                    continue;
                }
                let rest = &call[m + method.len() + 1..];
                let handler = &rest[..rest.find(')').expect("handler's end")];
                let name = handler.rsplit("::").next().unwrap_or(handler).trim();
                out.push((method.to_uppercase(), path.clone(), name.to_string()));
            }
        }
    }
    out
}

/// The handlers in `crates/server/src/routes/` that take the `Admin` extractor.
fn admin_handlers() -> Vec<String> {
    let mut out = Vec::new();
    for file in rust_files(&root().join("crates/server/src/routes")) {
        let src = read(&file);
        for (at, _) in src.match_indices("pub async fn ") {
            let rest = &src[at + "pub async fn ".len()..];
            let name = &rest[..rest.find('(').expect("parameters")];
            let params = &rest[..rest.find(") ->").unwrap_or(rest.len())];
            if params.contains(": Admin,") || params.contains(": Admin)") {
                out.push(name.to_string());
            }
        }
    }
    out
}

#[test]
fn the_admin_token_help_names_every_route_that_needs_it() {
    let config = read(&root().join("crates/server/src/config.rs"));
    let field = config
        .find("pub admin_token")
        .expect("the admin token flag");
    // The doc comment above the field (past its attributes), as `serve --help` prints it.
    let help = config[..field]
        .lines()
        .rev()
        .skip(1)
        .skip_while(|l| l.trim_start().starts_with("#["))
        .take_while(|l| l.trim_start().starts_with("///"))
        .map(|l| l.trim_start().trim_start_matches("///").trim())
        .collect::<Vec<_>>()
        .into_iter()
        .rev()
        .collect::<Vec<_>>()
        .join(" ");
    let routes = routes();
    let admin = admin_handlers();
    assert!(
        routes.len() > 20 && admin.len() > 10,
        "{routes:?} {admin:?}"
    );
    let guarded: Vec<String> = routes
        .iter()
        .filter(|(_, _, h)| admin.contains(h))
        .map(|(m, p, _)| format!("{m} {p}"))
        .collect();
    for h in &admin {
        assert!(
            routes.iter().any(|(_, _, r)| r == h),
            "{h} takes Admin but no route in app.rs names it"
        );
    }
    let missing: Vec<&String> = guarded.iter().filter(|r| !help.contains(*r)).collect();
    assert!(
        missing.is_empty(),
        "--admin-token's help does not name {missing:?}: {help}"
    );
    // And it names no route that does not need the token.
    let words: Vec<&str> = help.split_whitespace().collect();
    for pair in words.windows(2) {
        let path = pair[1].trim_end_matches([',', '.', ';']);
        if ["GET", "POST", "PUT", "PATCH", "DELETE"].contains(&pair[0]) && path.starts_with('/') {
            let named = format!("{} {path}", pair[0]);
            assert!(guarded.contains(&named), "{named} is open: {help}");
        }
    }
}

/// The module names a `//!` table of `file` lists in its first column (`` [`x`] `` or `` `x` ``).
fn mapped_modules(file: &Path) -> Vec<String> {
    let text = read(file);
    let mut in_map = false;
    text.lines()
        .filter(|l| {
            if l.starts_with("//! | module |") {
                in_map = true;
            } else if !l.starts_with("//! |") {
                in_map = false;
            }
            in_map
        })
        .filter_map(|l| l.strip_prefix("//! | "))
        .filter_map(|row| row.split(" | ").next())
        .map(|cell| {
            cell.trim_matches(|c| matches!(c, '[' | ']' | '`' | ' '))
                .to_string()
        })
        .filter(|m| m != "module" && m != "the crate root" && !m.starts_with("---"))
        .collect()
}

/// The modules `file` declares (`mod x;`, `pub mod x;`, `pub(crate) mod x;`), test-only ones
/// left out.
fn declared_modules(file: &Path) -> Vec<String> {
    let src = read(file);
    let mut out = Vec::new();
    let mut test_only = false;
    for line in src.lines().map(str::trim) {
        if line.starts_with("#[cfg(test)]") {
            test_only = true;
            continue;
        }
        let decl = line
            .strip_prefix("pub mod ")
            .or_else(|| line.strip_prefix("pub(crate) mod "))
            .or_else(|| line.strip_prefix("mod "));
        if let Some(name) = decl.and_then(|d| d.strip_suffix(';'))
            && !test_only
        {
            out.push(name.to_string());
        }
        if !line.starts_with("#[") {
            test_only = false;
        }
    }
    out
}

/// The workspace's crates: each folder under `crates/` with its `Cargo.toml`.
fn crate_dirs() -> Vec<PathBuf> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(root().join("crates"))
        .expect("crates/")
        .map(|e| e.expect("entry").path())
        .filter(|p| p.join("Cargo.toml").exists())
        .collect();
    dirs.sort();
    dirs
}

#[test]
fn every_module_is_in_its_crates_map() {
    let dirs = crate_dirs();
    assert!(dirs.len() >= 8, "the scan finds the crates: {dirs:?}");
    let mut total = 0;
    for dir in dirs {
        let lib = dir.join("src/lib.rs");
        let mapped = mapped_modules(&lib);
        let declared = declared_modules(&lib);
        total += declared.len();
        assert!(
            !declared.is_empty(),
            "{}: the scan finds its modules",
            lib.display()
        );
        let missing: Vec<&String> = declared.iter().filter(|m| !mapped.contains(m)).collect();
        assert!(
            missing.is_empty(),
            "{}'s `//!` map does not list {missing:?}",
            lib.display()
        );
        let stale: Vec<&String> = mapped.iter().filter(|m| !declared.contains(m)).collect();
        assert!(
            stale.is_empty(),
            "{}'s `//!` map lists modules it lacks: {stale:?}",
            lib.display()
        );
    }
    assert!(total > 40, "the scan finds the modules ({total})");
}

/// The `crowdmorph-*` crates a manifest depends on (normal dependencies, not dev ones), by
/// short name (`crowdmorph-core` → `core`).
fn workspace_deps(manifest: &Path) -> Vec<String> {
    let text = read(manifest);
    let mut out = Vec::new();
    let mut in_deps = false;
    for line in text.lines().map(str::trim) {
        if line.starts_with('[') {
            in_deps = line.ends_with("dependencies]") && !line.contains("dev-dependencies");
            continue;
        }
        if in_deps && let Some(rest) = line.strip_prefix("crowdmorph-") {
            let name: String = rest
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '-')
                .collect();
            if !matches!(name.as_str(), "proto" | "client") {
                out.push(name);
            }
        }
    }
    out.sort();
    out.dedup();
    out
}

/// The crate map of ARCHITECTURE.md: each row's crate folder and the crates its "uses" column
/// names.
fn architecture_crate_map() -> Vec<(String, Vec<String>)> {
    let text = read(&root().join("ARCHITECTURE.md"));
    let section = text
        .split("## Crate map")
        .nth(1)
        .expect("ARCHITECTURE.md has a crate map")
        .split("\n## ")
        .next()
        .unwrap_or("");
    let mut rows = Vec::new();
    for line in section.lines() {
        let cells: Vec<&str> = line.split(" | ").map(str::trim).collect();
        if cells.len() < 3 || !cells[0].starts_with("| `crates/") {
            continue;
        }
        let path = cells[0]
            .trim_start_matches("| ")
            .trim_matches('`')
            .to_string();
        let mut uses: Vec<String> = cells[1]
            .split(',')
            .map(|s| s.trim().trim_matches('`').to_string())
            .filter(|s| !s.is_empty() && s != "—")
            .collect();
        uses.sort();
        rows.push((path, uses));
    }
    rows
}

#[test]
fn architecture_md_maps_every_crate_and_what_it_uses() {
    let map = architecture_crate_map();
    let dirs = crate_dirs();
    assert_eq!(
        map.iter().map(|(p, _)| p.clone()).collect::<Vec<_>>(),
        dirs.iter()
            .map(|d| d.strip_prefix(root()).unwrap_or(d).display().to_string())
            .collect::<Vec<_>>(),
        "ARCHITECTURE.md's crate map has one row per crate, in folder order"
    );
    for (path, uses) in map {
        let deps = workspace_deps(&root().join(&path).join("Cargo.toml"));
        assert_eq!(
            uses, deps,
            "{path}: ARCHITECTURE.md says it uses {uses:?}, its Cargo.toml {deps:?}"
        );
    }
}

#[test]
fn the_data_crate_builds_without_the_servers_dependencies() {
    let manifest = read(&root().join("crates/core/Cargo.toml"));
    let deps: Vec<&str> = manifest
        .lines()
        .filter_map(|l| l.split(['.', ' ', '=']).next())
        .filter(|n| !n.is_empty() && !n.starts_with('[') && !n.starts_with('#'))
        .collect();
    for forbidden in [
        "tokio",
        "axum",
        "wgpu",
        "object_store",
        "hyper",
        "rayon",
        "gltf",
    ] {
        assert!(
            !deps.contains(&forbidden),
            "crates/core depends on {forbidden}: it is the data layer (ARCHITECTURE.md)"
        );
    }
    assert!(
        deps.contains(&"glam"),
        "the scan reads the manifest: {deps:?}"
    );
}

/// Backticked words of a Markdown text that name files or folders of the repository: they
/// contain a `/` or end in a source extension, and are not routes (`/v1/...`), globs, media
/// types or URLs.
fn named_paths(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut in_fence = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") || line.trim_start().starts_with("~~~") {
            in_fence = !in_fence;
            continue;
        }
        if in_fence {
            continue;
        }
        for (i, part) in line.split('`').enumerate() {
            let path = part.trim();
            let source = [".rs", ".md", ".wgsl", ".py", ".toml", ".js", ".html"]
                .iter()
                .any(|x| path.ends_with(x));
            let plain = !path.is_empty()
                && path
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || matches!(c, '/' | '.' | '_' | '-'));
            if i % 2 == 1
                && plain
                && (path.contains('/') || source)
                && !path.starts_with('/')
                && !path.starts_with("application/")
                && !path.starts_with("text/")
                && !path.starts_with("model/")
                && !path.starts_with("image/")
            {
                out.push(path.to_string());
            }
        }
    }
    out
}

#[test]
fn every_path_architecture_md_names_exists() {
    let mut docs = vec![root().join("ARCHITECTURE.md")];
    let design = root().join("docs/design");
    if let Ok(dir) = std::fs::read_dir(&design) {
        docs.extend(dir.filter_map(Result::ok).map(|e| e.path()));
    }
    let mut checked = 0;
    for doc in &docs {
        let missing: Vec<String> = named_paths(&read(doc))
            .into_iter()
            .inspect(|_| checked += 1)
            .filter(|p| {
                // A bare file name (`mod.rs`) names a file somewhere in the tree: only paths
                // are checked.
                p.contains('/') && !root().join(p).exists()
            })
            .collect();
        assert!(
            missing.is_empty(),
            "{} names paths that do not exist: {missing:?}",
            doc.display()
        );
    }
    assert!(checked > 50, "the scan finds the paths ({checked})");
}

/// `src` with its `#[cfg(test)]` items cut off: the product code.
///
/// A `#[cfg(test)]` in front of a one-line item (`mod priced_tests;`, a `use`) drops only that
/// line; one in front of a block (`mod tests {`) ends the product code there.
fn product_code(src: &str) -> String {
    let mut out = String::with_capacity(src.len());
    let mut lines = src.lines();
    while let Some(line) = lines.next() {
        if line.trim() == "#[cfg(test)]" {
            match lines.next() {
                Some(item) if item.trim_end().ends_with(';') => continue,
                _ => break,
            }
        }
        out.push_str(line);
        out.push('\n');
    }
    out
}

/// `src` without its comments (line comments, doc comments included).
fn code_only(src: &str) -> String {
    src.lines()
        .map(|l| l.find("//").map_or(l, |i| &l[..i]))
        .collect::<Vec<_>>()
        .join("\n")
}

#[test]
fn rig_is_pure_data() {
    let files = rust_files(&root().join("crates/core/src/rig"));
    assert!(files.len() >= 5, "the scan finds rig/: {files:?}");
    for f in files {
        let src = read(&f);
        let code = code_only(&product_code(&src));
        for forbidden in ["tokio", "wgpu", "axum", "std::fs", "std::io"] {
            assert!(
                !code.contains(forbidden),
                "{} uses {forbidden}: rig/ is pure data (ARCHITECTURE.md)",
                f.display()
            );
        }
    }
}

/// The module path of a file of a workspace crate, the crate's short name first
/// (`crates/server/src/http/mod.rs` → `["server", "http"]`); `None` for the umbrella library
/// and the binary under `src/`.
fn module_of(file: &Path) -> Option<Vec<String>> {
    let rel = file.strip_prefix(root().join("crates")).ok()?;
    let mut it = rel.iter();
    let krate = it.next()?.to_string_lossy().to_string();
    if it.next()? != "src" {
        return None;
    }
    let mut parts = vec![krate];
    parts.extend(it.map(|p| p.to_string_lossy().trim_end_matches(".rs").to_string()));
    if parts.last().is_some_and(|p| p == "mod" || p == "lib") {
        parts.pop();
    }
    Some(parts)
}

/// Expands a `use` tree `a::{b, c::{d, e}}` into its leaves, each after `prefix`.
fn expand(tree: &str, prefix: &[String], out: &mut Vec<Vec<String>>) {
    let tree = tree.trim();
    if let Some(open) = tree.find('{') {
        let mut p = prefix.to_vec();
        p.extend(
            tree[..open]
                .split("::")
                .map(str::trim)
                .filter(|s| !s.is_empty())
                .map(str::to_string),
        );
        let close = tree.rfind('}').filter(|&c| c > open).unwrap_or(tree.len());
        let inner = &tree[open + 1..close];
        let (mut depth, mut start) = (0, 0);
        for (i, c) in inner.char_indices() {
            match c {
                '{' => depth += 1,
                '}' => depth -= 1,
                ',' if depth == 0 => {
                    expand(&inner[start..i], &p, out);
                    start = i + 1;
                }
                _ => {}
            }
        }
        expand(&inner[start..], &p, out);
    } else if !tree.is_empty() {
        let mut p = prefix.to_vec();
        let leaf = tree.split(" as ").next().unwrap_or(tree);
        p.extend(leaf.split("::").map(|s| s.trim().to_string()));
        out.push(p);
    }
}

/// `path` (starting with `crate`, `super`, `self` or a workspace crate `crowdmorph_x`) as
/// absolute segments, seen from `base` (whose first segment is its crate).
fn absolute(path: &[String], base: &[String]) -> Vec<String> {
    let mut abs = base.to_vec();
    let mut segs = path;
    match segs.first().map(String::as_str) {
        Some("crate") => {
            abs.truncate(1);
            segs = &segs[1..];
        }
        Some(other) if other.starts_with("crowdmorph_") => {
            abs = vec![other["crowdmorph_".len()..].to_string()];
            segs = &segs[1..];
        }
        Some("self") => segs = &segs[1..],
        _ => {
            while segs.first().is_some_and(|s| s == "super") {
                abs.pop();
                segs = &segs[1..];
            }
        }
    }
    abs.extend(segs.iter().filter(|s| *s != "self" && *s != "*").cloned());
    abs
}

/// Every path the code of a file of module `module` names that starts with `crate`, `super`
/// or `self` (in `use` statements, braces expanded, and inline), made absolute. Inline
/// modules (`mod x { ... }`) are followed, so that their `super` is the file's module.
/// `pub use` re-exports are the parent's facade, not a dependency of its code: left out.
fn crate_paths(code: &str, module: &[String]) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let mut inline: Vec<(String, i32)> = Vec::new();
    let mut depth = 0i32;
    let mut pending_use: Option<String> = None;
    for line in code.lines() {
        let t = line.trim();
        let mut base = module.to_vec();
        base.extend(inline.iter().map(|(m, _)| m.clone()));
        let mut relative = Vec::new();
        if let Some(stmt) = pending_use.as_mut() {
            stmt.push_str(t);
        } else if let Some(rest) = t.strip_prefix("use ") {
            pending_use = Some(rest.to_string());
        } else {
            // Inline paths.
            for start in ["crate::", "super::", "crowdmorph_"] {
                let mut from = 0;
                while let Some(i) = t[from..].find(start) {
                    let at = from + i;
                    let prev = t[..at].chars().last();
                    if prev.is_none_or(|c| !c.is_alphanumeric() && c != '_' && c != ':') {
                        let path: String = t[at..]
                            .chars()
                            .take_while(|c| c.is_alphanumeric() || *c == '_' || *c == ':')
                            .collect();
                        relative.push(
                            path.split("::")
                                .filter(|s| !s.is_empty())
                                .map(str::to_string)
                                .collect(),
                        );
                    }
                    from = at + start.len();
                }
            }
        }
        if pending_use.as_ref().is_some_and(|s| s.contains(';')) {
            let stmt = pending_use.take().unwrap_or_default();
            expand(stmt.split(';').next().unwrap_or(""), &[], &mut relative);
        }
        for p in relative {
            if p.first().is_some_and(|s| {
                s == "crate" || s == "super" || s == "self" || s.starts_with("crowdmorph_")
            }) {
                out.push(absolute(&p, &base));
            }
        }
        // Inline modules open with `mod x {` and close with their brace.
        let name = t
            .strip_prefix("pub mod ")
            .or_else(|| t.strip_prefix("pub(crate) mod "))
            .or_else(|| t.strip_prefix("mod "))
            .and_then(|r| r.strip_suffix('{'))
            .map(str::trim);
        for c in t.chars() {
            match c {
                '{' => depth += 1,
                '}' => depth -= 1,
                _ => {}
            }
        }
        if let Some(name) = name {
            inline.push((name.to_string(), depth));
        }
        while inline.last().is_some_and(|&(_, d)| depth < d) {
            inline.pop();
        }
    }
    out
}

/// Finds a cycle in `edges` (a file → the files it imports), if there is one.
fn find_cycle(
    edges: &std::collections::BTreeMap<String, std::collections::BTreeSet<String>>,
) -> Option<Vec<String>> {
    fn visit(
        n: &str,
        edges: &std::collections::BTreeMap<String, std::collections::BTreeSet<String>>,
        state: &mut std::collections::BTreeMap<String, u8>,
        stack: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        state.insert(n.to_string(), 1);
        stack.push(n.to_string());
        for m in edges.get(n).into_iter().flatten() {
            match state.get(m.as_str()).copied().unwrap_or(0) {
                1 => {
                    let at = stack.iter().position(|s| s == m).unwrap_or(0);
                    let mut cycle = stack[at..].to_vec();
                    cycle.push(m.clone());
                    return Some(cycle);
                }
                0 => {
                    if let Some(c) = visit(m, edges, state, stack) {
                        return Some(c);
                    }
                }
                _ => {}
            }
        }
        stack.pop();
        state.insert(n.to_string(), 2);
        None
    }
    let mut state = std::collections::BTreeMap::new();
    for n in edges.keys() {
        if state.get(n.as_str()).copied().unwrap_or(0) == 0 {
            let mut stack = Vec::new();
            if let Some(c) = visit(n, edges, &mut state, &mut stack) {
                return Some(c);
            }
        }
    }
    None
}

/// The workspace's file-level import graph: an edge from each file of a crate to every other
/// file whose module (or an item of it) its product code names through `crate::`, `super::`,
/// `self::` or another crate's name (`crowdmorph_core::rig::...`).
/// Re-exports (`pub use`) are not edges, and a path through one ends at the re-exporting
/// module; test modules and files ending in `tests.rs` are left out.
fn import_graph() -> std::collections::BTreeMap<String, std::collections::BTreeSet<String>> {
    let files: Vec<(PathBuf, Vec<String>)> = rust_files(&root().join("crates"))
        .into_iter()
        .filter(|f| !f.to_string_lossy().ends_with("tests.rs"))
        .filter_map(|f| module_of(&f).map(|m| (f, m)))
        .collect();
    let by_module: std::collections::BTreeMap<Vec<String>, String> = files
        .iter()
        .map(|(f, m)| {
            (
                m.clone(),
                f.strip_prefix(root()).unwrap_or(f).display().to_string(),
            )
        })
        .collect();
    let mut edges = std::collections::BTreeMap::new();
    for (file, module) in &files {
        let name = by_module[module].clone();
        let src = read(file);
        let code = code_only(&product_code(&src));
        let mut targets = std::collections::BTreeSet::new();
        for abs in crate_paths(&code, module) {
            // The longest prefix that is a module file.
            let target = (0..=abs.len())
                .rev()
                .find_map(|n| by_module.get(&abs[..n]))
                .cloned();
            if let Some(t) = target
                && t != name
            {
                targets.insert(t);
            }
        }
        edges.insert(name, targets);
    }
    edges
}

#[test]
fn no_file_of_the_library_imports_one_that_imports_it_back() {
    let edges = import_graph();
    let n: usize = edges.values().map(|t| t.len()).sum();
    assert!(n > 300, "the scan finds the imports ({n})");
    assert!(
        edges["crates/engine/src/facade.rs"].contains("crates/core/src/rig/mod.rs"),
        "the scan resolves `use crowdmorph_core::rig::...`"
    );
    assert!(
        edges["crates/server/src/routes/frames.rs"].contains("crates/server/src/scheduler.rs"),
        "the scan resolves `use crate::scheduler::...`"
    );
    assert!(
        edges["crates/import/src/gltf.rs"].contains("crates/import/src/channels.rs"),
        "the scan resolves `use super::channels::...`"
    );
    // The search finds a cycle where there is one.
    let two = std::collections::BTreeMap::from([
        (
            "a".to_string(),
            std::collections::BTreeSet::from(["b".to_string()]),
        ),
        (
            "b".to_string(),
            std::collections::BTreeSet::from(["a".to_string()]),
        ),
    ]);
    assert_eq!(find_cycle(&two).map(|c| c.len()), Some(3));
    if let Some(cycle) = find_cycle(&edges) {
        panic!("import cycle: {}", cycle.join(" → "));
    }
    // Routes are the top layer: only the router and other routes name them.
    for (file, targets) in &edges {
        let top =
            file.starts_with("crates/server/src/routes/") || file == "crates/server/src/app.rs";
        assert!(
            top || !targets
                .iter()
                .any(|t| t.starts_with("crates/server/src/routes/")),
            "{file} imports a route module: {targets:?}"
        );
    }
}

/// The server's layer of one of its files: app → routes → state → services → admission → http,
/// and the server's core (batcher, registry, metrics, sessions, ...) beside them.
fn server_layer(file: &str) -> Option<&'static str> {
    let rel = file.strip_prefix("crates/server/src/")?;
    Some(match rel.split('/').next().unwrap_or(rel) {
        "app.rs" => "app",
        "routes" => "routes",
        "state.rs" => "state",
        "services" => "services",
        "admission" => "admission",
        "http" => "http",
        "lib.rs" => "lib",
        _ => "core",
    })
}

#[test]
fn the_servers_imports_run_one_way() {
    let edges = import_graph();
    let mut checked = 0;
    for (file, targets) in &edges {
        let Some(layer) = server_layer(file) else {
            continue;
        };
        // What each layer may not name (ARCHITECTURE.md, "Server imports run one way").
        let forbidden: &[&str] = match layer {
            "app" | "lib" => &[],
            "routes" => &["app"],
            "state" => &["app", "routes"],
            "services" => &["app", "routes", "state"],
            "admission" => &["app", "routes", "state", "services"],
            "http" => &["app", "routes", "state", "services", "admission", "core"],
            _ => &["app", "routes", "state", "services", "admission"],
        };
        for target in targets {
            let Some(to) = server_layer(target) else {
                continue;
            };
            checked += 1;
            // The core holds charges of the queue memory (a session's stream): that one file
            // of admission it may name.
            let queue_memory = target == "crates/server/src/admission/memory.rs";
            assert!(
                !forbidden.contains(&to) || (layer == "core" && queue_memory),
                "{file} ({layer}) imports {target} ({to}): server imports run \
                 app → routes → state → services → admission → http"
            );
            // Of the core, only the accept loop answers errors itself.
            assert!(
                layer != "core"
                    || to != "http"
                    || file.ends_with("/conn.rs")
                    || !target.contains("/http/error"),
                "{file} uses the HTTP layer's errors: only conn.rs of the core does"
            );
        }
    }
    assert!(
        checked > 100,
        "the scan finds the server's imports ({checked})"
    );
}

/// The CPU mirrors a shader's header names (`// Pass `x` (CPU mirror: `engine::cpu::f`) ...`):
/// each `engine::...` path in backticks after "CPU mirror" in the file's first comment block.
fn shader_mirrors(src: &str) -> Vec<String> {
    let header: String = src
        .lines()
        .take_while(|l| l.starts_with("//"))
        .map(|l| l.trim_start_matches('/').trim())
        .collect::<Vec<_>>()
        .join(" ");
    let mut out = Vec::new();
    for part in header.split("CPU mirror").skip(1) {
        // The names up to the closing parenthesis or sentence.
        let scope = part.split([')', '.']).next().unwrap_or("");
        for (i, piece) in scope.split('`').enumerate() {
            if i % 2 == 1 && piece.starts_with("engine::") {
                out.push(piece.to_string());
            }
        }
    }
    out
}

/// Whether the engine crate defines what `path` (`engine::cpu::CpuRig::blend`) names: the
/// module's file exists, and it (or, for a method, an impl of its type) defines the last name.
fn engine_item_exists(path: &str) -> bool {
    let segs: Vec<&str> = path.split("::").skip(1).collect();
    let src = root().join("crates/engine/src");
    let mut dir = src.clone();
    let mut file = src.join("lib.rs");
    let mut rest = &segs[..];
    while let Some((first, tail)) = rest.split_first() {
        let as_dir = dir.join(first).join("mod.rs");
        let as_file = dir.join(format!("{first}.rs"));
        if as_dir.exists() {
            file = as_dir;
            dir = dir.join(first);
        } else if as_file.exists() {
            file = as_file;
            dir = dir.join(first);
        } else {
            break;
        }
        rest = tail;
    }
    let code = code_only(&read(&file));
    match rest {
        [item] => [
            "fn ", "struct ", "enum ", "const ", "static ", "type ", "trait ",
        ]
        .iter()
        .any(|kw| code.contains(&format!("{kw}{item}"))),
        [ty, method] => {
            (code.contains(&format!("struct {ty}")) || code.contains(&format!("enum {ty}")))
                && code.contains(&format!("fn {method}"))
        }
        _ => false,
    }
}

#[test]
fn every_shader_headers_cpu_mirror_exists() {
    let dir = root().join("crates/engine/shaders");
    let mut checked = 0;
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("shaders/")
        .map(|e| e.expect("entry").path())
        .collect();
    files.extend(
        std::fs::read_dir(dir.join("lib"))
            .expect("shaders/lib/")
            .map(|e| e.expect("entry").path()),
    );
    for f in files
        .iter()
        .filter(|f| f.extension().is_some_and(|x| x == "wgsl"))
    {
        for mirror in shader_mirrors(&read(f)) {
            checked += 1;
            assert!(
                engine_item_exists(&mirror),
                "{}: its header names the CPU mirror `{mirror}`, which the engine crate does not define",
                f.display()
            );
        }
    }
    assert!(checked >= 7, "the scan finds the mirrors ({checked})");
    assert!(
        !engine_item_exists("engine::cpu::no_such_pass"),
        "the check can fail"
    );
}

#[test]
fn no_module_of_the_python_client_imports_one_that_imports_it_back() {
    let dir = root().join("clients/python/src/crowdmorph");
    let mut edges = std::collections::BTreeMap::new();
    let modules: Vec<String> = std::fs::read_dir(&dir)
        .expect("the Python package")
        .filter_map(Result::ok)
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().to_string();
            name.strip_suffix(".py").map(str::to_string)
        })
        .collect();
    assert!(
        modules.len() >= 4,
        "the scan finds the package: {modules:?}"
    );
    for m in &modules {
        let src = read(&dir.join(format!("{m}.py")));
        let mut targets = std::collections::BTreeSet::new();
        for line in src.lines().map(str::trim) {
            // `from .x import ...`, `from crowdmorph.x import ...`, `import crowdmorph.x`.
            // `from . import a, b as c` names modules after `import`.
            let named: Vec<&str> = if let Some(rest) = line
                .strip_prefix("from . import ")
                .or_else(|| line.strip_prefix("from crowdmorph import "))
            {
                rest.split(',')
                    .filter_map(|n| n.split_whitespace().next())
                    .collect()
            } else {
                line.strip_prefix("from .")
                    .or_else(|| line.strip_prefix("from crowdmorph."))
                    .or_else(|| line.strip_prefix("import crowdmorph."))
                    .and_then(|r| r.split([' ', ',', '.']).next())
                    .into_iter()
                    .collect()
            };
            for t in named {
                if t != m && modules.iter().any(|x| x == t) {
                    targets.insert(t.to_string());
                }
            }
        }
        edges.insert(m.clone(), targets);
    }
    assert!(
        edges["client"].contains("sessions") && edges["client"].contains("errors"),
        "the scan reads `from . import sessions` and `from .errors import ...`: {edges:?}"
    );
    if let Some(cycle) = find_cycle(&edges) {
        panic!("import cycle in the Python client: {}", cycle.join(" → "));
    }
}

/// The names of the compile-time variables `build.rs` hands the crate with
/// `cargo::rustc-env=NAME=...`: every one only where it found a program (nginx, HAProxy,
/// SeaweedFS, Chromium, ...), so each may be unset on a fresh machine.
fn build_script_variables() -> Vec<String> {
    let src = code_only(&read(&root().join("build.rs")));
    let mut names: Vec<String> = src
        .split('"')
        .skip(1)
        .step_by(2)
        .filter_map(|lit| {
            let name = lit.strip_prefix("cargo::rustc-env=").unwrap_or(lit);
            let name = name.split('=').next().unwrap_or(name);
            let is_name = name.starts_with("CROWDMORPH_")
                && name.len() > "CROWDMORPH_".len()
                && name
                    .bytes()
                    .all(|b| b.is_ascii_uppercase() || b.is_ascii_digit() || b == b'_');
            is_name.then(|| name.to_string())
        })
        .collect();
    names.sort();
    names.dedup();
    names
}

/// Every `.rs` file of the repository (the crate, its tests, the clients, build.rs), build
/// outputs and dependencies left out.
fn repository_rust_files() -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![root().to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).expect("read_dir") {
            let p = e.expect("entry").path();
            let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
            if p.is_dir() {
                if !matches!(name, "target" | "node_modules" | ".git" | ".venv") {
                    stack.push(p);
                }
            } else if name.ends_with(".rs") {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// Issue 49: `env!` is evaluated when the crate compiles, so a test reading a variable that
/// `build.rs` sets only where it found a program stopped the whole suite from building on a
/// machine without that program, instead of listing the test as ignored with its reason.
/// Such a variable is read with `option_env!`; `env!` is left to what cargo always sets.
#[test]
fn no_code_reads_a_variable_the_build_may_leave_unset_with_env() {
    let conditional = build_script_variables();
    for expected in [
        "CROWDMORPH_NGINX_PATH",
        "CROWDMORPH_HAPROXY_PATH",
        "CROWDMORPH_WEED_PATH",
        "CROWDMORPH_CHROMIUM_PATH",
    ] {
        assert!(
            conditional.iter().any(|n| n == expected),
            "the scan of build.rs finds {expected}: {conditional:?}"
        );
    }
    // Spelled in two pieces so that this file's own literal is not a use.
    let mac = concat!("env", "!(");
    let mut offenders = Vec::new();
    let files = repository_rust_files();
    assert!(
        files.len() > 100,
        "the scan finds the sources ({})",
        files.len()
    );
    for f in files {
        let code = code_only(&read(&f));
        for (at, _) in code.match_indices(mac) {
            // `option_env!(` ends in the same bytes: only a bare `env!` is a compile-time must.
            let before = code[..at].chars().next_back();
            if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
                continue;
            }
            let args = code[at + mac.len()..].trim_start();
            let Some(name) = args
                .strip_prefix('"')
                .and_then(|rest| rest.split('"').next())
            else {
                continue;
            };
            // Cargo sets these for every compilation of a package.
            let always = name.starts_with("CARGO_") || name == "OUT_DIR";
            if !always || conditional.iter().any(|n| n == name) {
                let line = code[..at].lines().count();
                offenders.push(format!("{}:{line}: env!(\"{name}\")", f.display()));
            }
        }
    }
    assert!(
        offenders.is_empty(),
        "read these with option_env! (build.rs sets them only where it finds the program, \
         and env! stops the whole suite from compiling without it): {offenders:#?}"
    );
}
