//! `geocal serve` against hostile clients: a rebinding `Host` is refused when no token guards
//! the API, slow clients are cut off after the time-out while others are served, the
//! connection cap holds, oversize bodies are refused before they are read, the auth scheme is
//! case-insensitive and two `Authorization` headers are refused, every error answer is JSON,
//! and the OpenAPI document says what the daemon as configured does.

mod common;

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
            .stderr(Stdio::null())
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
fn connections_beyond_the_cap_wait_for_a_free_slot() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = Daemon::start(
        dir.path(),
        "request_timeout_s = 3.0\nmax_connections = 2\n",
        &[],
    );
    let own = daemon.address.clone();
    let opened = Instant::now();
    // Two silent connections hold both slots until the header time-out closes them.
    let idle: Vec<TcpStream> = (0..2).map(|_| daemon.connect()).collect();
    let answer = get(&daemon, "/v1/health", &own, &[]);
    assert_eq!(answer.status, 200);
    assert!(
        opened.elapsed() >= Duration::from_millis(2500),
        "served after {:?}: the cap of 2 did not hold",
        opened.elapsed()
    );
    drop(idle);
}
