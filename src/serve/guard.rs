//! What every API request passes before a handler sees it: the `Host` allow-list (against DNS
//! rebinding, when no token guards the API), a refused oversize `Content-Length`, a body read
//! time-out, and error answers made JSON (`ErrorBody`) whatever produced them.

use std::net::IpAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::extract::{Request, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::api::ErrorBody;

fn error(status: StatusCode, message: impl Into<String>) -> Response {
    (
        status,
        axum::Json(ErrorBody {
            error: message.into(),
        }),
    )
        .into_response()
}

/// The `Host` names the API answers to without a token: loopback names and addresses with
/// the listening port, and the configured names.
#[derive(Debug, Clone)]
pub struct HostCheck {
    pub port: u16,
    pub names: Vec<String>,
}

impl HostCheck {
    pub fn allows(&self, host: &str) -> bool {
        let host = host.trim().to_ascii_lowercase();
        let (name, port) = split_host(&host);
        // A Host without a port names the scheme's default port (80 for http).
        let port_ok = port.map_or(self.port == 80, |p| p == self.port);
        let configured = self.names.iter().any(|allowed| {
            let allowed = allowed.trim().to_ascii_lowercase();
            allowed == host || (allowed == name && port_ok)
        });
        if configured {
            return true;
        }
        is_loopback_name(name) && port_ok
    }
}

/// Whether a host name (`localhost`, `127.0.0.1`, `[::1]`) names this machine's loopback.
pub fn is_loopback_name(name: &str) -> bool {
    name.eq_ignore_ascii_case("localhost")
        || name
            .trim_start_matches('[')
            .trim_end_matches(']')
            .parse::<IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

/// The host name of a Host header value (`[::1]:7878` → `[::1]`), lower case.
pub fn host_name(host: &str) -> String {
    split_host(&host.trim().to_ascii_lowercase()).0.to_owned()
}

/// `name` and `port` of a Host header value (`[::1]:7878`, `localhost:7878`, `localhost`).
fn split_host(host: &str) -> (&str, Option<u16>) {
    if let Some(rest) = host.strip_prefix('[') {
        return match rest.split_once(']') {
            Some((ip, tail)) => (
                &host[..ip.len() + 2],
                tail.strip_prefix(':').and_then(|p| p.parse().ok()),
            ),
            None => (host, None),
        };
    }
    match host.rsplit_once(':') {
        Some((name, port)) => (name, port.parse().ok()),
        None => (host, None),
    }
}

pub async fn check_host(
    State(check): State<Arc<Option<HostCheck>>>,
    request: Request,
    next: Next,
) -> Response {
    let Some(check) = check.as_ref() else {
        return next.run(request).await;
    };
    let hosts: Vec<&HeaderValue> = request.headers().get_all(header::HOST).iter().collect();
    let host = match hosts.as_slice() {
        [one] => one.to_str().unwrap_or(""),
        [] => "",
        _ => return error(StatusCode::BAD_REQUEST, "several Host headers"),
    };
    if check.allows(host) {
        return next.run(request).await;
    }
    tracing::warn!(host, path = %request.uri().path(), "refused: Host not allowed");
    error(
        StatusCode::MISDIRECTED_REQUEST,
        format!(
            "Host `{host}` is not one this daemon answers to without a token (loopback names \
             with port {}, or the daemon's allowed_host_names)",
            check.port
        ),
    )
}

/// Whether a request that changes state (any method but GET, HEAD, OPTIONS) comes from
/// another web origin: an `Origin` other than the request's own host (either scheme, for a
/// TLS proxy in front), `Origin: null`, or `Sec-Fetch-Site: cross-site`. Clients that send
/// neither header (the CLI, scripts) are not browsers acting for another site.
pub fn cross_origin(method: &axum::http::Method, headers: &axum::http::HeaderMap) -> bool {
    use axum::http::Method;
    if matches!(*method, Method::GET | Method::HEAD | Method::OPTIONS) {
        return false;
    }
    from_another_origin(headers)
}

/// Whether a browser sent the request for a page of another web origin (see `cross_origin`),
/// whatever its method: the live streams refuse such readers too.
pub fn from_another_origin(headers: &axum::http::HeaderMap) -> bool {
    let text = |name: &str| {
        headers
            .get_all(name)
            .iter()
            .map(|v| v.to_str().unwrap_or("\u{0}").trim().to_ascii_lowercase())
            .collect::<Vec<_>>()
    };
    if text("sec-fetch-site")
        .iter()
        .any(|site| site == "cross-site")
    {
        return true;
    }
    let hosts = text("host");
    text("origin").iter().any(|origin| {
        let own = hosts.len() == 1
            && ["http://", "https://"].iter().any(|scheme| {
                origin
                    .strip_prefix(scheme)
                    .is_some_and(|rest| rest == hosts[0].as_str())
            });
        !own
    })
}

/// The middleware: a state-changing request from another web origin is a 403 (a page
/// elsewhere must not ack a prompt or submit a job through the operator's browser).
pub async fn check_origin(request: Request, next: Next) -> Response {
    if !cross_origin(request.method(), request.headers()) {
        return next.run(request).await;
    }
    let origin = request
        .headers()
        .get(header::ORIGIN)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_owned();
    tracing::warn!(origin, method = %request.method(), path = %request.uri().path(), "refused: cross-origin request");
    error(
        StatusCode::FORBIDDEN,
        format!(
            "a {} from another web origin (`{origin}`) is refused: state-changing requests \
             from a browser must come from the daemon's own pages",
            request.method()
        ),
    )
}

/// Body limits: a `Content-Length` over the limit is refused before anything is read, and a
/// body must arrive whole within the time-out.
#[derive(Debug, Clone, Copy)]
pub struct BodyLimits {
    pub max_bytes: usize,
    pub timeout: Duration,
}

pub async fn read_body(State(limits): State<BodyLimits>, request: Request, next: Next) -> Response {
    let declared = request.headers().get_all(header::CONTENT_LENGTH);
    for value in declared.iter() {
        match value
            .to_str()
            .ok()
            .and_then(|v| v.trim().parse::<u64>().ok())
        {
            Some(length) if length > limits.max_bytes as u64 => {
                return error(
                    StatusCode::PAYLOAD_TOO_LARGE,
                    format!(
                        "the body is {length} bytes, over the daemon's limit of {} (max_body_bytes)",
                        limits.max_bytes
                    ),
                );
            }
            Some(_) => {}
            None => return error(StatusCode::BAD_REQUEST, "Content-Length is not a number"),
        }
    }
    let (parts, body) = request.into_parts();
    let read = axum::body::to_bytes(body, limits.max_bytes);
    let bytes = match tokio::time::timeout(limits.timeout, read).await {
        Ok(Ok(bytes)) => bytes,
        Ok(Err(e)) => {
            let too_large = std::error::Error::source(&e)
                .is_some_and(|s| s.is::<http_body_util::LengthLimitError>());
            return if too_large {
                error(
                    StatusCode::PAYLOAD_TOO_LARGE,
                    format!(
                        "the body is over the daemon's limit of {} bytes (max_body_bytes)",
                        limits.max_bytes
                    ),
                )
            } else {
                error(StatusCode::BAD_REQUEST, format!("reading the body: {e}"))
            };
        }
        Err(_) => {
            tracing::warn!(path = %parts.uri.path(), "refused: body not received within {:?}", limits.timeout);
            let mut response = error(
                StatusCode::REQUEST_TIMEOUT,
                format!("the body did not arrive within {:?}", limits.timeout),
            );
            response
                .headers_mut()
                .insert(header::CONNECTION, HeaderValue::from_static("close"));
            return response;
        }
    };
    next.run(Request::from_parts(parts, Body::from(bytes)))
        .await
}

/// Error answers that are not JSON yet (the router's 404 and 405, extractor rejections such
/// as a path id that does not parse) become `ErrorBody`, their text kept as the message.
pub async fn json_errors(request: Request, next: Next) -> Response {
    let response = next.run(request).await;
    let status = response.status();
    let is_json = response
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if !(status.is_client_error() || status.is_server_error()) || is_json {
        return response;
    }
    let (mut parts, body) = response.into_parts();
    let text = axum::body::to_bytes(body, 64 * 1024)
        .await
        .map(|b| String::from_utf8_lossy(&b).trim().to_owned())
        .unwrap_or_default();
    let message = if text.is_empty() {
        status.canonical_reason().unwrap_or("error").to_owned()
    } else {
        text
    };
    let body = serde_json::to_vec(&ErrorBody { error: message }).unwrap_or_default();
    parts.headers.remove(header::CONTENT_LENGTH);
    parts.headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    Response::from_parts(parts, Body::from(body))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn state_changing_requests_from_other_origins_are_cross_origin() {
        use axum::http::{HeaderMap, Method};
        let headers = |pairs: &[(&'static str, &str)]| {
            let mut map = HeaderMap::new();
            for (name, value) in pairs {
                map.append(*name, value.parse().unwrap());
            }
            map
        };
        let own = headers(&[
            ("host", "127.0.0.1:7878"),
            ("origin", "http://127.0.0.1:7878"),
        ]);
        assert!(!cross_origin(&Method::POST, &own));
        let proxied = headers(&[("host", "geocal.lab"), ("origin", "https://geocal.lab")]);
        assert!(!cross_origin(&Method::POST, &proxied));
        assert!(!cross_origin(&Method::POST, &headers(&[("host", "x:1")])));
        for refused in [
            headers(&[
                ("host", "127.0.0.1:7878"),
                ("origin", "http://evil.example"),
            ]),
            headers(&[
                ("host", "127.0.0.1:7878"),
                ("origin", "http://127.0.0.1:7879"),
            ]),
            headers(&[("host", "127.0.0.1:7878"), ("origin", "null")]),
            headers(&[("host", "127.0.0.1:7878"), ("sec-fetch-site", "cross-site")]),
            headers(&[("origin", "http://127.0.0.1:7878")]),
        ] {
            assert!(cross_origin(&Method::POST, &refused), "{refused:?}");
            assert!(!cross_origin(&Method::GET, &refused), "{refused:?}");
        }
    }

    #[test]
    fn loopback_hosts_with_the_port_and_configured_names_are_allowed() {
        let check = HostCheck {
            port: 7878,
            names: vec!["geocal.lab".into(), "other:9000".into()],
        };
        for ok in [
            "127.0.0.1:7878",
            "localhost:7878",
            "LOCALHOST:7878",
            "[::1]:7878",
            "127.0.0.2:7878",
            "geocal.lab:7878",
            "other:9000",
        ] {
            assert!(check.allows(ok), "{ok}");
        }
        for refused in [
            "evil.example",
            "evil.example:7878",
            "127.0.0.1:7879",
            "localhost",
            "localhost.evil.example:7878",
            "geocal.lab:80",
            "other:7878",
            "",
            "[::1]",
        ] {
            assert!(!check.allows(refused), "{refused}");
        }
    }
}
