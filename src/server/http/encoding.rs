//! HTTP `Content-Encoding` both ways. A response large enough to gain is compressed, with
//! tower-http's layer, with zstd (preferred) or gzip when the request's `Accept-Encoding` asks
//! for it, at the fastest level (zstd 1, gzip 1: the server compresses every response once, and
//! vertex buffers gain most from the residual formats, not from a slower level). A request
//! whose `Accept-Encoding` accepts neither (`identity;q=0`, `*;q=0`, `br`) gets the identity
//! encoding: RFC 9110 (§12.1, §12.5.3) lets a server disregard a preference it cannot meet, and
//! the plain bytes serve such a client better than a 406 on every route (tower-http answered
//! one carrying the success body).
//!
//! A request body sent with `Content-Encoding: zstd` or `gzip` is inflated as it is read, so the
//! body limits apply to the inflated bytes and a bomb stops at the limit (413) without being
//! inflated further. Any other request encoding is 415. A client that asks for nothing gets the
//! plain bytes.
//!
//! What an encoder holds while it compresses one response ([`encoder_bytes`]) is charged by the
//! router before the response is made (`app.rs`); when it cannot be, the response goes out
//! plain.

use axum::http::{HeaderMap, header};
use tower_http::CompressionLevel;
use tower_http::compression::predicate::{NotForContentType, Predicate, SizeAbove};
use tower_http::compression::{CompressionLayer, DefaultPredicate};
use tower_http::decompression::RequestDecompressionLayer;

/// Responses smaller than this go out plain: one packet either way.
pub const MIN_COMPRESSED_BYTES: u64 = 1400;

/// The response encodings the server offers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    /// zstd, level 1.
    Zstd,
    /// gzip (deflate), level 1.
    Gzip,
}

/// Memory one encoder holds while it compresses a response: zstd level 1's streaming context
/// with its window and tables (1.31 MiB measured after 16 MiB through it; `tests`), deflate's 32 KiB window and
/// hash chains (about 300 KiB in miniz_oxide), rounded up.
pub fn encoder_bytes(e: Encoding) -> u64 {
    match e {
        Encoding::Zstd => 2 << 20,
        Encoding::Gzip => 512 << 10,
    }
}

/// The encoding the compression layer may pick for a request: the first of zstd, gzip that
/// its `Accept-Encoding` accepts, by name (`x-gzip` is gzip; names are case-insensitive) or
/// through `*`, with a non-zero quality. `None`: neither, and the response is not compressed
/// (the router then drops the header, so that the layer answers with the identity encoding
/// rather than a 406).
pub fn accepted(headers: &HeaderMap) -> Option<Encoding> {
    // Per coding: the quality its own entry gives it, else the wildcard's.
    let (mut zstd, mut gzip, mut any) = (None, None, None);
    for value in headers.get_all(header::ACCEPT_ENCODING) {
        let Ok(value) = value.to_str() else { continue };
        for item in value.split(',') {
            let mut parts = item.split(';');
            let name = parts.next().unwrap_or("").trim().to_ascii_lowercase();
            let zero = parts.any(|p| {
                p.trim()
                    .strip_prefix("q=")
                    .and_then(|q| q.trim().parse::<f32>().ok())
                    .is_some_and(|q| q <= 0.0)
            });
            match name.as_str() {
                "zstd" => zstd = Some(!zero),
                "gzip" | "x-gzip" => gzip = Some(!zero),
                "*" => any = Some(!zero),
                _ => {}
            }
        }
    }
    let any = any.unwrap_or(false);
    if zstd.unwrap_or(any) {
        Some(Encoding::Zstd)
    } else if gzip.unwrap_or(any) {
        Some(Encoding::Gzip)
    } else {
        None
    }
}

/// Which responses are compressed: tower-http's default (not images, not gRPC, not event
/// streams) above [`MIN_COMPRESSED_BYTES`]; rendered PNG and JPEG frames are already
/// compressed, and raw RGBA frames (`application/octet-stream`) are too big to be worth the
/// CPU on the way to a browser canvas.
pub fn compress_layer() -> CompressionLayer<impl Predicate> {
    let predicate = DefaultPredicate::new()
        .and(SizeAbove::new(MIN_COMPRESSED_BYTES))
        .and(NotForContentType::const_new("image/"))
        .and(NotForContentType::const_new("application/octet-stream"));
    CompressionLayer::new()
        .no_br()
        .no_deflate()
        .quality(CompressionLevel::Fastest)
        .compress_when(predicate)
}

/// Inflates zstd and gzip request bodies; refuses others with 415.
pub fn decompress_layer() -> RequestDecompressionLayer {
    RequestDecompressionLayer::new().no_br().no_deflate()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accept_encoding_picks_zstd_then_gzip_and_honours_zero_quality() {
        let h = |v: &str| {
            let mut m = HeaderMap::new();
            m.insert(header::ACCEPT_ENCODING, v.parse().expect("header"));
            m
        };
        assert_eq!(
            accepted(&h("gzip, deflate, br, zstd")),
            Some(Encoding::Zstd)
        );
        assert_eq!(accepted(&h("gzip;q=0.5")), Some(Encoding::Gzip));
        assert_eq!(accepted(&h("zstd;q=0, gzip")), Some(Encoding::Gzip));
        assert_eq!(accepted(&h("identity")), None);
        assert_eq!(accepted(&HeaderMap::new()), None);
        // The wildcard stands for every coding not named; names are case-insensitive.
        assert_eq!(accepted(&h("*")), Some(Encoding::Zstd));
        assert_eq!(accepted(&h("*, zstd;q=0")), Some(Encoding::Gzip));
        assert_eq!(accepted(&h("zstd;q=0, *;q=0.5")), Some(Encoding::Gzip));
        assert_eq!(accepted(&h("*;q=0, GZIP")), Some(Encoding::Gzip));
        assert_eq!(accepted(&h("x-gzip")), Some(Encoding::Gzip));
        for none in ["*;q=0", "identity;q=0", "br", "*;q=0, zstd;q=0"] {
            assert_eq!(accepted(&h(none)), None, "{none}");
        }
    }

    #[test]
    fn the_zstd_charge_bounds_its_encoder() {
        use zstd::zstd_safe::{CCtx, CParameter, InBuffer, OutBuffer, zstd_sys::ZSTD_EndDirective};
        // A level-1 streaming context after 16 MiB of vertex-like data through it.
        let mut cctx = CCtx::create();
        cctx.set_parameter(CParameter::CompressionLevel(1))
            .expect("level");
        let mut x = 0u32;
        let chunk: Vec<u8> = (0..1 << 20)
            .map(|_| {
                x = x.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                (x >> 24) as u8
            })
            .collect();
        let mut out = vec![0u8; 2 << 20];
        for _ in 0..16 {
            let mut input = InBuffer::around(&chunk);
            while input.pos() < chunk.len() {
                let mut output = OutBuffer::around(&mut out[..]);
                cctx.compress_stream2(&mut output, &mut input, ZSTD_EndDirective::ZSTD_e_continue)
                    .expect("compress");
            }
        }
        let used = cctx.sizeof() as u64;
        assert!(used <= encoder_bytes(Encoding::Zstd), "{used}");
        assert!(used > encoder_bytes(Encoding::Zstd) / 16, "{used}");
    }
}
