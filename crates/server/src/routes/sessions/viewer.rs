//! A session viewer's WebSocket: its hello and updates checked (a bad one closes it with
//! 1008 and the reason), then its socket loop, which sends what its one-message outbox gets
//! and reads its updates.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use axum::extract::ws::{CloseFrame, Message, WebSocket};
use crowdmorph_proto::{
    CameraSpec, DEFAULT_KEYFRAME_EVERY, Format, ImageFormat, ImageOptions, MAX_KEYFRAME_EVERY,
    MAX_VIEWER_TOLERANCE, ViewerHello, ViewerOutput, ViewerUpdate,
};
use tokio::time::Instant;

use crate::sessions::{
    CLOSE_TIMEOUT, MAX_VIEWER_MESSAGE_BYTES, Session, SessionLimits, Viewer, ViewerSettings, bump,
    close,
};
use crate::state::AppState;
use crowdmorph_engine::render::scene;

async fn close_with(socket: &mut WebSocket, code: u16, reason: &str) {
    let frame = CloseFrame {
        code,
        reason: reason.into(),
    };
    let _ = tokio::time::timeout(CLOSE_TIMEOUT, socket.send(Message::Close(Some(frame)))).await;
}

/// Reads the hello; `Err` is the close code and reason.
async fn read_hello(
    socket: &mut WebSocket,
    limits: &SessionLimits,
) -> Result<ViewerSettings, (u16, String)> {
    let timeout = limits.hello_timeout;
    let msg = match tokio::time::timeout(timeout, socket.recv()).await {
        Err(_) => {
            return Err((
                close::POLICY,
                format!("no hello within {:.1} s", timeout.as_secs_f64()),
            ));
        }
        Ok(None) => return Err((close::NORMAL, String::new())),
        Ok(Some(Err(e))) => return Err(socket_error(&e)),
        Ok(Some(Ok(m))) => m,
    };
    let text = match msg {
        Message::Text(t) => t,
        Message::Close(_) => return Err((close::NORMAL, String::new())),
        _ => {
            return Err((
                close::POLICY,
                "the first message must be a JSON hello (text)".into(),
            ));
        }
    };
    let hello: ViewerHello = parse_json(text.as_str(), "hello")?;
    crate::sessions::check_lod(&hello.lod)?;
    let temporal = check_modes(&hello)?;
    let image = hello.image.unwrap_or(ImageOptions {
        format: ImageFormat::Jpeg,
        quality: 80,
        ..ImageOptions::default()
    });
    crowdmorph_engine::render::encode::check_image(&image, crowdmorph_proto::MAX_IMAGE_SIDE)
        .map_err(|e| (close::POLICY, close::truncate(format!("bad image: {e}"))))?;
    let pixels = u64::from(image.width) * u64::from(image.height);
    if hello.output == ViewerOutput::Frames && pixels > limits.max_viewer_pixels {
        return Err((
            close::POLICY,
            close::truncate(format!(
                "bad image: {}x{} is more than {} pixels (--max-viewer-pixels)",
                image.width, image.height, limits.max_viewer_pixels
            )),
        ));
    }
    if let Some(c) = &hello.camera {
        check_camera(c, &image)?;
    }
    Ok(ViewerSettings {
        output: hello.output,
        format: hello.format,
        normals: hello.normals,
        camera: hello.camera,
        lod: hello.lod,
        image,
        temporal,
        compression: hello.compression,
        layers: hello.layers,
        tolerance: hello.tolerance.unwrap_or(0.0),
    })
}

/// The hello's residual and compression modes: a viewer that asks for what a session cannot
/// send is told why, not given something else. `Ok` is the keyframe interval of a temporal
/// viewer.
fn check_modes(hello: &ViewerHello) -> Result<Option<u32>, (u16, String)> {
    let refuse = |why: &str| Err((close::POLICY, close::truncate(format!("bad hello: {why}"))));
    if hello.format == Format::Q16R {
        return refuse(
            "format q16r is for crowd frames; sessions send residuals with \"temporal\": \
             true and format q16",
        );
    }
    if hello.format == Format::Weights {
        return refuse(
            "format weights is for crowd frames; a viewer asks for poses with \"output\": \
             \"weights\"",
        );
    }
    if hello.output == ViewerOutput::Weights {
        check_weights(hello).map_err(|why| {
            (
                close::POLICY,
                close::truncate(format!("bad hello: output weights {why}")),
            )
        })?;
        return Ok(None);
    }
    let frames = hello.output == ViewerOutput::Frames;
    if frames && hello.temporal {
        return refuse("temporal residuals are for vertex buffers, not output frames");
    }
    if frames && hello.layers {
        return refuse("layers are for vertex buffers; images already show them");
    }
    if frames && hello.compression.is_some() {
        return refuse("compression is for vertex buffers; images are already compressed");
    }
    if hello.temporal && hello.format != Format::Q16 {
        return refuse(&format!(
            "temporal residuals need format q16 ({} values would not decode bit for bit)",
            hello.format.name()
        ));
    }
    if let Some(t) = hello.tolerance {
        if !(t.is_finite() && (0.0..=MAX_VIEWER_TOLERANCE).contains(&t)) {
            return refuse(&format!(
                "tolerance {t} must be a finite number in 0..={MAX_VIEWER_TOLERANCE} (a \
                 fraction of the rig's diagonal per metre from the camera)"
            ));
        }
        if frames {
            return refuse("tolerance is for vertex buffers; images are drawn from exact poses");
        }
    }
    match (hello.temporal, hello.keyframe_every) {
        (false, Some(_)) => refuse("keyframe_every is for temporal viewers"),
        (true, Some(n)) if !(1..=MAX_KEYFRAME_EVERY).contains(&n) => refuse(&format!(
            "keyframe_every must be 1..={MAX_KEYFRAME_EVERY}, not {n}"
        )),
        (true, n) => Ok(Some(n.unwrap_or(DEFAULT_KEYFRAME_EVERY))),
        (false, None) => Ok(None),
    }
}

/// What a viewer asking for poses may not ask for besides: they are the heads' whole poses
/// (no LOD level cuts them), with no vertices to format, give normals of, code as residuals
/// or draw layers on. `Err` is the end of the reason.
fn check_weights(hello: &ViewerHello) -> Result<(), &'static str> {
    if hello.format != Format::F32 {
        return Err("has no vertex format (leave format out)");
    }
    if hello.normals {
        return Err("has no normals");
    }
    if hello.temporal || hello.keyframe_every.is_some() {
        return Err("has no temporal residuals (an unchanged head is already marked unchanged)");
    }
    if hello.layers {
        return Err("has no layer inputs (a viewer that blends itself has the weights)");
    }
    if hello.tolerance.is_some() {
        return Err("is each head's exact pose: no tolerance (leave tolerance out)");
    }
    if hello.lod != crowdmorph_proto::LodChoice::Fixed(0) {
        return Err("is each head's whole pose: no LOD level (leave lod out)");
    }
    Ok(())
}

fn socket_error(e: &axum::Error) -> (u16, String) {
    let text = e.to_string();
    if text.contains("too long") || text.contains("Space limit") || text.contains("size") {
        (
            close::TOO_BIG,
            format!("messages are limited to {MAX_VIEWER_MESSAGE_BYTES} bytes"),
        )
    } else {
        (close::POLICY, close::truncate(text))
    }
}

fn parse_json<T: serde::de::DeserializeOwned>(text: &str, what: &str) -> Result<T, (u16, String)> {
    let mut de = serde_json::Deserializer::from_str(text);
    let value: T = serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let path = e.path().to_string();
        (
            close::POLICY,
            close::truncate(format!("bad {what} at {path}: {}", e.into_inner())),
        )
    })?;
    de.end()
        .map_err(|e| (close::POLICY, close::truncate(format!("bad {what}: {e}"))))?;
    Ok(value)
}

/// Checks a viewer's camera as the renderer will use it, at its image's aspect: the checks of
/// `POST /v1/crowd/render` (range, a finite and invertible projection), so a camera that
/// could never draw is refused at the hello or update, not found out at every tick.
fn check_camera(c: &CameraSpec, image: &ImageOptions) -> Result<(), (u16, String)> {
    let aspect = image.width.max(1) as f32 / image.height.max(1) as f32;
    scene::layout(&[], None, &[], None, Some(c), aspect)
        .map(|_| ())
        .map_err(|e| (close::POLICY, close::truncate(format!("bad camera: {e}"))))
}

/// Runs one viewer until it leaves, breaks a rule or the session ends.
pub(super) async fn serve_viewer(state: AppState, session: Arc<Session>, mut socket: WebSocket) {
    let settings = match read_hello(&mut socket, &state.config.sessions).await {
        Ok(s) => s,
        Err((code, reason)) => {
            if code == close::POLICY || code == close::TOO_BIG {
                bump(&state.sessions.metrics.viewers_closed_policy, 1);
            }
            finish(&mut socket, code, &reason).await;
            return;
        }
    };
    if session.stopped.load(Ordering::Acquire) {
        close_with(&mut socket, close::AWAY, "session ended").await;
        return;
    }
    let viewer = Arc::new(Viewer::new(settings));
    let admitted = {
        let mut i = match session.inner.lock() {
            Ok(i) => i,
            Err(_) => return,
        };
        if i.viewers.len() >= state.config.sessions.max_viewers {
            false
        } else {
            i.viewers.push(viewer.clone());
            i.next_viewer += 1;
            i.idle_since = None;
            session.viewers_changed.notify_one();
            true
        }
    };
    if !admitted {
        bump(&state.sessions.metrics.viewers_refused, 1);
        let reason = format!(
            "the session has {} viewers, the most it takes (--max-session-viewers)",
            state.config.sessions.max_viewers
        );
        close_with(&mut socket, close::AGAIN, &reason).await;
        return;
    }
    let (code, reason) = viewer_loop(&state, &session, &viewer, &mut socket).await;
    // An image still rendering for it stops at its next stage.
    viewer.gone.cancel();
    if let Ok(mut i) = session.inner.lock() {
        i.viewers.retain(|v| !Arc::ptr_eq(v, &viewer));
        if i.viewers.is_empty() {
            i.idle_since = Some(Instant::now());
            session.viewers_changed.notify_one();
        }
    }
    if code == close::POLICY || code == close::TOO_BIG {
        bump(&state.sessions.metrics.viewers_closed_policy, 1);
    }
    finish(&mut socket, code, &reason).await;
}

/// Ends a viewer's socket: after the viewer's own close (1000, no reason) the WebSocket library
/// has queued the 1000 reply, and a second close would be refused, so that is only flushed out;
/// code 0 means the socket is gone; anything else is the server's close.
async fn finish(socket: &mut WebSocket, code: u16, reason: &str) {
    if code == close::NORMAL && reason.is_empty() {
        let _ = tokio::time::timeout(CLOSE_TIMEOUT, futures_util::SinkExt::flush(socket)).await;
    } else if code != 0 {
        close_with(socket, code, reason).await;
    }
}

/// A viewer's update (`{"camera": ...}` and/or `{"lod": ...}`), checked as a hello is and used
/// from the next tick; `Err` is the close.
fn apply_update(viewer: &Viewer, text: &str) -> Result<(), (u16, String)> {
    let update: ViewerUpdate = parse_json(text, "update")?;
    if let Some(c) = &update.camera
        && let Some(s) = viewer.settings()
    {
        check_camera(c, &s.image)?;
    }
    if let Some(l) = &update.lod {
        crate::sessions::check_lod(l)?;
        if *l != crowdmorph_proto::LodChoice::Fixed(0)
            && viewer
                .settings()
                .is_some_and(|s| s.output == ViewerOutput::Weights)
        {
            return Err((
                close::POLICY,
                "bad update: output weights is each head's whole pose: no LOD level".into(),
            ));
        }
    }
    if let Ok(mut s) = viewer.settings.lock() {
        if let Some(c) = update.camera {
            s.camera = Some(c);
        }
        if let Some(l) = update.lod {
            s.lod = l;
        }
    }
    Ok(())
}

/// The viewer's socket loop: sends what its outbox gets, reads its updates. Returns the close
/// to send (code 0: none, the socket is gone).
async fn viewer_loop(
    state: &AppState,
    session: &Session,
    viewer: &Viewer,
    socket: &mut WebSocket,
) -> (u16, String) {
    let limit = state.config.sessions.max_viewer_messages.max(1);
    let mut window = Instant::now();
    let mut in_window = 0u32;
    loop {
        if let Some(c) = viewer.close_asked() {
            return c;
        }
        tokio::select! {
            () = viewer.closing.notified() => {}
            () = viewer.ready.notified() => {
                let out = match viewer.outbox.lock() {
                    Ok(mut o) => o.pending.take().map(|p| {
                        o.sent = p.after;
                        (p.layers, p.message)
                    }),
                    Err(_) => return (close::AWAY, "internal error".into()),
                };
                let Some((layers, message)) = out else { continue };
                // The layer inputs first: the head's new vertices draw with them.
                let sends = [layers.as_ref().map(|l| &l.bytes), Some(&message.bytes)];
                for bytes in sends.into_iter().flatten().cloned() {
                    let len = bytes.len() as u64;
                    let send = socket.send(Message::Binary(bytes));
                    tokio::select! {
                        r = send => if r.is_err() { return (0, String::new()) },
                        () = viewer.closing.notified() => {
                            return viewer.close_asked().unwrap_or((close::AWAY, String::new()));
                        }
                    }
                    let m = &state.sessions.metrics;
                    bump(&m.sent, 1);
                    bump(&m.bytes_sent, len);
                    session.with_stats(|s| {
                        s.messages_sent += 1;
                        s.bytes_sent += len;
                    });
                }
                // Their queue memory goes back once they are sent.
                drop((layers, message));
            }
            msg = socket.recv() => {
                let msg = match msg {
                    None => return (0, String::new()),
                    Some(Err(e)) => return socket_error(&e),
                    Some(Ok(m)) => m,
                };
                let now = Instant::now();
                if now.duration_since(window) >= Duration::from_secs(1) {
                    window = now;
                    in_window = 0;
                }
                in_window += 1;
                if in_window > limit {
                    return (
                        close::POLICY,
                        format!("more than {limit} messages per second (--max-viewer-messages)"),
                    );
                }
                match msg {
                    Message::Text(t) => {
                        if let Err(c) = apply_update(viewer, t.as_str()) {
                            return c;
                        }
                    }
                    Message::Binary(_) => {
                        return (close::POLICY, "viewer messages are JSON text".into());
                    }
                    Message::Close(_) => return (close::NORMAL, String::new()),
                    Message::Ping(_) | Message::Pong(_) => {}
                }
            }
        }
    }
}
