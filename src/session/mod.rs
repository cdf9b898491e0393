//! The recorded session: message types (the geocal-session/1 contract), the MCAP recorder
//! and the one session reader that solve, replay, diagnose and report share.

pub mod messages;
