//! The API's accept loop. `axum::serve` sets no header time-out and no limits, and hyper
//! answers a request head it cannot parse with an empty body. Here:
//! - every connection is accepted at once and waits (`door`) until its request head is in
//!   and has passed the Host and token checks; at most `MAX_WAITING` wait, a newer one pushes
//!   out the oldest, and one whose head is not in within the time-out is cut;
//! - the head is read and checked here (request line, URI and header sizes, Content-Length,
//!   Transfer-Encoding), so every malformed request gets a JSON error, before hyper sees it;
//! - an admitted request takes one of `max_connections` slots while its handler runs (event
//!   streams have their own cap, `api::StreamSlots`);
//! - one request per connection (no keep-alive), so every request passes the head check.

use std::convert::Infallible;
use std::future::Future;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::extract::ConnectInfo;
use axum::http::StatusCode;
use axum::Router;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, ReadBuf};
use tokio::net::{TcpListener, TcpStream};

use super::door::{Entry, Waiting};

/// Limits on the API's connections.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// For a request's head (here) and its body (`guard::read_body`).
    pub request_timeout: Duration,
}

/// Connections whose request is not in (or not yet checked) at most; more push out the oldest.
pub const MAX_WAITING: usize = 512;
/// A request head's limits: beyond them 431 (headers) or 414 (the target).
const MAX_HEAD_BYTES: usize = 64 * 1024;
const MAX_HEADERS: usize = 64;
const MAX_TARGET_BYTES: usize = 8 * 1024;

/// The connection's place among the waiting ones, for the admission after the token check
/// (`api::admit`).
#[derive(Clone)]
pub struct Admission(pub Arc<Entry>);

/// Serve `app` on `listener` until `shutdown` resolves; then let open connections finish
/// their request (streams end on the daemon's own shutdown) and return.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    limits: Limits,
    shutdown: impl Future<Output = ()>,
) {
    let waiting = Waiting::new(MAX_WAITING);
    let (stop, stopped) = tokio::sync::watch::channel(false);
    // Every connection holds a sender: when all are dropped, every connection has closed.
    let (open, mut all_closed) = tokio::sync::mpsc::channel::<()>(1);
    tokio::pin!(shutdown);
    loop {
        let (stream, peer) = tokio::select! {
            _ = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    // E.g. out of file descriptors: wait instead of spinning.
                    tracing::warn!("API: accept failed: {e}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
        };
        let entry = Arc::new(waiting.enter());
        let app = app.clone();
        let stopped = stopped.clone();
        let open = open.clone();
        tokio::spawn(async move {
            let pushed_out = entry.clone();
            tokio::select! {
                _ = pushed_out.pushed_out() => {
                    tracing::debug!(%peer, "API: a waiting connection pushed out by newer ones");
                }
                _ = connection(stream, peer, app, limits, entry, stopped) => {}
            }
            drop(open);
        });
    }
    let _ = stop.send(true);
    drop(open);
    let _ = all_closed.recv().await;
}

async fn connection(
    mut stream: TcpStream,
    peer: SocketAddr,
    app: Router,
    limits: Limits,
    entry: Arc<Entry>,
    mut stopped: tokio::sync::watch::Receiver<bool>,
) {
    let head = match tokio::time::timeout(limits.request_timeout, read_head(&mut stream)).await {
        Ok(Ok(head)) => head,
        Ok(Err(HeadError::Closed)) => return,
        Ok(Err(HeadError::Refused(status, message))) => {
            tracing::warn!(%peer, status = status.as_u16(), "API: refused: {message}");
            refuse(stream, status, &message).await;
            return;
        }
        Err(_) => {
            tracing::debug!(%peer, "API: no request head within {:?}: cut", limits.request_timeout);
            return;
        }
    };
    let service = hyper::service::service_fn(move |mut request: hyper::Request<Incoming>| {
        request.extensions_mut().insert(ConnectInfo(peer));
        request.extensions_mut().insert(Admission(entry.clone()));
        let mut router = app.clone();
        async move {
            let response = tower::Service::call(&mut router, request).await;
            Ok::<_, Infallible>(response.unwrap_or_else(|never| match never {}))
        }
    });
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder
        .timer(TokioTimer::new())
        .header_read_timeout(limits.request_timeout)
        .keep_alive(false);
    let io = Rewind {
        prefix: head,
        read: 0,
        inner: stream,
    };
    let connection = builder
        .serve_connection(TokioIo::new(io), service)
        .with_upgrades();
    tokio::pin!(connection);
    let served = tokio::select! {
        served = connection.as_mut() => served,
        _ = stopped.changed() => {
            connection.as_mut().graceful_shutdown();
            connection.await
        }
    };
    if let Err(e) = served {
        tracing::debug!(%peer, "API connection ended: {e}");
    }
}

enum HeadError {
    /// The peer closed the connection before sending a whole head.
    Closed,
    Refused(StatusCode, String),
}

/// The bytes read up to the end of the request head (and any body bytes after it), the head
/// checked.
async fn read_head(stream: &mut TcpStream) -> Result<Vec<u8>, HeadError> {
    let mut buffer = Vec::with_capacity(1024);
    let mut chunk = [0u8; 4096];
    loop {
        let n = stream
            .read(&mut chunk)
            .await
            .map_err(|_| HeadError::Closed)?;
        if n == 0 {
            return Err(HeadError::Closed);
        }
        buffer.extend_from_slice(&chunk[..n]);
        if let Some(end) = head_end(&buffer) {
            check_head(&buffer[..end]).map_err(|(s, m)| HeadError::Refused(s, m))?;
            return Ok(buffer);
        }
        if buffer.len() > MAX_HEAD_BYTES {
            return Err(HeadError::Refused(
                StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
                format!("the request's headers are over {MAX_HEAD_BYTES} bytes"),
            ));
        }
    }
}

/// Where the head ends (after its blank line), if it does.
fn head_end(buffer: &[u8]) -> Option<usize> {
    let crlf = buffer
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .map(|i| i + 4);
    let lf = buffer.windows(2).position(|w| w == b"\n\n").map(|i| i + 2);
    match (crlf, lf) {
        (Some(a), Some(b)) => Some(a.min(b)),
        (a, b) => a.or(b),
    }
}

/// What hyper would refuse with an empty body, refused here with a reason.
fn check_head(head: &[u8]) -> Result<(), (StatusCode, String)> {
    let bad = |message: String| (StatusCode::BAD_REQUEST, message);
    if head.len() > MAX_HEAD_BYTES {
        return Err((
            StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
            format!("the request's headers are over {MAX_HEAD_BYTES} bytes"),
        ));
    }
    let mut headers = [httparse::EMPTY_HEADER; MAX_HEADERS];
    let mut request = httparse::Request::new(&mut headers);
    match request.parse(head) {
        Ok(httparse::Status::Complete(_)) => {}
        Ok(httparse::Status::Partial) => {
            return Err(bad("the request head is incomplete".into()));
        }
        Err(httparse::Error::TooManyHeaders) => {
            return Err((
                StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
                format!("more than {MAX_HEADERS} request headers"),
            ))
        }
        Err(e) => {
            return Err(bad(format!(
                "the request line or a header does not parse ({e})"
            )))
        }
    }
    let target = request.path.unwrap_or("");
    if target.len() > MAX_TARGET_BYTES {
        return Err((
            StatusCode::URI_TOO_LONG,
            format!("the request target is over {MAX_TARGET_BYTES} bytes"),
        ));
    }
    if axum::http::Uri::try_from(target).is_err() {
        return Err(bad("the request target is not a valid URI".into()));
    }
    if request
        .method
        .is_some_and(|m| axum::http::Method::from_bytes(m.as_bytes()).is_err())
    {
        return Err(bad("the method is not a valid token".into()));
    }
    fn values<'b>(headers: &[httparse::Header<'b>], name: &str) -> Vec<&'b [u8]> {
        headers
            .iter()
            .filter(|h| h.name.eq_ignore_ascii_case(name))
            .map(|h| h.value)
            .collect()
    }
    let lengths = values(request.headers, "content-length");
    let mut length = None;
    for value in &lengths {
        let text = std::str::from_utf8(value).unwrap_or("").trim();
        let parsed = (!text.is_empty() && text.bytes().all(|b| b.is_ascii_digit()))
            .then(|| text.parse::<u64>().ok())
            .flatten()
            .ok_or_else(|| bad("Content-Length is not a number".into()))?;
        if length.is_some_and(|l| l != parsed) {
            return Err(bad("several Content-Length headers that differ".into()));
        }
        length = Some(parsed);
    }
    let codings = values(request.headers, "transfer-encoding");
    if !codings.is_empty() {
        if !lengths.is_empty() {
            return Err(bad(
                "both Content-Length and Transfer-Encoding: send one".into()
            ));
        }
        let last = codings
            .last()
            .and_then(|v| std::str::from_utf8(v).ok())
            .and_then(|v| v.rsplit(',').next())
            .map(|v| v.trim().to_ascii_lowercase());
        if last.as_deref() != Some("chunked") {
            return Err(bad("a Transfer-Encoding must end in chunked".into()));
        }
    }
    for header in request.headers.iter() {
        if axum::http::HeaderValue::from_bytes(header.value).is_err() {
            return Err(bad(format!(
                "the value of header {} is not valid",
                header.name
            )));
        }
    }
    Ok(())
}

/// A JSON error answer, and the connection closed.
async fn refuse(mut stream: TcpStream, status: StatusCode, message: &str) {
    let body = serde_json::json!({ "error": message }).to_string();
    let answer = format!(
        "HTTP/1.1 {} {}\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\
         Connection: close\r\n\r\n{body}",
        status.as_u16(),
        status.canonical_reason().unwrap_or("Error"),
        body.len()
    );
    let _ = stream.write_all(answer.as_bytes()).await;
    let _ = stream.shutdown().await;
    // Read what the client still sends for a moment before closing: closing with unread
    // bytes resets the connection, and the client could lose the answer.
    let mut sink = [0u8; 4096];
    let drain = async {
        let mut left = MAX_HEAD_BYTES * 4;
        while left > 0 {
            match stream.read(&mut sink).await {
                Ok(0) | Err(_) => break,
                Ok(n) => left = left.saturating_sub(n),
            }
        }
    };
    let _ = tokio::time::timeout(Duration::from_secs(1), drain).await;
}

/// The stream with the bytes already read in front of it again, for hyper.
struct Rewind {
    prefix: Vec<u8>,
    read: usize,
    inner: TcpStream,
}

impl AsyncRead for Rewind {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        let this = &mut *self;
        if this.read < this.prefix.len() {
            let rest = &this.prefix[this.read..];
            let n = rest.len().min(buf.remaining());
            buf.put_slice(&rest[..n]);
            this.read += n;
            return Poll::Ready(Ok(()));
        }
        Pin::new(&mut this.inner).poll_read(cx, buf)
    }
}

impl AsyncWrite for Rewind {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status(head: &str) -> Option<u16> {
        check_head(head.as_bytes()).err().map(|(s, _)| s.as_u16())
    }

    #[test]
    fn malformed_heads_are_refused_with_their_status() {
        assert_eq!(status("GET /v1/health HTTP/1.1\r\nHost: x\r\n\r\n"), None);
        assert_eq!(status("GET /v1/health HTTP/1.1\nHost: x\n\n"), None);
        assert_eq!(status("GARBAGE\r\n\r\n"), Some(400));
        assert_eq!(status("GET /a b HTTP/1.1\r\n\r\n"), Some(400));
        assert_eq!(
            status("POST /v1/jobs HTTP/1.1\r\nContent-Length: 12x\r\n\r\n"),
            Some(400)
        );
        assert_eq!(
            status("POST /v1/jobs HTTP/1.1\r\nContent-Length: 1\r\nContent-Length: 2\r\n\r\n"),
            Some(400)
        );
        assert_eq!(
            status("POST /v1/jobs HTTP/1.1\r\nTransfer-Encoding: gzip\r\n\r\n"),
            Some(400)
        );
        assert_eq!(
            status("POST /v1/jobs HTTP/1.1\r\nTransfer-Encoding: chunked\r\n\r\n"),
            None
        );
        let long = format!("GET /{} HTTP/1.1\r\n\r\n", "a".repeat(MAX_TARGET_BYTES));
        assert_eq!(status(&long), Some(414));
        let many: String = (0..=MAX_HEADERS).map(|i| format!("X-{i}: a\r\n")).collect();
        assert_eq!(status(&format!("GET / HTTP/1.1\r\n{many}\r\n")), Some(431));
        assert_eq!(head_end(b"GET / HTTP/1.1\r\n\r\nbody"), Some(18));
        assert_eq!(head_end(b"GET / HTTP/1.1\r\nHost: x\r\n"), None);
    }
}
