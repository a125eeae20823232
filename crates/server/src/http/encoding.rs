//! HTTP `Content-Encoding` both ways. A response large enough to gain is compressed, with
//! tower-http's layer, with zstd (preferred) or gzip when the request's `Accept-Encoding` asks
//! for it, at the fastest level (zstd 1, gzip 1: the server compresses every response once, and
//! vertex buffers gain most from the residual formats, not from a slower level). A request
//! whose `Accept-Encoding` accepts neither (`identity;q=0`, `*;q=0`, `br`) gets the identity
//! encoding: RFC 9110 (§12.1, §12.5.3) lets a server disregard a preference it cannot meet, and
//! the plain bytes serve such a client better than a 406 on every route (tower-http answered
//! one carrying the success body).
//!
//! A request body sent with `Content-Encoding: zstd` or `gzip` (`x-gzip` too; codings are
//! case-insensitive) is inflated as it is read ([`inflate_request`]), every member of a gzip
//! body and every frame of a zstd one, so the body limits apply to the inflated bytes and a
//! bomb stops at the limit (413) without being inflated further. Any other request encoding is
//! a 415 that names it. A client that asks for nothing gets the plain bytes.
//!
//! What an encoder holds while it compresses one response ([`encoder_bytes`]) is charged by the
//! router before the response is made (`app.rs`); when it cannot be, the response goes out
//! plain. What a decoder holds ([`decoder_bytes`]) is charged by the router before the body is
//! read: a zstd frame's window is whatever its header asks for, so the decoder takes at most
//! RFC 9659's 8 MiB ([`ZSTD_WINDOW_LOG_MAX`]) and refuses a frame that wants more.

use std::io::Write;
use std::pin::Pin;
use std::task::{Context, Poll, ready};

use axum::body::Body;
use axum::extract::Request;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use bytes::{Buf, Bytes};
use tower_http::CompressionLevel;
use tower_http::compression::predicate::{NotForContentType, Predicate, SizeAbove};
use tower_http::compression::{CompressionLayer, DefaultPredicate};
use zstd::stream::raw::{InBuffer, Operation, OutBuffer};

use super::error::ApiError;

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

/// The largest zstd window a request body may use, as a power of two: 8 MiB, the limit RFC
/// 9659 sets for zstd in HTTP (libzstd would otherwise allocate up to 128 MiB for a frame
/// whose header asks for it).
pub const ZSTD_WINDOW_LOG_MAX: u32 = 23;

/// Memory a decoder of a request body with these headers holds while the body is read, for
/// the router's charge: zstd's window at its cap plus its context (about 160 KiB), deflate's
/// 32 KiB window and state; `None` for a body sent plain (or with a refused coding).
pub fn decoder_bytes(headers: &HeaderMap) -> Option<u64> {
    match request_coding(headers) {
        Ok(Coding::Zstd) => Some((1 << ZSTD_WINDOW_LOG_MAX) + (256 << 10)),
        Ok(Coding::Gzip) => Some(64 << 10),
        Ok(Coding::Identity) | Err(_) => None,
    }
}

/// A request body's content coding.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Coding {
    Identity,
    Gzip,
    Zstd,
}

/// The coding of a request's body from its `Content-Encoding` (none: identity), or the value
/// it refuses: one coding of `zstd`, `gzip` (or `x-gzip`) and `identity`, in any case.
fn request_coding(headers: &HeaderMap) -> Result<Coding, String> {
    let mut values = headers.get_all(header::CONTENT_ENCODING).iter();
    let (Some(value), None) = (values.next(), values.next()) else {
        return match headers.get_all(header::CONTENT_ENCODING).iter().count() {
            0 => Ok(Coding::Identity),
            n => Err(format!("{n} Content-Encoding headers")),
        };
    };
    let text = String::from_utf8_lossy(value.as_bytes());
    match text.trim().to_ascii_lowercase().as_str() {
        "identity" | "" => Ok(Coding::Identity),
        "gzip" | "x-gzip" => Ok(Coding::Gzip),
        "zstd" => Ok(Coding::Zstd),
        _ => Err(crowdmorph_core::rig::quoted_name(&text)),
    }
}

/// Inflates a zstd or gzip request body as the handler reads it (the header and the
/// compressed length go: the body limits then count inflated bytes); refuses any other
/// `Content-Encoding` with a 415 that names it and lists the codings taken.
pub async fn inflate_request(req: Request, next: Next) -> Response {
    let coding = match request_coding(req.headers()) {
        Ok(c) => c,
        Err(refused) => {
            let mut resp = ApiError::new(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "unsupported_media_type",
                format!(
                    "Content-Encoding {refused} is not supported: send the body plain, or with \
                     zstd or gzip (x-gzip)"
                ),
            )
            .into_response();
            resp.headers_mut().insert(
                header::ACCEPT_ENCODING,
                HeaderValue::from_static("zstd, gzip"),
            );
            return resp;
        }
    };
    let decoder = match coding {
        Coding::Identity => return next.run(req).await,
        Coding::Gzip => Decoder::Gzip(Box::new(flate2::write::MultiGzDecoder::new(Vec::new()))),
        // Not `whole` before any input: an empty body is no zstd stream.
        Coding::Zstd => {
            let made = zstd::stream::raw::Decoder::new().and_then(|mut d| {
                d.set_parameter(zstd::stream::raw::DParameter::WindowLogMax(
                    ZSTD_WINDOW_LOG_MAX,
                ))
                .map(|()| d)
            });
            match made {
                Ok(d) => Decoder::Zstd { d, whole: false },
                Err(e) => return ApiError::internal(e).into_response(),
            }
        }
    };
    let (mut parts, body) = req.into_parts();
    parts.headers.remove(header::CONTENT_ENCODING);
    parts.headers.remove(header::CONTENT_LENGTH);
    let body = Body::new(Inflate {
        body,
        decoder,
        input: Bytes::new(),
        ended: false,
        done: false,
    });
    next.run(Request::from_parts(parts, body)).await
}

/// Most inflated bytes one frame of an [`Inflate`] body holds: the body limit is checked
/// between frames, so a bomb inflates at most this far past it.
const INFLATED_FRAME: usize = 64 << 10;

/// The decoder of an [`Inflate`] body.
enum Decoder {
    /// Every member of the stream (RFC 1952 allows several, and `cat a.gz b.gz` makes them).
    Gzip(Box<flate2::write::MultiGzDecoder<Vec<u8>>>),
    /// Every frame of the stream (libzstd's streaming decoder goes on to the next frame);
    /// `whole` is whether the last frame begun has ended.
    Zstd {
        d: zstd::stream::raw::Decoder<'static>,
        whole: bool,
    },
}

impl Decoder {
    /// Inflates from the front of `input` (taking what it consumed off it) until it has some
    /// output, at most about [`INFLATED_FRAME`] bytes, or needs more input.
    fn step(&mut self, input: &mut Bytes) -> std::io::Result<Vec<u8>> {
        match self {
            Decoder::Gzip(d) => {
                // Each write inflates into flate2's 32 KiB buffer and hands the previous one's
                // output to the vector: output grows by at most that per write.
                while !input.is_empty() && d.get_ref().len() < INFLATED_FRAME {
                    let n = d.write(input)?;
                    if n == 0 {
                        return Err(std::io::Error::new(
                            std::io::ErrorKind::InvalidData,
                            "the gzip stream takes no more input",
                        ));
                    }
                    input.advance(n);
                }
                Ok(std::mem::take(d.get_mut()))
            }
            Decoder::Zstd { d, whole } => {
                let mut out = vec![0u8; INFLATED_FRAME];
                let mut inb = InBuffer::around(input);
                let mut outb = OutBuffer::around(&mut out[..]);
                let hint = d.run(&mut inb, &mut outb)?;
                let (used, made) = (inb.pos(), outb.pos());
                if used == 0 && made == 0 {
                    return Err(std::io::Error::new(
                        std::io::ErrorKind::InvalidData,
                        "the zstd stream takes no more input",
                    ));
                }
                input.advance(used);
                *whole = hint == 0;
                out.truncate(made);
                Ok(out)
            }
        }
    }

    /// Once the input has ended: output still buffered, and whether there may be more (call
    /// again), or an error if the stream was cut short.
    fn finish(&mut self) -> std::io::Result<(Vec<u8>, bool)> {
        match self {
            Decoder::Gzip(d) => {
                // Checks the last member's trailer (CRC and length) and hands over the rest.
                d.try_finish()?;
                Ok((std::mem::take(d.get_mut()), false))
            }
            Decoder::Zstd { d, whole } => {
                // A frame that ended is decoded and flushed whole; a fresh one would now ask
                // for the next frame's header, which is not a missing part.
                if *whole {
                    return Ok((Vec::new(), false));
                }
                let mut out = vec![0u8; INFLATED_FRAME];
                let mut outb = OutBuffer::around(&mut out[..]);
                let hint = d.run(&mut InBuffer::around(&[]), &mut outb)?;
                let made = outb.pos();
                *whole = hint == 0;
                if made == 0 && !*whole {
                    return Err(std::io::Error::new(
                        std::io::ErrorKind::UnexpectedEof,
                        "the zstd stream ends inside a frame",
                    ));
                }
                out.truncate(made);
                Ok((out, made > 0))
            }
        }
    }
}

/// A request body inflated as it is read, one bounded frame at a time.
struct Inflate {
    body: Body,
    decoder: Decoder,
    /// Compressed bytes received and not yet inflated.
    input: Bytes,
    /// The compressed body has ended.
    ended: bool,
    /// Everything has been inflated.
    done: bool,
}

impl http_body::Body for Inflate {
    type Data = Bytes;
    type Error = std::io::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, Self::Error>>> {
        let this = &mut *self;
        loop {
            if this.done {
                return Poll::Ready(None);
            }
            if !this.input.is_empty() {
                let out = this.decoder.step(&mut this.input)?;
                if !out.is_empty() {
                    return Poll::Ready(Some(Ok(http_body::Frame::data(Bytes::from(out)))));
                }
                continue;
            }
            if this.ended {
                let (out, more) = this.decoder.finish()?;
                this.done = !more;
                if out.is_empty() {
                    continue;
                }
                return Poll::Ready(Some(Ok(http_body::Frame::data(Bytes::from(out)))));
            }
            match ready!(Pin::new(&mut this.body).poll_frame(cx)) {
                // Trailers of a compressed request carry nothing the server reads.
                Some(Ok(frame)) => this.input = frame.into_data().unwrap_or_default(),
                Some(Err(e)) => return Poll::Ready(Some(Err(std::io::Error::other(e)))),
                None => this.ended = true,
            }
        }
    }

    fn is_end_stream(&self) -> bool {
        self.done
    }
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

    /// `bytes` through an [`Inflate`] body fed `chunk` bytes at a time.
    fn inflated(coding: Coding, bytes: &[u8], chunk: usize) -> std::io::Result<Vec<u8>> {
        use http_body_util::BodyExt;
        let decoder = match coding {
            Coding::Gzip => Decoder::Gzip(Box::new(flate2::write::MultiGzDecoder::new(Vec::new()))),
            Coding::Zstd => Decoder::Zstd {
                d: zstd::stream::raw::Decoder::new()?,
                whole: false,
            },
            Coding::Identity => unreachable!("identity bodies are not wrapped"),
        };
        let chunks: Vec<Result<http_body::Frame<Bytes>, std::io::Error>> = bytes
            .chunks(chunk.max(1))
            .map(|c| Ok(http_body::Frame::data(Bytes::copy_from_slice(c))))
            .collect();
        let body = Body::new(http_body_util::StreamBody::new(futures_util::stream::iter(
            chunks,
        )));
        let mut inflate = Inflate {
            body,
            decoder,
            input: Bytes::new(),
            ended: false,
            done: false,
        };
        let mut out = Vec::new();
        let rt = tokio::runtime::Builder::new_current_thread()
            .build()
            .expect("runtime");
        rt.block_on(async {
            while let Some(frame) = inflate.frame().await {
                let data = frame?.into_data().unwrap_or_default();
                assert!(
                    data.len() <= 2 * INFLATED_FRAME,
                    "a frame of {}",
                    data.len()
                );
                out.extend_from_slice(&data);
            }
            Ok::<_, std::io::Error>(())
        })?;
        Ok(out)
    }

    #[test]
    fn bodies_inflate_whole_whatever_their_members_frames_and_chunks() {
        let text: Vec<u8> = (0..300_000u32)
            .flat_map(|i| (i % 251).to_le_bytes())
            .collect();
        let gz = |b: &[u8]| {
            let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
            e.write_all(b).expect("gzip");
            e.finish().expect("gzip")
        };
        let (a, b) = text.split_at(123_457);
        let mut members = gz(a);
        members.extend(gz(b""));
        members.extend(gz(b));
        let mut frames = zstd::bulk::compress(a, 1).expect("zstd");
        frames.extend(zstd::bulk::compress(b, 1).expect("zstd"));
        for chunk in [1, 7, 4096, 1 << 20] {
            for (coding, bytes) in [(Coding::Gzip, &members), (Coding::Zstd, &frames)] {
                let got = inflated(coding, bytes, chunk).expect("inflates");
                assert!(got == text, "{coding:?} in chunks of {chunk}");
                // Cut anywhere inside the last member or frame: an error, never a short body.
                for cut in [1, 5, bytes.len() / 3] {
                    let short = &bytes[..bytes.len() - cut];
                    assert!(
                        inflated(coding, short, chunk).is_err(),
                        "{coding:?} cut by {cut} in chunks of {chunk}"
                    );
                }
            }
        }
        assert!(inflated(Coding::Zstd, b"", 1).is_err());
        assert!(inflated(Coding::Gzip, b"", 1).is_err());
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
