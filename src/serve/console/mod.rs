//! The operator's console: one page (`/`) with its script and style embedded in the binary,
//! and the login that turns the daemon's token into an HttpOnly, SameSite=Strict cookie. The
//! page reads and acts only through the `/v1` API, behind the same guards as any client.

use axum::extract::State;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Form, Router};
use serde::Deserialize;

use super::auth::{Token, SESSION_COOKIE};

const PAGE: &str = include_str!("../../../assets/console/index.html");
const SCRIPT: &str = include_str!("../../../assets/console/console.js");
const STYLE: &str = include_str!("../../../assets/console/console.css");

/// The page may load only its own script and style, talk only to its own origin, frame only
/// its own reports, and be framed by no one (a framed Continue button could be clickjacked).
const PAGE_POLICY: &str = "default-src 'none'; script-src 'self'; style-src 'self'; \
     img-src 'self' data:; connect-src 'self'; frame-src 'self'; form-action 'self'; \
     frame-ancestors 'none'; base-uri 'none'";

/// The console's routes; `token` is the daemon's, when it has one.
pub fn routes<S: Clone + Send + Sync + 'static>(token: Option<Token>) -> Router<S> {
    Router::new()
        .route("/", get(page))
        .route("/console/assets/console.js", get(script))
        .route("/console/assets/console.css", get(style))
        .route("/console/login", post(login))
        .route("/console/logout", post(logout))
        .with_state(token)
}

fn asset(content_type: &'static str, body: &'static str) -> Response {
    let mut response = body.into_response();
    let headers = response.headers_mut();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    // Assets change with the binary: always revalidate, never keep a stale console.
    headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    headers.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    response
}

async fn page() -> Response {
    let mut response = asset("text/html; charset=utf-8", PAGE);
    let headers = response.headers_mut();
    headers.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(PAGE_POLICY),
    );
    headers.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    headers.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    response
}

async fn script() -> Response {
    asset("text/javascript; charset=utf-8", SCRIPT)
}

async fn style() -> Response {
    asset("text/css; charset=utf-8", STYLE)
}

#[derive(Deserialize)]
struct Login {
    token: String,
}

fn error(status: StatusCode, message: &str) -> Response {
    (
        status,
        axum::Json(super::api::ErrorBody {
            error: message.to_owned(),
        }),
    )
        .into_response()
}

/// The login form: the token in a form body (never in a URL); right, a session cookie the
/// browser sends with every API request of the page and that no script can read.
async fn login(State(token): State<Option<Token>>, Form(login): Form<Login>) -> Response {
    let Some(token) = token else {
        // Without a token (loopback) there is nothing to log in to.
        return StatusCode::NO_CONTENT.into_response();
    };
    if !token.matches(login.token.trim().as_bytes()) {
        tracing::warn!("refused: console login with a wrong token");
        return error(StatusCode::UNAUTHORIZED, "that is not the daemon's token");
    }
    let cookie = format!(
        "{SESSION_COOKIE}={}; HttpOnly; SameSite=Strict; Path=/",
        token.session_value()
    );
    let mut response = StatusCode::NO_CONTENT.into_response();
    if let Ok(value) = HeaderValue::from_str(&cookie) {
        response.headers_mut().insert(header::SET_COOKIE, value);
    }
    response
}

async fn logout() -> Response {
    let mut response = StatusCode::NO_CONTENT.into_response();
    response.headers_mut().insert(
        header::SET_COOKIE,
        HeaderValue::from_static("geocal_session=; HttpOnly; SameSite=Strict; Path=/; Max-Age=0"),
    );
    response
}
