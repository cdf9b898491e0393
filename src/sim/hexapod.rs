//! Simulated hexapod (placeholder until its commit).
