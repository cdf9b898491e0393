//! Semantic checks of a parsed configuration: what serde cannot see (ranges, counts,
//! cross-references, identifiability of the plan). Each failure names the key.

use std::collections::BTreeSet;

use super::{Config, DriverKind};
use crate::model::kinematics::Structure;

type Invalid = (String, String);

fn fail<T>(key: &str, message: impl Into<String>) -> Result<T, Invalid> {
    Err((key.to_string(), message.into()))
}

fn positive(key: &str, value: f64) -> Result<(), Invalid> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        fail(key, format!("expected a positive number, found {value}"))
    }
}

fn non_negative(key: &str, value: f64) -> Result<(), Invalid> {
    if value.is_finite() && value >= 0.0 {
        Ok(())
    } else {
        fail(key, format!("expected a number >= 0, found {value}"))
    }
}

/// Check a parsed configuration; on failure return (key, what was expected).
pub fn validate(config: &Config) -> Result<(), Invalid> {
    validate_machine(config)?;
    validate_devices(config)?;
    validate_plan(config)?;
    validate_sim(config)
}

fn validate_machine(config: &Config) -> Result<(), Invalid> {
    let machine = &config.machine;
    if let Err(e) = Structure::parse(&machine.structure) {
        return fail("machine.structure", e.to_string());
    }
    for axis in ["x", "y", "z"] {
        let key = format!("machine.travel_m.{axis}");
        let Some([lo, hi]) = machine.travel_m.get(axis) else {
            return fail(
                &key,
                "missing: expected [low, high] in metres for each of x, y, z",
            );
        };
        if !(lo.is_finite() && hi.is_finite() && lo < hi) {
            return fail(&key, format!("expected low < high, found [{lo}, {hi}]"));
        }
    }
    if let Some(extra) = machine
        .travel_m
        .keys()
        .find(|k| !["x", "y", "z"].contains(&k.as_str()))
    {
        return fail(
            &format!("machine.travel_m.{extra}"),
            "unknown axis: expected only x, y, z",
        );
    }
    if machine.targets.is_empty() {
        return fail("machine.targets", "expected at least one target");
    }
    let mut ids = BTreeSet::new();
    for (i, target) in machine.targets.iter().enumerate() {
        if !ids.insert(target.id.as_str()) {
            return fail(
                &format!("machine.targets[{i}].id"),
                format!("duplicate target id `{}`", target.id),
            );
        }
        if target.offset_m.iter().any(|v| !v.is_finite()) {
            return fail(
                &format!("machine.targets[{i}].offset_m"),
                "expected finite numbers",
            );
        }
    }
    Ok(())
}

fn validate_devices(config: &Config) -> Result<(), Invalid> {
    let tracer = &config.devices.tracer;
    non_negative("devices.tracer.noise_m", tracer.noise_m)?;
    non_negative("devices.tracer.noise_ppm", tracer.noise_ppm)?;
    positive("devices.tracer.sample_rate_hz", tracer.sample_rate_hz)?;
    positive("devices.tracer.wavelength_m", tracer.wavelength_m)?;
    non_negative("devices.tracer.dead_path_m", tracer.dead_path_m)?;
    if let Some(env) = &config.devices.environment {
        positive("devices.environment.sample_rate_hz", env.sample_rate_hz)?;
    }
    positive("devices.machine.feed_m_s", config.devices.machine.feed_m_s)
}

fn validate_plan(config: &Config) -> Result<(), Invalid> {
    let plan = &config.plan;
    if plan.targets.is_empty() {
        return fail("plan.targets", "expected at least one target id");
    }
    let mut seen = BTreeSet::new();
    for (i, id) in plan.targets.iter().enumerate() {
        if config.target_offset(id).is_none() {
            let known: Vec<&str> = config
                .machine
                .targets
                .iter()
                .map(|t| t.id.as_str())
                .collect();
            return fail(
                &format!("plan.targets[{i}]"),
                format!("unknown target `{id}`: expected one of {known:?}"),
            );
        }
        if !seen.insert(id.as_str()) {
            return fail(
                &format!("plan.targets[{i}]"),
                format!("target `{id}` listed twice"),
            );
        }
    }
    for (axis, range) in [
        ("x", &plan.grid.x),
        ("y", &plan.grid.y),
        ("z", &plan.grid.z),
    ] {
        let key = format!("plan.grid.{axis}");
        if range.count == 0 {
            return fail(&format!("{key}.count"), "expected at least 1 point");
        }
        if range.count > 1 && range.from == range.to {
            return fail(&key, "from == to with count > 1 would repeat points");
        }
        if let Some([lo, hi]) = config.machine.travel_m.get(axis) {
            for (name, value) in [("from", range.from), ("to", range.to)] {
                if !(value.is_finite() && *lo <= value && value <= *hi) {
                    return fail(
                        &format!("{key}.{name}"),
                        format!("{value} m is outside the travel [{lo}, {hi}] m of axis {axis}"),
                    );
                }
            }
        }
    }
    let points = plan.grid.x.count * plan.grid.y.count * plan.grid.z.count;
    let stations = plan.stations.len();
    if stations < 4 {
        return fail(
            "plan.stations",
            format!(
                "expected at least 4 stations (multilateration needs m >= 4), found {stations}"
            ),
        );
    }
    if points < 16 {
        return fail(
            "plan.grid",
            format!("expected at least 16 points (multilateration needs n >= 16), found {points}"),
        );
    }
    if stations * points < 4 * stations + 3 * points {
        return fail(
            "plan",
            format!(
                "{stations} stations x {points} points give {} lengths for {} unknowns: expected m*n >= 4m + 3n",
                stations * points,
                4 * stations + 3 * points
            ),
        );
    }
    let mut ids = BTreeSet::new();
    for (i, station) in plan.stations.iter().enumerate() {
        if !ids.insert(station.id.as_str()) {
            return fail(
                &format!("plan.stations[{i}].id"),
                format!("duplicate station id `{}`", station.id),
            );
        }
        if let Some(hint) = station.hint_m {
            if hint.iter().any(|v| !v.is_finite()) {
                return fail(
                    &format!("plan.stations[{i}].hint_m"),
                    "expected finite numbers",
                );
            }
        }
    }
    if plan.passes.is_empty() {
        return fail(
            "plan.passes",
            "expected at least one pass (\"forward\" or \"backward\")",
        );
    }
    positive("plan.dwell_s", plan.dwell_s)?;
    positive("plan.stillstand.window_s", plan.stillstand.window_s)?;
    positive("plan.stillstand.tolerance_m", plan.stillstand.tolerance_m)?;
    if plan.stillstand.window_s > plan.dwell_s {
        return fail(
            "plan.stillstand.window_s",
            format!(
                "{} s is longer than plan.dwell_s = {} s: expected window_s <= dwell_s",
                plan.stillstand.window_s, plan.dwell_s
            ),
        );
    }
    if plan.max_dwell_s.is_nan() || plan.max_dwell_s < plan.dwell_s {
        return fail(
            "plan.max_dwell_s",
            format!(
                "expected max_dwell_s >= dwell_s = {} s, found {}",
                plan.dwell_s, plan.max_dwell_s
            ),
        );
    }
    let samples_in_window = plan.stillstand.window_s * config.devices.tracer.sample_rate_hz;
    if samples_in_window < 3.0 {
        return fail(
            "plan.stillstand.window_s",
            format!(
                "holds {samples_in_window:.1} samples at devices.tracer.sample_rate_hz: expected at least 3"
            ),
        );
    }
    Ok(())
}

fn validate_sim(config: &Config) -> Result<(), Invalid> {
    let devices = &config.devices;
    let uses_sim = devices.tracer.driver == DriverKind::Sim
        || devices.machine.driver == DriverKind::Sim
        || devices
            .environment
            .as_ref()
            .is_some_and(|e| e.driver == DriverKind::Sim);
    let Some(sim) = &config.sim else {
        if uses_sim {
            return fail(
                "sim",
                "missing: a device uses driver \"sim\", so a [sim] table is expected",
            );
        }
        return Ok(());
    };
    non_negative("sim.station_hint_error_m", sim.station_hint_error_m)?;
    non_negative("sim.relocation_s", sim.relocation_s)?;
    positive("sim.environment.air_temp_k", sim.environment.air_temp_k)?;
    positive("sim.environment.pressure_pa", sim.environment.pressure_pa)?;
    positive(
        "sim.environment.temp_period_s",
        sim.environment.temp_period_s,
    )?;
    if config.plan.stations.iter().any(|s| s.hint_m.is_none()) {
        return fail(
            "plan.stations",
            "the simulated world places its true stations near their hints: expected hint_m on every station",
        );
    }
    Ok(())
}
