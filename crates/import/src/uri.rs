//! Files a `.gltf` names beside itself (buffers and images, read on the command line only:
//! the server takes self-contained files): glTF URIs are percent-encoded relative references,
//! and one that is absolute or climbs out of the file's folder is refused.

use std::path::{Component, Path};

/// The file a relative URI names beside a `.gltf` in `base`, refused when it is absolute or
/// climbs out of that folder.
pub(crate) fn resolve_relative(base: &Path, uri: &str) -> Result<std::path::PathBuf, String> {
    let decoded = percent_decode(uri);
    let rel = Path::new(&decoded);
    if rel
        .components()
        .any(|c| !matches!(c, Component::Normal(_) | Component::CurDir))
    {
        return Err(format!(
            "external path {uri:?} must be relative and stay in the file's folder"
        ));
    }
    Ok(base.join(rel))
}

/// `s` with its `%XX` escapes decoded (invalid UTF-8 replaced).
fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let hex = |c: u8| (c as char).to_digit(16);
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%'
            && i + 2 < b.len()
            && let (Some(h), Some(l)) = (hex(b[i + 1]), hex(b[i + 2]))
        {
            out.push((h * 16 + l) as u8);
            i += 3;
            continue;
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}
