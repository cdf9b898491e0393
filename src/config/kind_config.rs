//! Strict parsing shared by every configuration layout (the core `Config` and the kinds with
//! their own: `rotary_sphere`, `probe_install`, `hexapod`): which kind a file declares, and
//! serde errors as file/key/message.

use std::path::Path;

use serde::de::DeserializeOwned;

use super::ConfigError;

/// The `kind` a configuration text declares, if it parses as TOML and has one.
pub fn declared_kind(text: &str) -> Option<String> {
    let value: toml::Table = text.parse().ok()?;
    value.get("kind")?.as_str().map(str::to_owned)
}

/// The text of a configuration file, or a `Read` error naming it.
pub fn read(path: &Path) -> Result<String, ConfigError> {
    std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
        file: path.to_path_buf(),
        source,
    })
}

/// Parse `text` into `T`, rejecting unknown keys; errors name `file`, the key path and why.
pub fn parse_strict<T: DeserializeOwned>(text: &str, file: &Path) -> Result<T, ConfigError> {
    let parse_error = |key: String, message: String| ConfigError::Parse {
        file: file.to_path_buf(),
        key,
        message,
    };
    let deserializer = toml::de::Deserializer::parse(text)
        .map_err(|e| parse_error(String::from("(document)"), e.to_string()))?;
    serde_path_to_error::deserialize(deserializer).map_err(|e| {
        let key = e.path().to_string();
        parse_error(key, e.into_inner().to_string().trim_end().to_string())
    })
}

/// An `Invalid` error for `file` at `key`.
pub fn invalid(file: &Path, key: &str, message: impl Into<String>) -> ConfigError {
    ConfigError::Invalid {
        file: file.to_path_buf(),
        key: key.to_owned(),
        message: message.into(),
    }
}

/// An `Invalid` error at `kind` unless the file declares `expected`.
pub fn expect_kind(file: &Path, kind: &str, expected: &str) -> Result<(), ConfigError> {
    if kind == expected {
        Ok(())
    } else {
        Err(invalid(
            file,
            "kind",
            format!("expected \"{expected}\", got \"{kind}\""),
        ))
    }
}

/// Checks that `value` is finite and positive, else an `Invalid` error.
pub fn positive(file: &Path, key: &str, value: f64) -> Result<(), ConfigError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(invalid(
            file,
            key,
            format!("expected a finite number > 0, got {value}"),
        ))
    }
}

/// Checks that `value` is finite and not negative, else an `Invalid` error.
pub fn non_negative(file: &Path, key: &str, value: f64) -> Result<(), ConfigError> {
    if value.is_finite() && value >= 0.0 {
        Ok(())
    } else {
        Err(invalid(
            file,
            key,
            format!("expected a finite number >= 0, got {value}"),
        ))
    }
}

/// Checks that every value is finite, else an `Invalid` error.
pub fn finite(file: &Path, key: &str, values: &[f64]) -> Result<(), ConfigError> {
    match values.iter().find(|v| !v.is_finite()) {
        None => Ok(()),
        Some(v) => Err(invalid(
            file,
            key,
            format!("expected finite numbers, got {v}"),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kind_is_read_without_the_rest() {
        assert_eq!(
            declared_kind("kind = \"hexapod\"\n[x]\ny = 1").as_deref(),
            Some("hexapod")
        );
        assert_eq!(declared_kind("kind = 3"), None);
        assert_eq!(declared_kind("not toml ="), None);
    }
}
