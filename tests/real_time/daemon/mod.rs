//! `geocal serve`: the daemon as its clients see it.

mod api;
mod history;
mod recording_memory;
mod schemathesis;
