//! Plan of kind `hexapod` (placeholder until its commit).
