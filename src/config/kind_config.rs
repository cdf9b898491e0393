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
        .map_err(|e| parse_error(String::from("(document)"), toml_error_text(text, &e)))?;
    serde_path_to_error::deserialize(deserializer).map_err(|e| {
        let key = e.path().to_string();
        parse_error(key, toml_error_text(text, &e.into_inner()))
    })
}

/// A TOML error as `line L, column C: message`, without the quoted source line that its
/// `Display` shows: an error must not echo a file's content (it may be one a daemon's client
/// did not send).
pub fn toml_error_text(text: &str, error: &toml::de::Error) -> String {
    let message = error.message().trim_end();
    match error.span() {
        Some(span) => {
            let before = &text.as_bytes()[..span.start.min(text.len())];
            let line = before.iter().filter(|&&b| b == b'\n').count() + 1;
            let line_start = before
                .iter()
                .rposition(|&b| b == b'\n')
                .map_or(0, |i| i + 1);
            let column = String::from_utf8_lossy(&before[line_start..])
                .chars()
                .count()
                + 1;
            format!("line {line}, column {column}: {message}")
        }
        None => message.to_owned(),
    }
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

    #[test]
    fn errors_say_where_without_quoting_the_text() {
        #[derive(Debug, serde::Deserialize)]
        #[serde(deny_unknown_fields)]
        #[allow(dead_code)]
        struct T {
            a: f64,
        }
        let secret = "root:$6$secretsalt$hash:19000:0:99999:7:::";
        for text in [
            format!("a = 1.0\n{secret}\n"),
            format!("a = 1.0\nb = \"{secret}\"\n"),
        ] {
            let e = parse_strict::<T>(&text, Path::new("x.toml"))
                .unwrap_err()
                .to_string();
            assert!(!e.contains("secretsalt"), "{e}");
            assert!(e.contains("x.toml") && e.contains("line 2"), "{e}");
        }
    }
}
