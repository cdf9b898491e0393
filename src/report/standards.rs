//! The report's uncertainty budget (GUM) with the normalisation to 20 °C: each kind's own
//! (`Kind::uncertainty`).

use crate::document::{KindReport, Section};

use super::Inputs;

/// The uncertainty budget of the positioning errors (k = 2) and their values referred to
/// 20 °C, from the declared uncertainties of the run's configuration (`run-config.toml`
/// beside the results; the documented defaults without it).
pub fn uncertainty(inputs: &Inputs, _: &KindReport) -> anyhow::Result<Vec<Section>> {
    let Some(session) = &inputs.session else {
        return Ok(Vec::new());
    };
    let config_path = inputs
        .results_path
        .parent()
        .map(|d| d.join(crate::run::resume::CONFIG_FILE))
        .filter(|p| p.is_file());
    crate::kinds::registry::Registry::standard()
        .named(inputs.kind()?)
        .map_or(Ok(Vec::new()), |k| {
            k.uncertainty(&inputs.results, session, config_path.as_deref())
        })
}
