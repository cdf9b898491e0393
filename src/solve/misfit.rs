//! Whether a fit's χ²/dof is believable for its degrees of freedom. When it is not, the
//! residuals say the model misses an effect, and the σ propagated from the noise model claim
//! more than the data support: every kind's results then carry a [`Misfit`] that says so.

use serde::{Deserialize, Serialize};

use super::chi2::chi2_sf;

/// Upper-tail probability of χ² below which a fit is flagged.
pub const MISFIT_P: f64 = 1e-3;

/// A fit whose χ² is improbably large for its degrees of freedom (results' `misfit`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Misfit {
    pub chi2_per_dof: f64,
    pub dof: usize,
    /// P(χ²(dof) ≥ χ² observed) when the noise model were right: below [`MISFIT_P`].
    pub p: f64,
    /// √(χ²/dof): the model's σ times this are what the fit's own residuals support.
    pub sigma_scale: f64,
}

impl Misfit {
    /// Some when `chi2` over `dof` degrees of freedom lies in the upper tail beyond `MISFIT_P`.
    pub fn check(chi2: f64, dof: usize) -> Option<Misfit> {
        if dof == 0 || !chi2.is_finite() {
            return None;
        }
        let p = chi2_sf(chi2, dof as f64);
        let chi2_per_dof = chi2 / dof as f64;
        (p < MISFIT_P && chi2_per_dof > 1.0).then(|| Misfit {
            chi2_per_dof,
            dof,
            p,
            sigma_scale: chi2_per_dof.sqrt(),
        })
    }

    /// The warning for the text output and the report.
    pub fn warning(&self) -> String {
        format!(
            "MISFIT: χ²/dof = {:.3} over {} degrees of freedom is improbable (p = {:.1e} < {:.0e}): \
             the model does not explain the residuals, so its σ are NOT trustworthy. The σ \
             scaled by √(χ²/dof) = {:.2} are given beside the model's; they assume the \
             unmodelled effect acts like noise, which it may not. Run `geocal diagnose SESSION` \
             to find the effect.",
            self.chi2_per_dof, self.dof, self.p, MISFIT_P, self.sigma_scale
        )
    }

    /// The warning, then each σ of the results (`results` as JSON) with its scaled value, at
    /// most `max_rows` of them: what the text output appends.
    pub fn text(&self, results: &serde_json::Value, max_rows: usize) -> String {
        let rows = sigma_rows(results);
        let mut out = format!("\n{}\n", self.warning());
        if rows.is_empty() {
            return out;
        }
        out.push_str(&format!(
            "  {:<48} {:>14} {:>14}\n",
            "σ",
            "model",
            format!("× {:.2}", self.sigma_scale)
        ));
        for (path, sigma) in rows.iter().take(max_rows) {
            out.push_str(&format!(
                "  {path:<48} {sigma:>14.4e} {:>14.4e}\n",
                sigma * self.sigma_scale
            ));
        }
        if rows.len() > max_rows {
            out.push_str(&format!(
                "  … and {} more σ (results.json): multiply each by {:.2}\n",
                rows.len() - max_rows,
                self.sigma_scale
            ));
        }
        out
    }
}

/// Every σ in a results document: (JSON path, value) of each number under a key that names a
/// σ (`sigma…`, `…_sigma…`), arrays element by element, zeros left out, the kind's own first.
pub fn sigma_rows(results: &serde_json::Value) -> Vec<(String, f64)> {
    fn walk(value: &serde_json::Value, path: &str, in_sigma: bool, out: &mut Vec<(String, f64)>) {
        match value {
            serde_json::Value::Number(n) if in_sigma => {
                if let Some(x) = n.as_f64() {
                    out.push((path.to_owned(), x));
                }
            }
            serde_json::Value::Array(items) => {
                for (i, item) in items.iter().enumerate() {
                    walk(item, &format!("{path}[{i}]"), in_sigma, out);
                }
            }
            serde_json::Value::Object(fields) => {
                for (key, item) in fields {
                    // The misfit itself says how the σ scale; it holds none.
                    if key == "misfit" {
                        continue;
                    }
                    let sigma = key.starts_with("sigma") || key.contains("_sigma");
                    let path = if path.is_empty() {
                        key.clone()
                    } else {
                        format!("{path}.{key}")
                    };
                    walk(item, &path, sigma, out);
                }
            }
            _ => {}
        }
    }
    let mut out = Vec::new();
    walk(results, "", false, &mut out);
    // A σ of 0 is a value fixed by definition (a reference), not an estimate.
    out.retain(|(_, sigma)| *sigma > 0.0);
    // The kind's own figures (a table's step angles, a sphere's location) before those of the
    // tracer network every tracer kind shares; fewer list indices first, else document order.
    let network = |path: &str| {
        ["stations", "points", "geometric_errors"]
            .iter()
            .any(|block| path.starts_with(block))
    };
    out.sort_by_key(|(path, _)| (network(path), path.matches('[').count()));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flags_only_the_improbable_upper_tail() {
        // χ²/dof = 1.0 and 1.1 over 300 dof are ordinary (p 0.48, 0.11); 1.3 is not (p 3e-4).
        assert!(Misfit::check(300.0, 300).is_none());
        assert!(Misfit::check(330.0, 300).is_none());
        let m = Misfit::check(390.0, 300).expect("flagged");
        assert!(m.p < MISFIT_P && m.p > 1e-5, "{m:?}");
        assert!((m.sigma_scale - 1.3f64.sqrt()).abs() < 1e-12);
        // Too small a χ² is not a misfit of the model.
        assert!(Misfit::check(200.0, 300).is_none());
        assert!(Misfit::check(0.0, 0).is_none());
        let big = Misfit::check(200.0 * 3000.0, 3000).expect("flagged");
        assert_eq!(big.p, 0.0);
    }

    #[test]
    fn finds_every_sigma_of_a_results_document() {
        let results = serde_json::json!({
            "chi2_per_dof": 4.0,
            "points": [{"id": "p0", "sigma_m": [1e-6, 2e-6, 3e-6]}],
            "rotary": {"radius_sigma_m": 5e-6, "steps": [{"sigma_rad": 1e-7, "error_rad": 2.0}]},
            "misfit": {"sigma_scale": 2.0},
        });
        let rows = sigma_rows(&results);
        let paths: Vec<&str> = rows.iter().map(|(p, _)| p.as_str()).collect();
        assert_eq!(
            paths,
            [
                "rotary.radius_sigma_m",
                "rotary.steps[0].sigma_rad",
                "points[0].sigma_m[0]",
                "points[0].sigma_m[1]",
                "points[0].sigma_m[2]",
            ]
        );
        let m = Misfit::check(4.0 * 100.0, 100).expect("flagged");
        let text = m.text(&results, 2);
        assert!(text.contains("geocal diagnose"), "{text}");
        assert!(text.contains("and 3 more"), "{text}");
    }
}
