//! The bearer token: read from a file only its owner can read, compared in constant time;
//! a request without it, or with another, is a 401 and is logged.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;

use anyhow::Context;
use axum::extract::{ConnectInfo, Request, State};
use axum::http::{header, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use subtle::ConstantTimeEq;

#[derive(Clone)]
pub struct Token(Vec<u8>);

impl Token {
    /// The token in `path` (surrounding whitespace ignored). Refused when the file is
    /// readable by its group or others, or holds fewer than 16 characters.
    pub fn load(path: &Path) -> anyhow::Result<Token> {
        let metadata = std::fs::metadata(path)
            .with_context(|| format!("reading the token file {}", path.display()))?;
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = metadata.permissions().mode();
            if mode & 0o077 != 0 {
                anyhow::bail!(
                    "the token file {} is readable or writable by its group or others (mode \
                     {:o}); make it private with `chmod 600 {}`",
                    path.display(),
                    mode & 0o777,
                    path.display()
                );
            }
        }
        #[cfg(not(unix))]
        let _ = metadata;
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading the token file {}", path.display()))?;
        let token = text.trim();
        if token.len() < 16 {
            anyhow::bail!(
                "the token in {} is {} characters long: use at least 16 (e.g. `openssl rand \
                 -hex 32`)",
                path.display(),
                token.len()
            );
        }
        Ok(Token(token.as_bytes().to_vec()))
    }

    pub fn matches(&self, presented: &[u8]) -> bool {
        // ct_eq on slices of different lengths is false without comparing the bytes.
        bool::from(self.0.as_slice().ct_eq(presented))
    }

    /// The console's session cookie value: a digest of the token, so the cookie jar never
    /// holds the token itself (it is as good as the token to this daemon, and to no other).
    pub fn session_value(&self) -> String {
        use sha2::{Digest, Sha256};
        let digest = Sha256::new()
            .chain_update(b"geocal console session\0")
            .chain_update(&self.0)
            .finalize();
        digest.iter().map(|b| format!("{b:02x}")).collect()
    }

    pub(super) fn matches_session(&self, presented: &str) -> bool {
        bool::from(self.session_value().as_bytes().ct_eq(presented.as_bytes()))
    }
}

/// The console's session cookie (set by its login form: HttpOnly, SameSite=Strict).
pub const SESSION_COOKIE: &str = "geocal_session";

/// The session cookie's values in a request's `Cookie` headers.
fn session_cookies(headers: &axum::http::HeaderMap) -> impl Iterator<Item = &str> {
    session_cookie_values(
        headers
            .get_all(header::COOKIE)
            .iter()
            .filter_map(|v| v.to_str().ok()),
    )
}

/// The values of the console's session cookie in `Cookie` header values.
pub fn session_cookie_values<'a>(
    cookie_headers: impl Iterator<Item = &'a str>,
) -> impl Iterator<Item = &'a str> {
    cookie_headers
        .flat_map(|v| v.split(';'))
        .filter_map(|pair| {
            let (name, value) = pair.trim().split_once('=')?;
            (name == SESSION_COOKIE).then_some(value.trim())
        })
}

/// What anyone may fetch without the token: the console's page, its assets and its login
/// (none holds data; the page asks for the token when the API refuses it).
fn is_public(method: &axum::http::Method, path: &str) -> bool {
    use axum::http::Method;
    match *method {
        Method::GET | Method::HEAD => path == "/" || path.starts_with("/console/assets/"),
        Method::POST => path == "/console/login" || path == "/console/logout",
        _ => false,
    }
}

/// The credentials of an `Authorization` header value: the scheme is case-insensitive
/// (RFC 9110, 11.1), so `bearer x` and `BEARER x` are `Bearer x`.
pub fn bearer_credentials(value: &str) -> Option<&str> {
    let (scheme, credentials) = value.trim().split_once(' ')?;
    scheme
        .eq_ignore_ascii_case("bearer")
        .then(|| credentials.trim())
}

/// The middleware: more than one `Authorization` header is a 400 (which would count?); with a
/// token configured, every request but the console's public ones must carry `Authorization:
/// Bearer <token>` or the console's session cookie.
pub async fn require_token(
    State(token): State<Arc<Option<Token>>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    request: Request,
    next: Next,
) -> Response {
    let mut headers = request.headers().get_all(header::AUTHORIZATION).iter();
    let first = headers.next();
    if headers.next().is_some() {
        tracing::warn!(peer = %peer, "refused: several Authorization headers");
        return (
            StatusCode::BAD_REQUEST,
            axum::Json(super::api::ErrorBody {
                error: "several Authorization headers: send one".into(),
            }),
        )
            .into_response();
    }
    let Some(token) = token.as_ref() else {
        return next.run(request).await;
    };
    let presented = first
        .and_then(|v| v.to_str().ok())
        .and_then(bearer_credentials)
        .map(|v| v.as_bytes().to_vec());
    let by_cookie =
        presented.is_none() && session_cookies(request.headers()).any(|c| token.matches_session(c));
    if by_cookie || is_public(request.method(), request.uri().path()) {
        return next.run(request).await;
    }
    match presented {
        Some(p) if token.matches(&p) => next.run(request).await,
        presented => {
            tracing::warn!(
                peer = %peer,
                method = %request.method(),
                path = %request.uri().path(),
                "refused: {}",
                if presented.is_some() { "wrong bearer token" } else { "no bearer token" }
            );
            (
                StatusCode::UNAUTHORIZED,
                [(header::WWW_AUTHENTICATE, "Bearer")],
                axum::Json(super::api::ErrorBody {
                    error: "a bearer token is required (Authorization: Bearer <token>)".into(),
                }),
            )
                .into_response()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn token_files_must_be_private_and_long_enough() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("token");
        std::fs::write(&path, "0123456789abcdef0123\n").unwrap();
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o644)).unwrap();
            let err = Token::load(&path).err().unwrap().to_string();
            assert!(err.contains("chmod 600"), "{err}");
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600)).unwrap();
        }
        let token = Token::load(&path).unwrap();
        assert!(token.matches(b"0123456789abcdef0123"));
        assert!(!token.matches(b"0123456789abcdef012"));
        assert!(!token.matches(b"0123456789abcdef0124"));
        assert_eq!(bearer_credentials("bearer abc"), Some("abc"));
        assert_eq!(bearer_credentials("BEARER  abc "), Some("abc"));
        assert_eq!(bearer_credentials("Basic abc"), None);
        assert_eq!(bearer_credentials("Bearerabc"), None);
        let session = token.session_value();
        assert_eq!(session.len(), 64);
        assert!(!session.contains("0123456789abcdef0123"));
        assert!(token.matches_session(&session));
        assert!(!token.matches_session(&session[1..]));
        let mut headers = axum::http::HeaderMap::new();
        headers.insert(
            header::COOKIE,
            format!("a=b; {SESSION_COOKIE}={session}; c=d")
                .parse()
                .unwrap(),
        );
        assert_eq!(
            session_cookies(&headers).collect::<Vec<_>>(),
            [session.as_str()]
        );
        use axum::http::Method;
        assert!(is_public(&Method::GET, "/"));
        assert!(is_public(&Method::GET, "/console/assets/console.js"));
        assert!(is_public(&Method::POST, "/console/login"));
        assert!(!is_public(&Method::GET, "/v1/jobs"));
        assert!(!is_public(&Method::POST, "/"));
        assert!(!is_public(&Method::GET, "/console/other"));
        std::fs::write(&path, "short").unwrap();
        assert!(Token::load(&path).is_err());
    }
}
