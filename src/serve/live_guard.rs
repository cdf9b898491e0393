//! The live view's door: a WebSocket-aware TCP front on the live port that reads the HTTP
//! upgrade request, checks its `Origin` against an allow-list and its token, and only then
//! splices the connection to the Foxglove server listening on an internal loopback port.
//!
//! The `foxglove` crate (0.30) completes the WebSocket handshake itself and offers no hook to
//! see the request's headers, so the check has to happen before it: WebSockets are not covered
//! by the browser's same-origin policy, and any page the operator opens could otherwise read
//! the machine's live data from 127.0.0.1.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

use tokio_util::sync::CancellationToken;

use super::auth::Token;
use super::door::{Entry, Waiting};

/// The Foxglove app's origins (the web app, and its former name).
pub const FOXGLOVE_ORIGINS: &[&str] = &["https://app.foxglove.dev", "https://studio.foxglove.dev"];

/// The upgrade request's headers must arrive within this time and this size.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);
const MAX_HANDSHAKE_BYTES: usize = 16 * 1024;
/// Live connections at once (each is one viewer).
const MAX_CONNECTIONS: usize = 32;

/// Who may open the live view.
#[derive(Clone, Default)]
pub struct LiveAccess {
    /// When set, a client must present it: `Authorization: Bearer …` (native clients), the
    /// console's session cookie (pages of the console's own origin), or `?token=…` in the
    /// URL (the Foxglove app: a browser WebSocket can set no header, and the app's origin
    /// gets no cookie of ours).
    pub token: Option<Token>,
    /// Origins allowed beside the Foxglove app's and the console's (e.g.
    /// `https://viewer.example:8443`).
    pub extra_origins: Vec<String>,
    /// The daemon's API port: a page served there (the console) is of an allowed origin, as
    /// long as it reached the daemon by the same host name as the live view.
    pub console_port: Option<u16>,
}

impl LiveAccess {
    fn origin_allowed(&self, origin: &str, host: Option<&str>) -> bool {
        let origin = origin.trim().trim_end_matches('/');
        self.is_console(origin, host)
            || FOXGLOVE_ORIGINS
                .iter()
                .copied()
                .chain(self.extra_origins.iter().map(String::as_str))
                .any(|allowed| allowed.trim_end_matches('/').eq_ignore_ascii_case(origin))
    }

    /// Whether `origin` is the console's: `http(s)://` the host name the request was sent to,
    /// with the API's port. Without a token only a loopback name counts, as the API answers
    /// no other then: a page whose name is rebound to 127.0.0.1 must not pass for it.
    fn is_console(&self, origin: &str, host: Option<&str>) -> bool {
        let (Some(port), Some(host)) = (self.console_port, host) else {
            return false;
        };
        let name = super::guard::host_name(host);
        if self.token.is_none() && !super::guard::is_loopback_name(&name) {
            return false;
        }
        ["http://", "https://"].iter().any(|scheme| {
            origin
                .get(..scheme.len())
                .is_some_and(|s| s.eq_ignore_ascii_case(scheme))
                && origin[scheme.len()..].eq_ignore_ascii_case(&format!("{name}:{port}"))
        })
    }

    /// Why the request may not open the live view, or `None` when it may.
    fn refusal(&self, request: &httparse::Request<'_, '_>) -> Option<(u16, String)> {
        let header = |name: &'static str| {
            request
                .headers
                .iter()
                .filter(move |h| h.name.eq_ignore_ascii_case(name))
                .map(|h| std::str::from_utf8(h.value).unwrap_or("\u{fffd}"))
        };
        // Browsers always send Origin on a WebSocket handshake; native clients need not.
        let origins: Vec<&str> = header("origin").collect();
        let hosts: Vec<&str> = header("host").collect();
        if origins.len() > 1 || hosts.len() > 1 {
            return Some((400, "several Origin or Host headers".into()));
        }
        let host = hosts.first().copied();
        if let Some(origin) = origins.first() {
            if !self.origin_allowed(origin, host) {
                return Some((
                    403,
                    format!(
                        "Origin `{origin}` is not allowed on the live view (allowed: the \
                         console's, the Foxglove app's and the daemon's live_origins)"
                    ),
                ));
            }
        }
        let Some(token) = &self.token else {
            return None;
        };
        let from_query = request
            .path
            .and_then(|p| p.split_once('?'))
            .into_iter()
            .flat_map(|(_, query)| form_urlencoded::parse(query.as_bytes()))
            .filter(|(key, _)| key == "token")
            .map(|(_, value)| value.into_owned());
        let from_header = header("authorization")
            .filter_map(super::auth::bearer_credentials)
            .map(str::to_owned);
        let presented: Vec<String> = from_query.chain(from_header).collect();
        // The console's cookie, only from the console's own pages: other sites on this host
        // (another port of 127.0.0.1 is the same site) get the cookie sent too.
        let from_console = origins
            .first()
            .is_some_and(|origin| self.is_console(origin.trim().trim_end_matches('/'), host));
        if presented.is_empty()
            && from_console
            && super::auth::session_cookie_values(header("cookie"))
                .any(|cookie| token.matches_session(cookie))
        {
            return None;
        }
        match presented.as_slice() {
            [one] if token.matches(one.as_bytes()) => None,
            [] => Some((
                401,
                "the live view needs the daemon's token: ws://HOST:PORT/?token=<token>".into(),
            )),
            [_] => Some((401, "wrong token".into())),
            _ => Some((400, "the token is given more than once".into())),
        }
    }
}

/// When the running job ends: every live connection admitted during it is closed.
#[derive(Default)]
pub struct RunEnds {
    current: std::sync::Mutex<CancellationToken>,
}

impl RunEnds {
    fn token(&self) -> CancellationToken {
        self.current
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// Close the connections open now; later ones wait for the next end.
    pub fn end(&self) {
        let mut current = self.current.lock().unwrap_or_else(|e| e.into_inner());
        std::mem::take(&mut *current).cancel();
    }
}

/// Accept on `listener` and splice every admitted connection to the Foxglove server
/// (`Front::inner`). A connection waits (`door`) until its handshake has
/// passed the checks, and only then takes one of the `MAX_CONNECTIONS` slots: a peer without
/// the token holds none. Runs until its runtime stops.
pub async fn front(listener: TcpListener, shared: Arc<Front>) {
    let slots = Arc::new(tokio::sync::Semaphore::new(MAX_CONNECTIONS));
    let waiting = Waiting::new(super::http::MAX_WAITING);
    loop {
        let (stream, peer) = match listener.accept().await {
            Ok(accepted) => accepted,
            Err(e) => {
                tracing::warn!("live view: accept failed: {e}");
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        let entry = waiting.enter();
        let shared = shared.clone();
        let slots = slots.clone();
        tokio::spawn(async move {
            tokio::select! {
                _ = entry.pushed_out() => {
                    tracing::debug!(%peer, "live view: a waiting connection pushed out by newer ones");
                }
                _ = connection(stream, peer, &shared, &entry, &slots) => {}
            }
        });
    }
}

async fn connection(
    mut stream: TcpStream,
    peer: SocketAddr,
    shared: &Front,
    entry: &Entry,
    slots: &Arc<tokio::sync::Semaphore>,
) {
    let Front {
        inner,
        access,
        run_ends,
        creation,
    } = shared;
    let inner = *inner;
    let head = match tokio::time::timeout(HANDSHAKE_TIMEOUT, read_head(&mut stream)).await {
        Ok(Ok(head)) => head,
        Ok(Err(reason)) => {
            tracing::warn!(%peer, "live view: refused: {reason}");
            answer(stream, 400, reason).await;
            return;
        }
        Err(_) => {
            tracing::warn!(%peer, "live view: refused: no complete handshake within {HANDSHAKE_TIMEOUT:?}");
            return;
        }
    };
    let mut headers = [httparse::EMPTY_HEADER; 64];
    let mut request = httparse::Request::new(&mut headers);
    if let Err(e) = request.parse(&head) {
        answer(stream, 400, format!("not an HTTP request: {e}")).await;
        return;
    }
    if let Some((status, reason)) = access.refusal(&request) {
        tracing::warn!(%peer, status, "live view: refused: {reason}");
        answer(stream, status, reason).await;
        return;
    }
    entry.admit();
    let Ok(_slot) = slots.clone().try_acquire_owned() else {
        tracing::warn!(%peer, "live view: refused, {MAX_CONNECTIONS} connections already open");
        answer(stream, 503, "too many live view connections".into()).await;
        return;
    };
    let run_ended = run_ends.token();
    let mut upstream = match TcpStream::connect(inner).await {
        Ok(upstream) => upstream,
        Err(e) => {
            tracing::error!("live view: the Foxglove server at {inner}: {e}");
            answer(stream, 503, "the live view is not available".into()).await;
            return;
        }
    };
    if upstream.write_all(&head).await.is_err() {
        return;
    }
    tokio::select! {
        _ = splice(&mut stream, &mut upstream, creation) => {}
        _ = run_ended.cancelled() => {
            tracing::debug!(%peer, "live view: the run ended, disconnecting");
        }
    }
}

/// What the front's connections share.
pub struct Front {
    /// The Foxglove server's internal loopback address.
    pub inner: SocketAddr,
    pub access: LiveAccess,
    pub run_ends: Arc<RunEnds>,
    pub creation: Arc<ChannelCreation>,
}

/// Held for writing while the live view creates a channel. The Foxglove server (0.30) sends
/// a new channel's advertisement to its clients before it files the channel as advertised to
/// them; a client that answers with a subscription within that moment is told "unknown
/// channel" and never gets the channel's messages. The front forwards nothing from a client
/// to the server while a channel is being created, so every subscription arrives after.
#[derive(Default)]
pub struct ChannelCreation(tokio::sync::RwLock<()>);

impl ChannelCreation {
    /// Create a channel (`create`) with the clients' messages held back meanwhile. Blocks:
    /// for a plain thread, never an async task.
    pub fn hold_clients_during<T>(&self, create: impl FnOnce() -> T) -> T {
        let _creating = self.0.blocking_write();
        create()
    }
}

/// Copy both ways until both sides have closed (as `tokio::io::copy_bidirectional`), holding
/// the client's bytes back while a channel is being created.
async fn splice(client: &mut TcpStream, server: &mut TcpStream, creation: &ChannelCreation) {
    let (mut from_client, mut to_client) = client.split();
    let (mut from_server, mut to_server) = server.split();
    let downstream = async {
        tokio::io::copy(&mut from_server, &mut to_client).await?;
        to_client.shutdown().await
    };
    let upstream = async {
        let mut buffer = vec![0u8; 16 * 1024];
        loop {
            let n = from_client.read(&mut buffer).await?;
            if n == 0 {
                return to_server.shutdown().await;
            }
            let _no_channel_being_created = creation.0.read().await;
            to_server.write_all(&buffer[..n]).await?;
        }
    };
    let _ = tokio::try_join!(downstream, upstream);
}

/// The request's bytes up to and including the blank line ending its headers. Clients wait
/// for the server's answer before sending frames, so nothing follows it yet.
async fn read_head(stream: &mut TcpStream) -> Result<Vec<u8>, String> {
    let mut head = Vec::with_capacity(1024);
    let mut buffer = [0u8; 2048];
    loop {
        let n = stream
            .read(&mut buffer)
            .await
            .map_err(|e| format!("reading the handshake: {e}"))?;
        if n == 0 {
            return Err("the connection closed during the handshake".into());
        }
        head.extend_from_slice(&buffer[..n]);
        if head.windows(4).any(|w| w == b"\r\n\r\n") {
            return Ok(head);
        }
        if head.len() > MAX_HANDSHAKE_BYTES {
            return Err(format!("handshake over {MAX_HANDSHAKE_BYTES} bytes"));
        }
    }
}

async fn answer(mut stream: TcpStream, status: u16, reason: String) {
    let body = serde_json::json!({ "error": reason }).to_string();
    let phrase = match status {
        400 => "Bad Request",
        401 => "Unauthorized",
        403 => "Forbidden",
        _ => "Service Unavailable",
    };
    let response = format!(
        "HTTP/1.1 {status} {phrase}\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\
         Connection: close\r\n\r\n{body}",
        body.len()
    );
    let _ = stream.write_all(response.as_bytes()).await;
    let _ = stream.shutdown().await;
}

#[cfg(test)]
mod tests {
    use super::*;

    fn refusal(access: &LiveAccess, head: &str) -> Option<u16> {
        let mut headers = [httparse::EMPTY_HEADER; 16];
        let mut request = httparse::Request::new(&mut headers);
        request.parse(head.as_bytes()).unwrap();
        access.refusal(&request).map(|(status, _)| status)
    }

    #[test]
    fn origins_and_tokens_are_checked() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("token");
        std::fs::write(&path, "0123456789abcdef0123").unwrap();
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600)).unwrap();
        }
        let open = LiveAccess::default();
        let guarded = LiveAccess {
            token: Some(Token::load(&path).unwrap()),
            extra_origins: vec!["http://viewer.example:8080".into()],
            console_port: Some(7878),
        };
        let session = guarded.token.as_ref().unwrap().session_value();
        let get = |target: &str, headers: &str| {
            format!("GET {target} HTTP/1.1\r\nHost: x\r\n{headers}\r\n")
        };
        assert_eq!(refusal(&open, &get("/", "")), None);
        assert_eq!(
            refusal(&open, &get("/", "Origin: https://app.foxglove.dev\r\n")),
            None
        );
        assert_eq!(
            refusal(&open, &get("/", "Origin: http://evil.example\r\n")),
            Some(403)
        );
        assert_eq!(refusal(&open, &get("/", "Origin: null\r\n")), Some(403));
        assert_eq!(refusal(&guarded, &get("/", "")), Some(401));
        assert_eq!(
            refusal(&guarded, &get("/?token=0123456789abcdef0123", "")),
            None
        );
        assert_eq!(
            refusal(&guarded, &get("/?token=0123456789abcdef0124", "")),
            Some(401)
        );
        assert_eq!(
            refusal(
                &guarded,
                &get("/", "authorization: BEARER 0123456789abcdef0123\r\n")
            ),
            None
        );
        assert_eq!(
            refusal(
                &guarded,
                &get(
                    "/?token=0123456789abcdef0123",
                    "Origin: http://viewer.example:8080\r\n"
                )
            ),
            None
        );
        assert_eq!(
            refusal(
                &guarded,
                &get(
                    "/?token=0123456789abcdef0123",
                    "Origin: http://evil.example\r\n"
                )
            ),
            Some(403)
        );
        assert_eq!(
            refusal(&guarded, &get("/?token=a&token=0123456789abcdef0123", "")),
            Some(400)
        );
        // The console's cookie opens the live view from the console's own origin only.
        let console = |origin: &str, cookie: &str| {
            format!(
                "GET / HTTP/1.1\r\nHost: 127.0.0.1:8765\r\nOrigin: {origin}\r\n\
                 Cookie: a=b; geocal_session={cookie}\r\n\r\n"
            )
        };
        assert_eq!(
            refusal(&guarded, &console("http://127.0.0.1:7878", &session)),
            None
        );
        assert_eq!(
            refusal(&guarded, &console("http://127.0.0.1:7878", "00")),
            Some(401)
        );
        assert_eq!(
            refusal(&guarded, &console("http://127.0.0.1:7879", &session)),
            Some(403)
        );
        assert_eq!(
            refusal(&guarded, &console("http://localhost:7878", &session)),
            Some(403)
        );
        assert_eq!(
            refusal(&guarded, &console("https://app.foxglove.dev", &session)),
            Some(401)
        );
        assert_eq!(
            refusal(&open, &console("http://127.0.0.1:7878", "")),
            Some(403)
        );
        // Without a token the console's origin needs no cookie, on loopback names only.
        let open_console = LiveAccess {
            console_port: Some(7878),
            ..LiveAccess::default()
        };
        let rebound = |name: &str| {
            format!("GET / HTTP/1.1\r\nHost: {name}:8765\r\nOrigin: http://{name}:7878\r\n\r\n")
        };
        assert_eq!(refusal(&open_console, &rebound("localhost")), None);
        assert_eq!(refusal(&open_console, &rebound("127.0.0.1")), None);
        assert_eq!(refusal(&open_console, &rebound("evil.example")), Some(403));
    }

    /// A client's subscription must not reach the server while a channel is being created
    /// (its advertisement may be out before the server knows it sent it), and must once the
    /// creation is done.
    #[test]
    fn client_bytes_wait_while_a_channel_is_created() {
        let runtime = tokio::runtime::Runtime::new().unwrap();
        let server = runtime.block_on(TcpListener::bind("127.0.0.1:0")).unwrap();
        let listener = runtime.block_on(TcpListener::bind("127.0.0.1:0")).unwrap();
        let address = listener.local_addr().unwrap();
        let creation = Arc::new(ChannelCreation::default());
        runtime.spawn(front(
            listener,
            Arc::new(Front {
                inner: server.local_addr().unwrap(),
                access: LiveAccess::default(),
                run_ends: Arc::new(RunEnds::default()),
                creation: creation.clone(),
            }),
        ));
        // What the server receives after the handshake, as it arrives.
        let (received, arrivals) = std::sync::mpsc::channel::<Vec<u8>>();
        runtime.spawn(async move {
            let (mut upstream, _) = server.accept().await.unwrap();
            let head = read_head(&mut upstream).await.unwrap();
            assert!(head.starts_with(b"GET / HTTP/1.1"));
            let mut buffer = [0u8; 256];
            loop {
                let n = upstream.read(&mut buffer).await.unwrap();
                if n == 0 || received.send(buffer[..n].to_vec()).is_err() {
                    break;
                }
            }
        });
        let mut client = std::net::TcpStream::connect(address).unwrap();
        client
            .write_all(format!("GET / HTTP/1.1\r\nHost: {address}\r\n\r\n").as_bytes())
            .unwrap();
        let (release, released) = std::sync::mpsc::channel::<()>();
        let (holding, held) = std::sync::mpsc::channel::<()>();
        let creator = std::thread::spawn(move || {
            creation.hold_clients_during(|| {
                holding.send(()).unwrap();
                released.recv().unwrap();
            })
        });
        held.recv().unwrap();
        use std::io::Write as _;
        client.write_all(b"subscribe").unwrap();
        assert_eq!(
            arrivals.recv_timeout(Duration::from_millis(300)),
            Err(std::sync::mpsc::RecvTimeoutError::Timeout),
            "forwarded while a channel was being created"
        );
        release.send(()).unwrap();
        creator.join().unwrap();
        let mut forwarded = Vec::new();
        while forwarded.len() < b"subscribe".len() {
            forwarded.extend(arrivals.recv_timeout(Duration::from_secs(30)).unwrap());
        }
        assert_eq!(forwarded, b"subscribe");
    }
}
