//! `geocal serve` against hostile clients: a rebinding `Host` is refused when no token guards
//! the API, slow clients are cut off after the time-out while others are served, the
//! connection cap holds, oversize bodies are refused before they are read, the auth scheme is
//! case-insensitive and two `Authorization` headers are refused, every error answer is JSON,
//! and the OpenAPI document says what the daemon as configured does.

use crate::common;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

struct Daemon {
    child: Child,
    /// `127.0.0.1:PORT`
    address: String,
    /// The live view's `HOST:PORT`, when it runs.
    live: Option<String>,
}

impl Daemon {
    fn start(dir: &Path, config: &str, extra: &[&str]) -> Daemon {
        let config_file = dir.join("serve.toml");
        std::fs::write(&config_file, config).expect("config");
        let mut child = Command::new(env!("CARGO_BIN_EXE_geocal"))
            .arg("serve")
            .arg("--config")
            .arg(&config_file)
            .arg("--data-dir")
            .arg(dir.join("data"))
            .args(["--listen", "127.0.0.1:0"])
            .args(if extra.contains(&"--live") {
                &[][..]
            } else {
                &["--live", "off"][..]
            })
            .args(extra)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(dir.join("daemon.log")).expect("log file"))
            .spawn()
            .expect("spawn geocal serve");
        let (url, live) = common::daemon_banner(&mut child);
        let address = url.trim_start_matches("http://").to_owned();
        let live = live.map(|ws| ws.trim_start_matches("ws://").to_owned());
        Daemon {
            child,
            address,
            live,
        }
    }

    fn port(&self) -> u16 {
        self.address
            .rsplit_once(':')
            .and_then(|(_, p)| p.parse().ok())
            .expect("port")
    }

    fn connect(&self) -> TcpStream {
        let stream = TcpStream::connect(&self.address).expect("connect");
        stream
            .set_read_timeout(Some(Duration::from_secs(120)))
            .expect("read timeout");
        stream
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// An answer read off the wire.
#[derive(Debug)]
struct Answer {
    status: u16,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Answer {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }

    /// The `ErrorBody` message; fails unless the answer is JSON with an `error` string.
    fn error(&self) -> String {
        assert!(
            self.header("content-type")
                .is_some_and(|t| t.starts_with("application/json")),
            "not JSON: {self:?}"
        );
        let body: Value = serde_json::from_slice(&self.body).expect("a JSON body");
        body["error"].as_str().expect("an error message").to_owned()
    }

    fn json(&self) -> Value {
        serde_json::from_slice(&self.body).expect("a JSON body")
    }
}

/// Read one HTTP/1.1 answer (the server closes or gives a Content-Length).
fn read_answer(stream: &mut TcpStream) -> Option<Answer> {
    let mut data = Vec::new();
    let mut buffer = [0u8; 8192];
    loop {
        let end = data.windows(4).position(|w| w == b"\r\n\r\n");
        if let Some(end) = end {
            let head = String::from_utf8_lossy(&data[..end]).into_owned();
            let mut lines = head.split("\r\n");
            let status: u16 = lines.next()?.split_whitespace().nth(1)?.parse().ok()?;
            let headers: Vec<(String, String)> = lines
                .filter_map(|l| l.split_once(':'))
                .map(|(n, v)| (n.trim().to_owned(), v.trim().to_owned()))
                .collect();
            let length = headers
                .iter()
                .find(|(n, _)| n.eq_ignore_ascii_case("content-length"))
                .and_then(|(_, v)| v.parse::<usize>().ok());
            let body_start = end + 4;
            if let Some(length) = length {
                while data.len() < body_start + length {
                    let n = stream.read(&mut buffer).ok()?;
                    if n == 0 {
                        return None;
                    }
                    data.extend_from_slice(&buffer[..n]);
                }
                let body = data[body_start..body_start + length].to_vec();
                return Some(Answer {
                    status,
                    headers,
                    body,
                });
            }
            // No length: chunked or until close; the tests send `Connection: close`.
            loop {
                match stream.read(&mut buffer) {
                    Ok(0) | Err(_) => break,
                    Ok(n) => data.extend_from_slice(&buffer[..n]),
                }
            }
            let body = dechunk(&data[body_start..]);
            return Some(Answer {
                status,
                headers,
                body,
            });
        }
        let n = stream.read(&mut buffer).ok()?;
        if n == 0 {
            return None;
        }
        data.extend_from_slice(&buffer[..n]);
    }
}

fn dechunk(data: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut rest = data;
    while let Some(line_end) = rest.windows(2).position(|w| w == b"\r\n") {
        let size = usize::from_str_radix(String::from_utf8_lossy(&rest[..line_end]).trim(), 16)
            .unwrap_or(0);
        if size == 0 {
            break;
        }
        let start = line_end + 2;
        out.extend_from_slice(&rest[start..(start + size).min(rest.len())]);
        rest = &rest[(start + size + 2).min(rest.len())..];
    }
    out
}

/// Send `request` (its lines joined with CRLF, a blank line added) and read the answer.
fn send(daemon: &Daemon, lines: &[&str], body: &[u8]) -> Answer {
    let mut stream = daemon.connect();
    let mut request = lines.join("\r\n");
    request.push_str("\r\nConnection: close\r\n\r\n");
    stream.write_all(request.as_bytes()).expect("write");
    stream.write_all(body).expect("write body");
    read_answer(&mut stream).unwrap_or_else(|| panic!("no answer to {lines:?}"))
}

fn get(daemon: &Daemon, path: &str, host: &str, extra: &[&str]) -> Answer {
    let request = format!("GET {path} HTTP/1.1");
    let host = format!("Host: {host}");
    let mut lines = vec![request.as_str(), host.as_str()];
    lines.extend_from_slice(extra);
    send(daemon, &lines, b"")
}

fn token_file(dir: &Path, token: &str) -> std::path::PathBuf {
    let path = dir.join("token");
    std::fs::write(&path, token).expect("token");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600)).expect("chmod");
    }
    path
}

/// Every operation of the document, as (path, method, operation).
fn operations(document: &Value) -> Vec<(String, String, Value)> {
    let mut out = Vec::new();
    for (path, item) in document["paths"].as_object().expect("paths") {
        for (method, operation) in item.as_object().expect("path item") {
            out.push((path.clone(), method.clone(), operation.clone()));
        }
    }
    out
}

#[test]
fn without_a_token_only_its_own_host_names_are_served_and_every_error_is_json() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = Daemon::start(dir.path(), "allowed_host_names = [\"geocal.lab\"]\n", &[]);
    let port = daemon.port();
    let own = format!("127.0.0.1:{port}");

    // DNS rebinding: a page whose name now resolves to 127.0.0.1 sends its own name.
    for host in ["evil.example".to_owned(), format!("evil.example:{port}")] {
        let refused = get(&daemon, "/v1/health", &host, &[]);
        assert_eq!(refused.status, 421, "{host}: {refused:?}");
        assert!(refused.error().contains("evil.example"), "{refused:?}");
    }
    let rebinding_submit = send(
        &daemon,
        &[
            "POST /v1/jobs HTTP/1.1",
            "Host: evil.example",
            "Content-Type: application/toml",
            "Content-Length: 2",
        ],
        b"x=",
    );
    assert_eq!(rebinding_submit.status, 421, "{rebinding_submit:?}");
    for host in [
        own.clone(),
        format!("localhost:{port}"),
        format!("[::1]:{port}"),
        format!("geocal.lab:{port}"),
    ] {
        let served = get(&daemon, "/v1/health", &host, &[]);
        assert_eq!(served.status, 200, "{host}: {served:?}");
        assert_eq!(served.json()["status"], "ok");
    }

    // Errors from the router and the extractors are JSON too.
    let bad_id = get(&daemon, "/v1/jobs/abc", &own, &[]);
    assert_eq!(bad_id.status, 400);
    assert!(bad_id.error().contains("abc"), "{bad_id:?}");
    let bad_prompt = send(
        &daemon,
        &[
            "POST /v1/prompts/x/ack HTTP/1.1",
            &format!("Host: {own}"),
            "Content-Length: 0",
        ],
        b"",
    );
    assert_eq!(bad_prompt.status, 400);
    bad_prompt.error();
    let no_route = get(&daemon, "/v2/nothing", &own, &[]);
    assert_eq!(no_route.status, 404);
    no_route.error();
    let wrong_method = send(
        &daemon,
        &[
            "PATCH /v1/jobs HTTP/1.1",
            &format!("Host: {own}"),
            "Content-Length: 0",
        ],
        b"",
    );
    assert_eq!(wrong_method.status, 405);
    wrong_method.error();
    assert!(wrong_method.header("allow").is_some(), "{wrong_method:?}");

    // A declared 10 GB body is refused from its headers alone: nothing of it is sent.
    let huge = send(
        &daemon,
        &[
            "POST /v1/jobs HTTP/1.1",
            &format!("Host: {own}"),
            "Content-Type: application/toml",
            "Content-Length: 10000000000",
        ],
        b"",
    );
    assert_eq!(huge.status, 413, "{huge:?}");
    assert!(huge.error().contains("10000000000"), "{huge:?}");

    // Which of two Authorization headers would count? Neither.
    let two = get(
        &daemon,
        "/v1/health",
        &own,
        &["Authorization: Bearer a", "Authorization: Bearer b"],
    );
    assert_eq!(two.status, 400);
    assert!(two.error().contains("Authorization"), "{two:?}");

    // The document as configured: no security, the Host refusal on every operation, both
    // bodies of POST /v1/jobs, the real metrics type.
    let document = get(&daemon, "/v1/openapi.json", &own, &[]).json();
    // A session job is a solve, diagnose or replay; a run is submitted as TOML.
    let session_types = &document["components"]["schemas"]["SessionJobType"]["enum"];
    assert_eq!(
        session_types,
        &serde_json::json!(["solve", "diagnose", "replay"]),
        "{}",
        document["components"]["schemas"]["SessionJob"]
    );
    assert!(
        document.get("security").is_none(),
        "{}",
        document["security"]
    );
    assert!(document["components"].get("securitySchemes").is_none());
    for (path, method, operation) in operations(&document) {
        let responses = &operation["responses"];
        for status in ["400", "408", "413", "421", "500"] {
            assert!(responses[status].is_object(), "{method} {path}: {status}");
        }
        assert!(
            responses.get("401").is_none(),
            "{method} {path}: 401 without a token"
        );
    }
    let bodies = &document["paths"]["/v1/jobs"]["post"]["requestBody"]["content"];
    assert!(bodies["application/toml"].is_object(), "{bodies}");
    assert_eq!(
        bodies["application/json"]["schema"]["$ref"],
        "#/components/schemas/SessionJob"
    );
    let metrics_doc = &document["paths"]["/metrics"]["get"]["responses"]["200"]["content"];
    let metrics = get(&daemon, "/metrics", &own, &[]);
    let served_type = metrics.header("content-type").expect("content type");
    let media_type = served_type.split(';').next().unwrap_or("").trim();
    assert!(
        metrics_doc[media_type].is_object(),
        "{served_type} in {metrics_doc}"
    );
}

#[test]
fn with_a_token_any_case_of_bearer_is_taken_and_the_document_says_so() {
    let dir = tempfile::tempdir().expect("tempdir");
    let token = "hardening-token-0123456789";
    let file = token_file(dir.path(), token);
    let daemon = Daemon::start(
        dir.path(),
        "",
        &[
            "--token-file",
            file.to_str().expect("utf-8"),
            "--live",
            "127.0.0.1:0",
        ],
    );
    let own = daemon.address.clone();
    for scheme in ["Bearer", "bearer", "BEARER"] {
        let auth = format!("Authorization: {scheme} {token}");
        let answer = get(&daemon, "/v1/health", &own, &[&auth]);
        assert_eq!(answer.status, 200, "{scheme}: {answer:?}");
    }
    let refused = get(&daemon, "/v1/health", &own, &[]);
    assert_eq!(refused.status, 401);
    refused.error();
    let good = format!("Authorization: Bearer {token}");
    let two = get(
        &daemon,
        "/v1/health",
        &own,
        &[&good, "Authorization: Bearer wrong"],
    );
    assert_eq!(two.status, 400, "{two:?}");
    let two = get(
        &daemon,
        "/v1/health",
        &own,
        &["Authorization: Bearer wrong", &good],
    );
    assert_eq!(two.status, 400, "{two:?}");
    // With a token the token is the guard: any Host name may be used to reach the daemon.
    let named = get(&daemon, "/v1/health", "geocal.lab.example:7878", &[&good]);
    assert_eq!(named.status, 200, "{named:?}");

    // The daemon's live view takes the same token (tests/live_view.rs checks the rest).
    let live = daemon.live.clone().expect("the live view's address");
    let upgrade = |target: &str, extra: &str| {
        let mut stream = TcpStream::connect(&live).expect("connect to the live view");
        stream
            .set_read_timeout(Some(Duration::from_secs(120)))
            .expect("read timeout");
        let request = format!(
            "GET {target} HTTP/1.1\r\nHost: {live}\r\nUpgrade: websocket\r\n\
             Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\
             Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n{extra}\r\n"
        );
        stream.write_all(request.as_bytes()).expect("write");
        let mut head = Vec::new();
        let mut byte = [0u8; 1];
        while !head.ends_with(b"\r\n\r\n") && stream.read(&mut byte).unwrap_or(0) == 1 {
            head.push(byte[0]);
        }
        String::from_utf8_lossy(&head).into_owned()
    };
    assert!(
        upgrade("/", "").starts_with("HTTP/1.1 401"),
        "{}",
        upgrade("/", "")
    );
    let with_token = format!("/?token={token}");
    let foreign = upgrade(&with_token, "Origin: http://evil.example\r\n");
    assert!(foreign.starts_with("HTTP/1.1 403"), "{foreign}");
    let admitted = upgrade(&with_token, "Origin: https://app.foxglove.dev\r\n");
    assert!(admitted.starts_with("HTTP/1.1 101"), "{admitted}");

    let document = get(&daemon, "/v1/openapi.json", &own, &[&good]).json();
    assert_eq!(document["security"], serde_json::json!([{ "bearer": [] }]));
    assert_eq!(
        document["components"]["securitySchemes"]["bearer"]["scheme"],
        "bearer"
    );
    for (path, method, operation) in operations(&document) {
        assert!(operation["responses"]["401"].is_object(), "{method} {path}");
        assert!(
            operation["responses"].get("421").is_none(),
            "{method} {path}"
        );
    }
}

#[test]
fn a_slow_client_is_cut_off_after_the_time_out_while_others_are_served() {
    let dir = tempfile::tempdir().expect("tempdir");
    let timeout = Duration::from_secs(2);
    let daemon = Daemon::start(dir.path(), "request_timeout_s = 2.0\n", &[]);
    let own = daemon.address.clone();

    let opened = Instant::now();
    // Headers that never end.
    let mut slow_headers = daemon.connect();
    slow_headers
        .write_all(format!("GET /v1/health HTTP/1.1\r\nHost: {own}\r\nX-Slow: 1\r\n").as_bytes())
        .expect("write");
    // A body that declares 100 bytes and sends 10.
    let mut slow_body = daemon.connect();
    slow_body
        .write_all(
            format!(
                "POST /v1/jobs HTTP/1.1\r\nHost: {own}\r\nContent-Type: application/toml\r\n\
                 Content-Length: 100\r\n\r\nkind = \"x\""
            )
            .as_bytes(),
        )
        .expect("write");

    // Meanwhile others are served.
    let mut served = 0;
    while opened.elapsed() < timeout {
        let answer = get(&daemon, "/v1/health", &own, &[]);
        assert_eq!(answer.status, 200, "{answer:?}");
        served += 1;
    }
    assert!(served >= 1);

    // The slow body gets a 408, the slow headers a closed connection (or a 408), each once
    // the time-out has run; a connection still open after the read time-out fails the test.
    let body_answer = read_answer(&mut slow_body).expect("an answer to the slow body");
    assert!(opened.elapsed() >= timeout);
    assert_eq!(body_answer.status, 408, "{body_answer:?}");
    assert!(
        body_answer.error().contains("did not arrive"),
        "{body_answer:?}"
    );
    let mut rest = Vec::new();
    let closed = slow_headers.read_to_end(&mut rest);
    assert!(closed.is_ok(), "still open: {closed:?}");
    assert!(opened.elapsed() >= timeout);
    let text = String::from_utf8_lossy(&rest);
    assert!(
        rest.is_empty() || text.starts_with("HTTP/1.1 408"),
        "the slow headers got: {text}"
    );
    // And the daemon still serves.
    assert_eq!(get(&daemon, "/v1/health", &own, &[]).status, 200);
}

#[test]
fn requests_beyond_the_cap_wait_for_a_free_slot() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = Daemon::start(
        dir.path(),
        "request_timeout_s = 3.0\nmax_connections = 2\n",
        &[],
    );
    let own = daemon.address.clone();
    let opened = Instant::now();
    // Two admitted requests whose bodies never arrive hold both slots until the body
    // time-out answers them; idle connections would hold none.
    let slow: Vec<TcpStream> = (0..2)
        .map(|_| {
            let mut stream = daemon.connect();
            stream
                .write_all(
                    format!(
                        "POST /v1/jobs HTTP/1.1\r\nHost: {own}\r\nContent-Type: \
                         application/toml\r\nContent-Length: 100\r\n\r\nkind"
                    )
                    .as_bytes(),
                )
                .expect("write");
            stream
        })
        .collect();
    std::thread::sleep(Duration::from_millis(300));
    let answer = get(&daemon, "/v1/health", &own, &[]);
    assert_eq!(answer.status, 200);
    assert!(
        opened.elapsed() >= Duration::from_millis(2500),
        "served after {:?}: the cap of 2 did not hold",
        opened.elapsed()
    );
    drop(slow);
}

/// Raise this process's open-file limit to its hard limit (for the flood).
fn raise_open_files() {
    // SAFETY: getrlimit/setrlimit with a valid pointer to a local struct.
    unsafe {
        let mut limit = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        if libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) == 0 && limit.rlim_cur < limit.rlim_max
        {
            limit.rlim_cur = limit.rlim_max;
            libc::setrlimit(libc::RLIMIT_NOFILE, &limit);
        }
    }
}

/// An open event stream (`/v1/events`, or `/v1/devices/samples`): its answer's head read,
/// the connection kept. `headers` end with `\r\n` each.
fn open_stream(daemon: &Daemon, path: &str, headers: &str) -> (u16, TcpStream) {
    let mut stream = daemon.connect();
    let request = format!(
        "GET {path} HTTP/1.1\r\nHost: {}\r\n{headers}\r\n",
        daemon.address
    );
    stream.write_all(request.as_bytes()).expect("write");
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        match stream.read(&mut byte) {
            Ok(1) => head.push(byte[0]),
            _ => break,
        }
    }
    let status = String::from_utf8_lossy(&head)
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    (status, stream)
}

#[test]
fn streams_and_a_flood_of_idle_connections_do_not_lock_the_api_out() {
    raise_open_files();
    let dir = tempfile::tempdir().expect("tempdir");
    let token = "flood-token-0123456789abcdef";
    let file = token_file(dir.path(), token);
    let daemon = Daemon::start(
        dir.path(),
        "max_connections = 4\nmax_streams = 4\n",
        &["--token-file", file.to_str().expect("utf-8")],
    );
    let auth = format!("Authorization: Bearer {token}\r\n");
    const EVENTS: &str = "/v1/events";
    const SAMPLES: &str = "/v1/devices/samples";
    // A stream for another origin's page is refused, with the token and all.
    for path in [EVENTS, SAMPLES] {
        let foreign = format!("{auth}Origin: http://evil.example\r\n");
        let (status, _) = open_stream(&daemon, path, &foreign);
        assert_eq!(status, 403, "{path}");
    }
    // Four streams of both kinds fill the stream cap (a fifth of either is refused) and hold
    // no request slot.
    let streams: Vec<TcpStream> = [EVENTS, SAMPLES, EVENTS, SAMPLES]
        .iter()
        .map(|path| {
            let (status, stream) = open_stream(&daemon, path, &auth);
            assert_eq!(status, 200, "{path}");
            stream
        })
        .collect();
    for path in [EVENTS, SAMPLES] {
        let (status, mut fifth) = open_stream(&daemon, path, &auth);
        assert_eq!(status, 503, "{path}");
        let mut rest = Vec::new();
        let _ = fifth.read_to_end(&mut rest);
        assert!(String::from_utf8_lossy(&rest).contains("max_streams"));
    }
    // Unauthenticated peers: streams refused, and 1000 connections that send nothing.
    for path in [EVENTS, SAMPLES] {
        let (status, _) = open_stream(&daemon, path, "");
        assert_eq!(status, 401, "{path}");
    }
    let flood: Vec<TcpStream> = (0..1000)
        .filter_map(|_| TcpStream::connect(&daemon.address).ok())
        .collect();
    assert!(flood.len() >= 900, "opened {} connections", flood.len());
    // An authenticated request is still answered (a generous time-out: assert the answer,
    // not its latency; benches/serve.rs measures that).
    let answer = get(&daemon, "/v1/health", &daemon.address, &[&auth]);
    assert_eq!(answer.status, 200, "{answer:?}");
    assert_eq!(answer.json()["status"], "ok");
    drop(flood);
    drop(streams);
}

#[test]
fn malformed_requests_get_json_errors() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = Daemon::start(dir.path(), "", &[]);
    let own = daemon.address.clone();
    let raw = |request: &[u8]| -> Answer {
        let mut stream = daemon.connect();
        stream.write_all(request).expect("write");
        read_answer(&mut stream).expect("an answer")
    };
    let host = format!("Host: {own}\r\n");
    let long_target = format!("GET /{} HTTP/1.1\r\n{host}\r\n", "a".repeat(9000));
    let many_headers = format!(
        "GET /v1/health HTTP/1.1\r\n{host}{}\r\n",
        (0..100)
            .map(|i| format!("X-{i}: a\r\n"))
            .collect::<String>()
    );
    let huge_header = format!(
        "GET /v1/health HTTP/1.1\r\n{host}X-Big: {}\r\n\r\n",
        "a".repeat(70 * 1024)
    );
    for (request, status) in [
        (
            format!("POST /v1/jobs HTTP/1.1\r\n{host}Content-Length: ten\r\n\r\n"),
            400,
        ),
        ("NOT AN HTTP REQUEST\r\n\r\n".to_string(), 400),
        (long_target, 414),
        (many_headers, 431),
        (huge_header, 431),
    ] {
        let answer = raw(request.as_bytes());
        assert_eq!(answer.status, status, "{answer:?}");
        assert!(!answer.error().is_empty());
    }
}

fn private_file(path: &Path, text: &str) {
    std::fs::write(path, text).expect("write");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o600)).expect("chmod");
    }
}

/// The small demo with `file` at each path-typed key a plan configuration has (docs/serve.md,
/// "What a plan may read"), one plan per key: (key, plan).
fn plans_naming(file: &str) -> Vec<(&'static str, String)> {
    let demo = common::small_demo();
    vec![
        (
            "sim.compensation[0].file",
            format!(
                "{demo}\n[[sim.compensation]]\nformat = \"linuxcnc-type0\"\nfile = \"{file}\"\naxis = \"x\"\n"
            ),
        ),
        (
            "hil.linuxcnc.comp_files[0].file",
            format!(
                "{demo}\n[hil]\nemulate = true\n[[hil.linuxcnc.comp_files]]\naxis = \"x\"\nfile = \"{file}\"\ntype = 0\n"
            ),
        ),
        (
            "devices.machine.linuxcnc.password_file",
            format!("{demo}\n[devices.machine.linuxcnc]\npassword_file = \"{file}\"\n"),
        ),
    ]
}

#[test]
fn plans_read_no_file_outside_the_allowed_folders_and_nothing_quotes_one() {
    let dir = tempfile::tempdir().expect("tempdir");
    let root = dir.path();
    let token = "probe-token-TOKENSECRET-0123456789";
    let token_path = token_file(root, token);
    let password = root.join("linuxcnc-passwords.toml");
    private_file(
        &password,
        "connect = \"PWSECRETconnect\"\nenable = \"PWSECRETenable\"\n",
    );
    let secrets = ["TOKENSECRET", "PWSECRET", "TABLESECRET"];
    // The one folder plans may read: a table that does not parse, and a symlink out of it.
    let tables = root.join("tables");
    std::fs::create_dir(&tables).expect("tables");
    let bad_table = tables.join("bad.txt");
    std::fs::write(&bad_table, "TABLESECRET 1 2\n0 0 0\n").expect("table");
    std::os::unix::fs::symlink(&token_path, tables.join("token-link")).expect("symlink");
    std::os::unix::fs::symlink(&password, tables.join("password-link")).expect("symlink");
    let config = format!("allowed_read_dirs = [\"{}\"]\n", tables.display());
    let guarded_dir = root.join("guarded");
    let open_dir = root.join("open");
    std::fs::create_dir_all(&guarded_dir).expect("dir");
    std::fs::create_dir_all(&open_dir).expect("dir");
    let token_arg = token_path.to_str().expect("utf-8").to_owned();
    let guarded = Daemon::start(&guarded_dir, &config, &["--token-file", &token_arg]);
    let open = Daemon::start(&open_dir, &config, &[]);
    let auth = format!("Authorization: Bearer {token}");

    let submit = |daemon: &Daemon, plan: &str, auth: Option<&str>| -> Answer {
        let length = format!("Content-Length: {}", plan.len());
        let host = format!("Host: {}", daemon.address);
        let mut lines = vec![
            "POST /v1/jobs HTTP/1.1",
            host.as_str(),
            "Content-Type: application/toml",
            length.as_str(),
        ];
        lines.extend(auth);
        send(daemon, &lines, plan.as_bytes())
    };
    let check_quiet = |what: &str, text: &str| {
        for secret in secrets {
            assert!(!text.contains(secret), "{what} quotes {secret}: {text}");
        }
    };
    let targets = [
        token_path.display().to_string(),
        password.display().to_string(),
        tables.join("token-link").display().to_string(),
        tables.join("password-link").display().to_string(),
        format!("{}/../token", tables.display()),
        "../../../token".to_string(),
        "/etc/shadow".to_string(),
    ];
    let mut refused = 0;
    for target in &targets {
        for (key, plan) in plans_naming(target) {
            let without = submit(&guarded, &plan, None);
            assert_eq!(without.status, 401, "{without:?}");
            check_quiet("a 401", &String::from_utf8_lossy(&without.body));
            for (daemon, auth) in [(&guarded, Some(auth.as_str())), (&open, None)] {
                let answer = submit(daemon, &plan, auth);
                assert_eq!(answer.status, 400, "{key} = {target}: {answer:?}");
                let error = answer.error();
                assert!(error.contains(key), "{key}: {error}");
                check_quiet("a 400", &error);
                refused += 1;
            }
        }
    }
    assert_eq!(refused, targets.len() * 3 * 2);
    // An allowed file is read, and its parse error says where, not what.
    let (key, plan) = plans_naming(&bad_table.display().to_string()).remove(0);
    for (daemon, auth) in [(&guarded, Some(auth.as_str())), (&open, None)] {
        let answer = submit(daemon, &plan, auth);
        assert_eq!(answer.status, 400, "{key}: {answer:?}");
        let error = answer.error();
        assert!(
            error.contains("bad.txt") && error.contains("line 1"),
            "{error}"
        );
        check_quiet("a parse error", &error);
    }
    // Nothing was stored, and the logs quote nothing either.
    for dir in [&guarded_dir, &open_dir] {
        let jobs = std::fs::read_dir(dir.join("data").join("jobs"))
            .map(|d| d.count())
            .unwrap_or(0);
        assert_eq!(jobs, 0, "a refused plan left a job folder");
    }
    drop(guarded);
    drop(open);
    for dir in [&guarded_dir, &open_dir] {
        let log = std::fs::read_to_string(dir.join("daemon.log")).expect("log");
        check_quiet("the daemon's log", &log);
    }

    // The CLI reads what its user names, and quotes none of it either.
    for target in [&token_path, &password, &bad_table] {
        for (_, plan) in plans_naming(&target.display().to_string()) {
            let file = root.join("plan.toml");
            std::fs::write(&file, plan).expect("plan");
            let output = Command::new(env!("CARGO_BIN_EXE_geocal"))
                .arg("check")
                .arg(&file)
                .output()
                .expect("geocal check");
            let text = String::from_utf8_lossy(&output.stderr).into_owned()
                + &String::from_utf8_lossy(&output.stdout);
            check_quiet("geocal check", &text);
        }
        let output = Command::new(env!("CARGO_BIN_EXE_geocal"))
            .arg("check")
            .arg(target)
            .output()
            .expect("geocal check");
        assert!(!output.status.success());
        let text = String::from_utf8_lossy(&output.stderr);
        let name = target.file_name().and_then(|n| n.to_str()).expect("name");
        assert!(text.contains(name), "names the file: {text}");
        check_quiet("geocal check of the file itself", &text);
    }
}
