//! `geocal serve`: the daemon as its clients see it.

mod api;
mod console_browser;
mod hardening;
mod history;
mod live_view;
mod recording_memory;
mod schemathesis;
