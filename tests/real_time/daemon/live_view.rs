//! The live view speaks the Foxglove WebSocket protocol: a Python client (the `websockets`
//! package) subscribes to a recorded topic and receives each message byte-equal, at its
//! recorded log time, with the recorded encoding and schema.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::Arc;

use geocal::serve::live::LiveView;
use geocal::session::tap::{MessageTap, TapChannel, TappedMessage};

#[test]
fn a_foxglove_client_receives_the_recorded_bytes_at_their_log_times() {
    let view = Arc::new(LiveView::start("127.0.0.1:0".parse().expect("address")).expect("start"));
    let url = format!("ws://{}", view.address());
    let schema = br#"{"type":"object","properties":{"length_m":{"type":"number"}}}"#.to_vec();
    let channel = Arc::new(TapChannel {
        id: 3,
        topic: "/tracer/t0/range".into(),
        message_encoding: "json".into(),
        schema: Some((
            "geocal.TracerSample".into(),
            "jsonschema".into(),
            schema.clone(),
        )),
    });
    let other = Arc::new(TapChannel {
        id: 4,
        topic: "/env/air".into(),
        message_encoding: "json".into(),
        schema: None,
    });
    let wanted = 20;
    let mut client = Command::new("python3")
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/live_view/client.py"
        ))
        .args([&url, "/tracer/t0/range", &wanted.to_string()])
        .stdout(Stdio::piped())
        .spawn()
        .expect("python3");
    let stdout = client.stdout.take().expect("client stdout");

    // Feed messages like the recorder does until the client has its samples; which ones it
    // sees depends on when it subscribed, so keep every sent one to check against.
    let sent = Arc::new(std::sync::Mutex::new(Vec::<(u64, Vec<u8>)>::new()));
    let done = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let feeder = {
        let (view, sent, done) = (view.clone(), sent.clone(), done.clone());
        std::thread::spawn(move || {
            let mut i = 0u64;
            while !done.load(std::sync::atomic::Ordering::Relaxed) && i < 200_000 {
                let log_time_ns = 1_700_000_000_000_000_000 + i * 1_000_000;
                let data = format!("{{\"seq\":{i},\"length_m\":{:.9}}}", 0.5 + i as f64 * 1e-6);
                sent.lock()
                    .expect("sent")
                    .push((log_time_ns, data.clone().into_bytes()));
                for c in [&channel, &other] {
                    view.message(&TappedMessage {
                        channel: c,
                        sequence: i as u32,
                        log_time_ns,
                        publish_time_ns: log_time_ns,
                        data: data.as_bytes(),
                        queue_depth: 0,
                    });
                }
                i += 1;
                std::thread::sleep(std::time::Duration::from_millis(5));
            }
        })
    };

    let mut advertised = None;
    let mut received = Vec::new();
    for line in BufReader::new(stdout).lines() {
        let line = line.expect("client output");
        let v: serde_json::Value = serde_json::from_str(&line).expect("client JSON line");
        if let Some(channel) = v.get("advertised") {
            advertised = Some(channel.clone());
            continue;
        }
        if v.get("connected").is_some() {
            continue;
        }
        let log_time = v["log_time_ns"].as_u64().expect("log_time_ns");
        let hex = v["payload_hex"].as_str().expect("payload_hex");
        let bytes: Vec<u8> = (0..hex.len())
            .step_by(2)
            .map(|k| u8::from_str_radix(&hex[k..k + 2], 16).expect("hex"))
            .collect();
        received.push((log_time, bytes));
    }
    done.store(true, std::sync::atomic::Ordering::Relaxed);
    feeder.join().expect("feeder");
    assert!(client.wait().expect("client").success(), "client failed");
    view.stop();

    let advertised = advertised.expect("the topic was advertised");
    assert_eq!(advertised["encoding"], "json");
    assert_eq!(advertised["schemaName"], "geocal.TracerSample");
    assert_eq!(advertised["schemaEncoding"], "jsonschema");
    assert_eq!(
        advertised["schema"].as_str().map(str::as_bytes),
        Some(&schema[..])
    );
    assert_eq!(received.len(), wanted);
    let sent = sent.lock().expect("sent");
    for message in &received {
        assert!(sent.contains(message), "not sent as such: {message:?}");
    }
    // In order and without gaps once subscribed.
    let first = sent.iter().position(|m| m == &received[0]).expect("first");
    assert_eq!(&sent[first..first + wanted], &received[..]);
    assert_eq!(view.dropped(), 0);
    println!(
        "{} messages received byte-equal; {} published",
        received.len(),
        view.published()
    );
}

/// What `handshake.py` got: the HTTP status (101 when admitted) and the first message's op or
/// the refusal's body.
fn handshake(url: &str, origin: Option<&str>, bearer: Option<&str>) -> serde_json::Value {
    handshake_with_cookie(url, origin, bearer, None)
}

fn handshake_with_cookie(
    url: &str,
    origin: Option<&str>,
    bearer: Option<&str>,
    cookie: Option<&str>,
) -> serde_json::Value {
    let output = Command::new("python3")
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/live_view/handshake.py"
        ))
        .args([
            url,
            origin.unwrap_or("-"),
            bearer.unwrap_or("-"),
            cookie.unwrap_or("-"),
        ])
        .output()
        .expect("python3");
    assert!(
        output.status.success(),
        "handshake.py: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_slice(&output.stdout).expect("handshake.py's JSON line")
}

#[test]
fn a_foreign_origin_or_a_missing_token_gets_nothing_from_the_live_view() {
    let dir = tempfile::tempdir().expect("tempdir");
    let token_file = dir.path().join("token");
    let token = "live-token-0123456789abcdef";
    std::fs::write(&token_file, token).expect("token");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&token_file, std::fs::Permissions::from_mode(0o600))
            .expect("chmod");
    }
    // The console's port: any, nothing listens there in this test.
    const CONSOLE_PORT: u16 = 7878;
    let loaded = geocal::serve::auth::Token::load(&token_file).expect("token");
    let session = format!("geocal_session={}", loaded.session_value());
    let access = geocal::serve::live::LiveAccess {
        token: Some(loaded),
        extra_origins: vec!["http://viewer.example:8080".into()],
        console_port: Some(CONSOLE_PORT),
    };
    let view =
        LiveView::start_guarded("127.0.0.1:0".parse().expect("address"), access).expect("start");
    let base = format!("ws://{}/", view.address());
    let with_token = format!("{base}?token={token}");

    // Refused before the Foxglove server sees them: no serverInfo, no data.
    let foreign = handshake(&with_token, Some("http://evil.example"), None);
    assert_eq!(foreign["status"], 403, "{foreign}");
    assert!(
        foreign["body"]
            .as_str()
            .unwrap_or("")
            .contains("evil.example"),
        "{foreign}"
    );
    let no_token = handshake(&base, None, None);
    assert_eq!(no_token["status"], 401, "{no_token}");
    let wrong = handshake(
        &format!("{base}?token=live-token-0123456789abcdee"),
        None,
        None,
    );
    assert_eq!(wrong["status"], 401, "{wrong}");
    let app_without_token = handshake(&base, Some("https://app.foxglove.dev"), None);
    assert_eq!(app_without_token["status"], 401, "{app_without_token}");

    // Admitted: the Foxglove app with the token in its URL, a configured origin, a native
    // client with the bearer header.
    // The console's cookie: from the console's own origin (the live view's host name, the
    // API's port) it is the token; from another port of the same host (the same site, so the
    // browser sends the cookie) the Origin is refused; elsewhere it counts for nothing.
    let console = format!("http://127.0.0.1:{CONSOLE_PORT}");
    let same_site = format!("http://127.0.0.1:{}", CONSOLE_PORT + 1);
    for (origin, cookie, status) in [
        (console.as_str(), "geocal_session=0123", 401),
        (console.as_str(), "", 401),
        (same_site.as_str(), session.as_str(), 403),
        ("http://localhost:7878", session.as_str(), 403),
        ("https://app.foxglove.dev", session.as_str(), 401),
    ] {
        let refused = handshake_with_cookie(&base, Some(origin), None, Some(cookie));
        assert_eq!(refused["status"], status, "{origin} {cookie}: {refused}");
    }

    for (url, origin, bearer, cookie) in [
        (&with_token, Some("https://app.foxglove.dev"), None, None),
        (&with_token, Some("http://viewer.example:8080"), None, None),
        (&base, None, Some(token), None),
        (&base, Some(console.as_str()), None, Some(session.as_str())),
    ] {
        let admitted = handshake_with_cookie(url, origin, bearer, cookie);
        assert_eq!(admitted["status"], 101, "{origin:?} {bearer:?}: {admitted}");
        assert_eq!(admitted["first_op"], "serverInfo", "{admitted}");
    }
    view.stop();
}
