//! `[report]`: what the report checks the results against: the tolerances the user declares
//! for the machine's errors (docs/report.md, "Summary").

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::ConfigError;

/// Declared tolerances, each a symmetric zone ±T around zero; a missing key is not checked.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ReportConfig {
    /// Largest |value| allowed of every length error (positioning, straightness), µm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance_um: Option<f64>,
    /// Largest |value| allowed of every angular error (roll, pitch, yaw, squareness), arcsec.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance_arcsec: Option<f64>,
}

impl ReportConfig {
    /// Each declared tolerance finite and positive.
    pub fn validate(&self, file: &Path) -> Result<(), ConfigError> {
        for (key, value) in [
            ("report.tolerance_um", self.tolerance_um),
            ("report.tolerance_arcsec", self.tolerance_arcsec),
        ] {
            if let Some(v) = value {
                super::kind_config::positive(file, key, v)?;
            }
        }
        Ok(())
    }

    /// The `[report]` table of a configuration text of any kind (absent: nothing declared).
    pub fn of_config_text(text: &str, file: &Path) -> Result<ReportConfig, ConfigError> {
        #[derive(Deserialize)]
        struct Outer {
            #[serde(default)]
            report: Option<ReportConfig>,
        }
        let parse_error = |key: String, message: String| ConfigError::Parse {
            file: file.to_path_buf(),
            key,
            message,
        };
        let deserializer = toml::de::Deserializer::parse(text)
            .map_err(|e| parse_error(String::from("(document)"), e.to_string()))?;
        let outer: Outer = serde_path_to_error::deserialize(deserializer).map_err(|e| {
            let key = e.path().to_string();
            parse_error(key, e.into_inner().to_string().trim_end().to_string())
        })?;
        let report = outer.report.unwrap_or_default();
        report.validate(file)?;
        Ok(report)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tolerances_parse_from_any_kind_and_bad_ones_are_named() {
        let file = Path::new("run.toml");
        let r = ReportConfig::of_config_text(
            "kind = \"hexapod\"\n[other]\nx = 1\n[report]\ntolerance_um = 8.0\n",
            file,
        )
        .expect("parse");
        assert_eq!(r.tolerance_um, Some(8.0));
        assert_eq!(r.tolerance_arcsec, None);
        let none = ReportConfig::of_config_text("kind = \"x\"\n", file).expect("parse");
        assert_eq!(none, ReportConfig::default());
        let err = ReportConfig::of_config_text("[report]\ntolerance_um = -1.0\n", file)
            .expect_err("negative");
        assert!(err.to_string().contains("report.tolerance_um"), "{err}");
        let err = ReportConfig::of_config_text("[report]\ntolerance_mm = 1.0\n", file)
            .expect_err("unknown key");
        assert!(err.to_string().contains("tolerance_mm"), "{err}");
    }
}
