//! Semantic checks of a parsed configuration: what serde cannot see (ranges, counts,
//! cross-references, identifiability of the plan). Each failure names the key.

use std::collections::{BTreeMap, BTreeSet};

use super::{Config, DriverKind, PlanKind};
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
    validate_rotary(config)?;
    validate_plan(config)?;
    super::hil::validate_drivers(config)?;
    if let Some(u) = &config.uncertainty {
        u.validate("uncertainty")?;
    }
    if let Some(n) = &config.normalisation {
        n.validate("normalisation")?;
    }
    if let Some(r) = &config.report {
        for (key, value) in [
            ("report.tolerance_um", r.tolerance_um),
            ("report.tolerance_arcsec", r.tolerance_arcsec),
        ] {
            if let Some(v) = value {
                positive(key, v)?;
            }
        }
    }
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
    let table_stations = plan.rotary.as_ref().map_or(0, |r| r.visits().len());
    let stations = plan.stations.len() + table_stations;
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
    if let Some(rotary) = &plan.rotary {
        for k in 0..table_stations {
            ids.insert(rotary.station_id(k));
        }
    }
    for (i, station) in plan.stations.iter().enumerate() {
        if !ids.insert(station.id.clone()) {
            return fail(
                &format!("plan.stations[{i}].id"),
                format!(
                    "duplicate station id `{}` (table stations are named plan.rotary.station_prefix + step number)",
                    station.id
                ),
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

/// The rotary table and its stations: present exactly for plan kind `rotary_tracer`.
fn validate_rotary(config: &Config) -> Result<(), Invalid> {
    let table = config.devices.rotary_table.as_ref();
    let Some(rotary) = &config.plan.rotary else {
        if config.kind == PlanKind::RotaryTracer {
            return fail(
                "plan.rotary",
                "missing: kind = \"rotary_tracer\" expects a [plan.rotary] table (table, axis_point_m, axis_direction, tracer_hint_m, and angles_rad or step_rad + count)",
            );
        }
        if table.is_some() {
            return fail(
                "devices.rotary_table",
                format!(
                    "kind = \"{}\" uses no rotary table: expected no [devices.rotary_table] (or kind = \"rotary_tracer\")",
                    config.kind.as_str()
                ),
            );
        }
        return Ok(());
    };
    if config.kind != PlanKind::RotaryTracer {
        return fail(
            "plan.rotary",
            format!(
                "kind = \"{}\" has no table stations: expected kind = \"rotary_tracer\" or no [plan.rotary]",
                config.kind.as_str()
            ),
        );
    }
    let Some(table) = table else {
        return fail(
            "devices.rotary_table",
            "missing: kind = \"rotary_tracer\" expects a [devices.rotary_table] with id and driver",
        );
    };
    if table.id.is_empty() || table.id.contains('/') {
        return fail(
            "devices.rotary_table.id",
            format!("expected a non-empty id without '/', found {:?}", table.id),
        );
    }
    if rotary.table != table.id {
        return fail(
            "plan.rotary.table",
            format!(
                "unknown table `{}`: expected `{}` (devices.rotary_table.id)",
                rotary.table, table.id
            ),
        );
    }
    for (key, v) in [
        ("plan.rotary.axis_point_m", rotary.axis_point_m),
        ("plan.rotary.axis_direction", rotary.axis_direction),
        ("plan.rotary.tracer_hint_m", rotary.tracer_hint_m),
    ] {
        if v.iter().any(|x| !x.is_finite()) {
            return fail(key, "expected 3 finite numbers");
        }
    }
    let direction = nalgebra::Vector3::from(rotary.axis_direction);
    if direction.norm() < 1e-9 {
        return fail(
            "plan.rotary.axis_direction",
            "expected a non-zero direction vector",
        );
    }
    let n = direction.normalize();
    let arm = nalgebra::Vector3::from(rotary.tracer_hint_m)
        - nalgebra::Vector3::from(rotary.axis_point_m);
    let radius_m = (arm - n * arm.dot(&n)).norm();
    if radius_m < 0.01 {
        return fail(
            "plan.rotary.tracer_hint_m",
            format!(
                "the tracer stands {radius_m:.4} m from the table axis: expected it off-centre (at least 0.01 m) so that rotating the table moves it"
            ),
        );
    }
    let stepped = rotary.step_rad.is_some() || rotary.count.is_some() || rotary.start_rad.is_some();
    match (&rotary.angles_rad, stepped) {
        (Some(_), true) => {
            return fail(
                "plan.rotary",
                "expected either angles_rad or step_rad + count (+ start_rad), not both",
            )
        }
        (None, false) => {
            return fail(
                "plan.rotary",
                "missing: expected angles_rad (commanded angles, radians) or step_rad + count",
            )
        }
        (None, true) => {
            let Some(step) = rotary.step_rad else {
                return fail(
                    "plan.rotary.step_rad",
                    "missing: expected the step between commanded angles, radians",
                );
            };
            if rotary.count.is_none() {
                return fail(
                    "plan.rotary.count",
                    "missing: expected the number of table stations",
                );
            }
            if !(step.is_finite() && step != 0.0) {
                return fail(
                    "plan.rotary.step_rad",
                    format!("expected a finite non-zero step in radians, found {step}"),
                );
            }
            if let Some(start) = rotary.start_rad {
                if !start.is_finite() {
                    return fail(
                        "plan.rotary.start_rad",
                        "expected a finite angle in radians",
                    );
                }
            }
        }
        (Some(_), false) => {}
    }
    let key = if rotary.angles_rad.is_some() {
        "plan.rotary.angles_rad"
    } else {
        "plan.rotary.count"
    };
    let angles = rotary.commanded_angles_rad();
    if angles.len() < 3 {
        return fail(
            key,
            format!(
                "expected at least 3 table angles (a circle needs 3 stations), found {}",
                angles.len()
            ),
        );
    }
    for (i, a) in angles.iter().enumerate() {
        if !a.is_finite() {
            return fail(key, format!("angle {i} is {a}: expected finite radians"));
        }
        for (k, b) in angles[..i].iter().enumerate() {
            let d = (a - b).rem_euclid(std::f64::consts::TAU);
            if d.min(std::f64::consts::TAU - d) < 1e-3 {
                return fail(
                    key,
                    format!(
                        "angles {k} ({b} rad) and {i} ({a} rad) put the tracer at the same place: expected distinct angles modulo 2π"
                    ),
                );
            }
        }
        if a.abs() > 100.0 {
            return fail(
                key,
                format!("angle {i} is {a}: expected radians (|angle| <= 100), not degrees"),
            );
        }
    }
    if rotary.angles_rad.is_some() && rotary.spacing != super::Spacing::Equal {
        return fail(
            "plan.rotary.spacing",
            "applies to the stepped form (step_rad + count): listed angles_rad are measured as given",
        );
    }
    if rotary.runs == Some(0) {
        return fail(
            "plan.rotary.runs",
            "expected at least 1 bidirectional run (ISO 230-2's cycle has 5)",
        );
    }
    if let Some(overshoot) = rotary.overshoot_rad {
        if rotary.runs.is_none() {
            return fail(
                "plan.rotary.overshoot_rad",
                "applies with runs (the ISO 230-2 cycle): expected runs = N too, or no overshoot_rad",
            );
        }
        if !(overshoot.is_finite() && overshoot > 0.0 && overshoot < 1.0) {
            return fail(
                "plan.rotary.overshoot_rad",
                format!("expected a positive angle in radians below 1, found {overshoot}"),
            );
        }
    }
    // Stations on a circle lie in one plane: multilateration needs one off that plane.
    let off_plane = config.plan.stations.iter().any(|s| {
        s.hint_m.is_some_and(|h| {
            let d = nalgebra::Vector3::from(h) - nalgebra::Vector3::from(rotary.tracer_hint_m);
            d.dot(&n).abs() >= 0.05
        })
    });
    if !off_plane {
        return fail(
            "plan.stations",
            "the table stations all lie in one plane: expected at least one station off the table, with hint_m at least 0.05 m above or below the tracer on the table",
        );
    }
    Ok(())
}

fn validate_sim(config: &Config) -> Result<(), Invalid> {
    let devices = &config.devices;
    let uses_sim = devices.tracer.driver == DriverKind::Sim
        || devices.machine.driver == DriverKind::Sim
        || devices
            .rotary_table
            .as_ref()
            .is_some_and(|r| r.driver == DriverKind::Sim)
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
    if let Some(pace) = sim.pace {
        positive("sim.pace", pace)?;
    }
    if let Some(factor) = sim.tracer_noise_factor {
        positive("sim.tracer_noise_factor", factor)?;
    }
    positive("sim.environment.air_temp_k", sim.environment.air_temp_k)?;
    positive("sim.environment.pressure_pa", sim.environment.pressure_pa)?;
    positive(
        "sim.environment.temp_period_s",
        sim.environment.temp_period_s,
    )?;
    let rotary = &sim.rotary;
    non_negative("sim.rotary.angle_error_rad", rotary.angle_error_rad)?;
    if rotary.harmonics == 0 {
        return fail("sim.rotary.harmonics", "expected at least 1 harmonic");
    }
    non_negative("sim.rotary.axis_offset_m", rotary.axis_offset_m)?;
    non_negative("sim.rotary.axis_tilt_rad", rotary.axis_tilt_rad)?;
    positive("sim.rotary.speed_rad_s", rotary.speed_rad_s)?;
    non_negative("sim.rotary.settle_s", rotary.settle_s)?;
    non_negative("sim.rotary.reversal_rad", rotary.reversal_rad)?;
    non_negative("sim.rotary.repeatability_rad", rotary.repeatability_rad)?;
    sim.effects.validate()?;
    validate_compensation(&sim.compensation)?;
    if config.plan.stations.iter().any(|s| s.hint_m.is_none()) {
        return fail(
            "plan.stations",
            "the simulated world places its true stations near their hints: expected hint_m on every station",
        );
    }
    Ok(())
}

/// Each axis table names an axis once, cross tables name theirs in the file, one controller
/// compensates an axis, and every file loads as its controller would read it.
fn validate_compensation(tables: &[super::sim::SimCompensation]) -> Result<(), Invalid> {
    use crate::compensate::TableFormat;
    let mut axis_tables = BTreeMap::new();
    let mut cross_targets = BTreeMap::new();
    let mut cross_files = BTreeMap::new();
    for (i, c) in tables.iter().enumerate() {
        let key = format!("sim.compensation[{i}]");
        if c.is_cross() {
            if c.controller_axis.is_some() {
                return fail(
                    &format!("{key}.controller_axis"),
                    "only for an axis's $AA_ENC_COMP table: the $AN_CEC tables name their axes \
                     (map them with `axis_names`)",
                );
            }
            if let Some(j) = cross_files.insert(c.file.clone(), i) {
                return fail(
                    &format!("{key}.file"),
                    format!(
                        "the same $AN_CEC file as sim.compensation[{j}]: its tables would act twice"
                    ),
                );
            }
            if let Some(names) = &c.axis_names {
                if names.len() != 3 || names.iter().any(|n| n.trim().is_empty()) {
                    return fail(
                        &format!("{key}.axis_names"),
                        format!("expected the 3 machine axis names of x, y, z, found {names:?}"),
                    );
                }
            }
            let cross =
                crate::compensate::applied::load_cross_tables(&c.file, &c.machine_axis_names())
                    .map_err(|e| (format!("{key}.file"), e.to_string()))?;
            for t in cross {
                cross_targets.entry(t.compensated).or_insert(i);
            }
            continue;
        }
        let Some(axis_name) = c.axis.as_deref() else {
            return fail(
                &format!("{key}.axis"),
                format!(
                    "missing: a {} table acts on one axis, expected x, y or z (only a sinumerik \
                     entry without `axis` applies its file's $AN_CEC cross tables)",
                    c.format.name()
                ),
            );
        };
        let Some(axis) = c.axis_index() else {
            return fail(
                &format!("{key}.axis"),
                format!("expected x, y or z, found `{axis_name}`"),
            );
        };
        if c.axis_names.is_some() {
            return fail(
                &format!("{key}.axis_names"),
                "only for the $AN_CEC cross tables of a sinumerik entry without `axis` \
                 (an axis table's name is `controller_axis`)",
            );
        }
        if axis_tables.insert(axis, (i, c.format)).is_some() {
            return fail(
                &format!("{key}.axis"),
                format!("axis {axis_name} has a table already: one table per axis"),
            );
        }
        crate::compensate::load_table(c.format, &c.file, &c.controller_axis_name())
            .map_err(|e| (format!("{key}.file"), e.to_string()))?;
    }
    for (axis, cross_entry) in cross_targets {
        if let Some((i, format)) = axis_tables.get(&axis) {
            if *format != TableFormat::Sinumerik {
                return fail(
                    &format!("sim.compensation[{i}].format"),
                    format!(
                        "axis {} has a {} table, but the $AN_CEC tables of \
                         sim.compensation[{cross_entry}] (SINUMERIK) compensate it too: one \
                         controller per machine",
                        crate::compensate::AXES[axis],
                        format.name()
                    ),
                );
            }
        }
    }
    Ok(())
}
