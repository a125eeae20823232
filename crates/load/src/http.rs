//! Lanes that are HTTP/1.1 connections: `crowdmorph load` against a server's
//! `POST /v1/crowd/frame`, with hyper's client connection driven directly (one connection per
//! lane, no pool), so that `--connections N` means exactly N sockets.
//!
//! A response body is counted as it streams in and dropped, never kept or decoded (the
//! generator should take as little CPU from a server on the same machine as it can); only an
//! error body is read, for its code. The server's timings come from its `Server-Timing` header.

use std::sync::Arc;

use bytes::Bytes;
use http_body_util::Full;
use hyper::client::conn::http1::SendRequest;
use hyper::header::{ACCEPT, CONTENT_TYPE, HOST};
use hyper_util::rt::TokioIo;

use super::{Lane, LoadError, Reply, WireEncoding};

/// Where to send and what.
#[derive(Debug)]
pub struct HttpTarget {
    /// `host:port`.
    authority: String,
    bodies: Arc<Vec<Bytes>>,
    /// The path of each body: `/v1/crowd/frame`, with the `?rig=` hint when it has one.
    paths: Arc<Vec<String>>,
    encoding: WireEncoding,
}

/// `host:port` of an `http://` URL (port 80 when it names none).
pub fn authority_of(url: &str) -> Result<String, LoadError> {
    let uri: hyper::Uri = url
        .parse()
        .map_err(|e| LoadError::Invalid(format!("{url:?} is not a URL: {e}")))?;
    match uri.scheme_str() {
        Some("http") => {}
        Some(other) => {
            return Err(LoadError::Invalid(format!(
                "only http:// URLs are supported, not {other}://"
            )));
        }
        None => {
            return Err(LoadError::Invalid(format!(
                "{url:?} needs a scheme: http://HOST:PORT"
            )));
        }
    }
    let host = uri
        .host()
        .ok_or_else(|| LoadError::Invalid(format!("{url:?} names no host")))?;
    Ok(format!("{host}:{}", uri.port_u16().unwrap_or(80)))
}

impl HttpTarget {
    /// A target at `url` (`http://host:port`) sending `bodies` (request `i` sends body
    /// `i mod len`) in `encoding`.
    pub fn new(
        url: &str,
        bodies: Vec<Bytes>,
        encoding: WireEncoding,
    ) -> Result<Arc<HttpTarget>, LoadError> {
        let bodies = bodies.into_iter().map(|b| (b, String::new())).collect();
        Self::with_rig_hints(url, bodies, encoding)
    }

    /// [`HttpTarget::new`] with each body's rig sent as `?rig=` (the clients' routing hint,
    /// so that a balancer keeps each rig on one replica); an empty rig sends none.
    pub fn with_rig_hints(
        url: &str,
        bodies: Vec<(Bytes, String)>,
        encoding: WireEncoding,
    ) -> Result<Arc<HttpTarget>, LoadError> {
        if bodies.is_empty() {
            return Err(LoadError::Invalid("no request bodies".into()));
        }
        let (bodies, paths): (Vec<Bytes>, Vec<String>) = bodies
            .into_iter()
            .map(|(b, rig)| {
                (
                    b,
                    crowdmorph_proto::with_rig_hint("/v1/crowd/frame", Some(&rig)),
                )
            })
            .unzip();
        Ok(Arc::new(HttpTarget {
            authority: authority_of(url)?,
            bodies: Arc::new(bodies),
            paths: Arc::new(paths),
            encoding,
        }))
    }

    async fn connect(&self) -> Result<SendRequest<Full<Bytes>>, LoadError> {
        let tcp = tokio::net::TcpStream::connect(&self.authority)
            .await
            .map_err(|source| LoadError::Connect {
                addr: self.authority.clone(),
                source,
            })?;
        // Requests are small and latency is what is measured: no Nagle delay.
        let _ = tcp.set_nodelay(true);
        let (sender, conn) = hyper::client::conn::http1::handshake(TokioIo::new(tcp))
            .await
            .map_err(|e| LoadError::Http(e.to_string()))?;
        tokio::spawn(async move {
            // The connection ends when the lane drops its sender or the server closes it.
            let _ = conn.await;
        });
        Ok(sender)
    }

    /// Opens `n` lanes (at least one), each its own connection.
    pub async fn lanes(self: &Arc<Self>, n: usize) -> Result<Vec<HttpLane>, LoadError> {
        let mut lanes = Vec::with_capacity(n.max(1));
        for _ in 0..n.max(1) {
            lanes.push(self.lane().await?);
        }
        Ok(lanes)
    }

    /// Opens one lane (one connection, opened now so that a wrong address fails before the
    /// run starts).
    pub async fn lane(self: &Arc<Self>) -> Result<HttpLane, LoadError> {
        let sender = self.connect().await?;
        Ok(HttpLane {
            target: self.clone(),
            sender: Some(sender),
        })
    }
}

/// One connection; it reconnects on the next request after its connection failed.
#[derive(Debug)]
pub struct HttpLane {
    target: Arc<HttpTarget>,
    sender: Option<SendRequest<Full<Bytes>>>,
}

fn failed(code: &str) -> Reply {
    Reply {
        status: 0,
        code: Some(code.to_string()),
        ..Reply::default()
    }
}

impl HttpLane {
    async fn exchange(&mut self, i: u64) -> Reply {
        let t = &self.target;
        let mut sender = match self.sender.take() {
            Some(s) if !s.is_closed() => s,
            _ => match t.connect().await {
                Ok(s) => s,
                Err(_) => return failed("connect"),
            },
        };
        if sender.ready().await.is_err() {
            return failed("transport");
        }
        let at = (i % t.bodies.len() as u64) as usize;
        let body = t.bodies[at].clone();
        let ct = t.encoding.content_type();
        let Ok(req) = hyper::Request::post(t.paths[at].as_str())
            .header(HOST, &t.authority)
            .header(CONTENT_TYPE, ct)
            .header(ACCEPT, ct)
            .body(Full::new(body))
        else {
            return failed("request");
        };
        let resp = match sender.send_request(req).await {
            Ok(r) => r,
            Err(_) => return failed("transport"),
        };
        let (reply, complete) = super::read_reply(resp).await;
        if !complete {
            return failed("transport");
        }
        self.sender = Some(sender);
        reply
    }
}

impl Lane for HttpLane {
    async fn send(&mut self, i: u64) -> Reply {
        self.exchange(i).await
    }
}

#[cfg(test)]
mod tests {
    // A test that meets an unexpected error should fail loudly.
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn each_body_carries_its_rig_as_a_hint() {
        let t = HttpTarget::with_rig_hints(
            "http://127.0.0.1:1",
            vec![
                (Bytes::new(), "ict0".into()),
                (Bytes::new(), "a b/c".into()),
                (Bytes::new(), String::new()),
            ],
            WireEncoding::Bincode,
        )
        .unwrap();
        assert_eq!(
            *t.paths,
            [
                "/v1/crowd/frame?rig=ict0",
                "/v1/crowd/frame?rig=a%20b%2Fc",
                "/v1/crowd/frame"
            ]
        );
    }

    #[test]
    fn urls_become_authorities() {
        assert_eq!(
            authority_of("http://127.0.0.1:8080").unwrap(),
            "127.0.0.1:8080"
        );
        assert_eq!(authority_of("http://localhost/v1").unwrap(), "localhost:80");
        assert!(
            authority_of("https://x:1")
                .unwrap_err()
                .to_string()
                .contains("only http://")
        );
        assert!(
            authority_of("127.0.0.1:8080")
                .unwrap_err()
                .to_string()
                .contains("scheme")
        );
    }
}
