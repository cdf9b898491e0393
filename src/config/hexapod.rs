//! Configuration of plan kind `hexapod` (placeholder until its commit).
