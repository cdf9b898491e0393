//! The report's header: machine, structure, session id and date, instruments (ids, serials,
//! declared noise) and the environment's range during the run, from the session's header and
//! its `/env/<id>` samples.

use crate::document::{cell, KindReport, Section, Table};
use crate::session::reader::{Completeness, Session};

use super::Inputs;

/// Kelvin at 0 °C, for display in °C.
const ZERO_CELSIUS_K: f64 = 273.15;

pub fn sections(inputs: &Inputs, _: &KindReport) -> anyhow::Result<Vec<Section>> {
    let results = inputs.results_path.display().to_string();
    let Some(session) = &inputs.session else {
        return Ok(vec![Section::new("header", "Run")
            .facts(vec![("results".into(), results)])
            .paragraph(
                "No session.mcap beside the results: machine, instruments and environment \
                 are not known to this report.",
            )]);
    };
    let h = &session.header;
    let travel = h
        .machine
        .travel_m
        .iter()
        .map(|(axis, [lo, hi])| format!("{axis} {lo:.3}…{hi:.3} m"))
        .collect::<Vec<_>>()
        .join(", ");
    let mut facts = vec![
        ("machine".to_string(), h.machine.name.clone()),
        ("structure".to_string(), h.machine.structure.clone()),
        ("axes".to_string(), h.machine.axes.join(", ")),
        ("session".to_string(), h.session_id.clone()),
        ("started at".to_string(), h.started_at.clone()),
        ("plan kind".to_string(), h.kind.clone()),
        (
            "recording".to_string(),
            match &session.completeness {
                Completeness::Complete => "complete".to_string(),
                Completeness::Truncated { reason, .. } => format!("truncated: {reason}"),
            },
        ),
        ("results".to_string(), results),
    ];
    if !travel.is_empty() {
        facts.insert(3, ("travel".to_string(), travel));
    }
    let mut section = Section::new("header", "Run")
        .facts(facts)
        .table(instruments(session));
    section = match environment(session) {
        Some(table) => section.table(table),
        None => section.paragraph("No environment sensor was recorded in this session."),
    };
    Ok(vec![section])
}

fn instruments(session: &Session) -> Table {
    let mut table = Table::new(
        "Instruments",
        &["id", "kind", "driver", "serial", "declared noise"],
    );
    for d in &session.header.devices {
        let serial = ["serial", "serial_number", "model"]
            .iter()
            .find_map(|k| d.extra.get(*k))
            .map(|v| v.as_str().map_or_else(|| v.to_string(), str::to_string))
            .unwrap_or_else(|| "—".to_string());
        let noise = match (d.noise_m, d.noise_ppm) {
            (Some(m), Some(ppm)) => format!("{:.3} µm + {ppm} ppm (1σ)", m * 1e6),
            (Some(m), None) => format!("{:.3} µm (1σ)", m * 1e6),
            (None, Some(ppm)) => format!("{ppm} ppm (1σ)"),
            (None, None) => "—".to_string(),
        };
        table.row(vec![
            d.id.clone(),
            d.kind.clone(),
            d.driver.clone(),
            serial,
            noise,
        ]);
    }
    table
}

/// min and max of finite values, or None.
fn span(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    values
        .filter(|v| v.is_finite())
        .fold(None, |acc, v| match acc {
            None => Some((v, v)),
            Some((lo, hi)) => Some((f64::min(lo, v), f64::max(hi, v))),
        })
}

fn environment(session: &Session) -> Option<Table> {
    let mut table = Table::new(
        "Environment during the run (min … max)",
        &[
            "sensor",
            "samples",
            "air [°C]",
            "pressure [hPa]",
            "humidity [%]",
            "material [°C]",
        ],
    );
    let range = |s: Option<(f64, f64)>, scale: f64, offset: f64, decimals: usize| match s {
        Some((lo, hi)) => format!(
            "{} … {}",
            cell(Some(lo * scale - offset), decimals),
            cell(Some(hi * scale - offset), decimals)
        ),
        None => "—".to_string(),
    };
    for (id, samples) in &session.env {
        if samples.is_empty() {
            continue;
        }
        let air = span(samples.iter().map(|s| s.msg.air_temp_k));
        let pressure = span(samples.iter().map(|s| s.msg.pressure_pa));
        let humidity = span(samples.iter().map(|s| s.msg.humidity_pct));
        let material = span(
            samples
                .iter()
                .flat_map(|s| s.msg.material_temp_k.iter().copied()),
        );
        table.row(vec![
            id.clone(),
            samples.len().to_string(),
            range(air, 1.0, ZERO_CELSIUS_K, 3),
            range(pressure, 0.01, 0.0, 2),
            range(humidity, 1.0, 0.0, 1),
            range(material, 1.0, ZERO_CELSIUS_K, 3),
        ]);
    }
    (!table.rows.is_empty()).then_some(table)
}
