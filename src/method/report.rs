//! Human-readable text of the tracer methods' results (the network of stations and points)
//! and plan check, and the units reports show beside SI.

use std::fmt::Write;

use crate::method::multilateration::MultilaterationResults;

pub fn um(v: f64) -> f64 {
    v * 1e6
}

pub fn multilateration_text(r: &MultilaterationResults) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "geocal multilateration — session {}", r.session_id);
    let _ = writeln!(
        s,
        "  {} windows used, {} dropped; {} samples averaged",
        r.extraction.windows_used, r.extraction.windows_dropped, r.extraction.samples_used
    );
    for (reason, count) in &r.extraction.dropped_reasons {
        let _ = writeln!(s, "    dropped {count}: {reason}");
    }
    for chunk in &r.extraction.damaged_chunks {
        let _ = writeln!(s, "    damaged chunk skipped: {}", chunk.describe());
    }
    let _ = writeln!(
        s,
        "  residual RMS {:.3} µm, chi²/dof {:.2} ({} dof), {} iterations{}",
        um(r.residual_rms_m),
        r.chi2_per_dof,
        r.dof,
        r.iterations,
        if r.converged {
            ""
        } else {
            " — NOT CONVERGED"
        }
    );
    let _ = writeln!(s, "  gauge: {}", r.gauge);
    if let Some(robust) = &r.robust {
        let _ = writeln!(
            s,
            "  robust: {} loss beyond {} sigma, {} rounds, {} length(s) down-weighted",
            robust.loss,
            robust.threshold_sigma,
            robust.rounds,
            robust.downweighted.len()
        );
        for d in robust.downweighted.iter().take(5) {
            let _ = writeln!(
                s,
                "    station {} target {} point {} pass {}: residual {:.3} µm, weight {:.3}",
                d.station,
                d.target,
                d.point,
                d.pass,
                um(d.residual_m),
                d.weight
            );
        }
    }
    let _ = writeln!(s, "\n  station        x [m]        y [m]        z [m]   σxyz [µm]           d0 [m]    rms [µm]");
    for st in &r.stations {
        let _ = writeln!(
            s,
            "  {:<8} {:>12.6} {:>12.6} {:>12.6}   {:>5.2} {:>5.2} {:>5.2}  {:>12.6}  {:>8.3}",
            st.id,
            st.position_m[0],
            st.position_m[1],
            st.position_m[2],
            um(st.sigma_m[0]),
            um(st.sigma_m[1]),
            um(st.sigma_m[2]),
            st.home_distance_m,
            um(st.residual_rms_m)
        );
    }
    let n = r.points.len().max(1) as f64;
    let mut rms = [0.0f64; 3];
    let mut max = [0.0f64; 3];
    let mut sigma = [0.0f64; 3];
    for p in &r.points {
        for k in 0..3 {
            rms[k] += p.error_m[k].powi(2) / n;
            max[k] = max[k].max(p.error_m[k].abs());
            sigma[k] += p.sigma_m[k].powi(2) / n;
        }
    }
    let _ = writeln!(
        s,
        "\n  volumetric error over {} points (actual − nominal):",
        r.points.len()
    );
    for (k, axis) in ["x", "y", "z"].iter().enumerate() {
        let _ = writeln!(
            s,
            "    {axis}: RMS {:>7.3} µm, max |e| {:>7.3} µm, mean σ {:>6.3} µm",
            um(rms[k].sqrt()),
            um(max[k]),
            um(sigma[k].sqrt())
        );
    }
    s
}

pub fn plan_check_text(check: &crate::method::plan_check::PlanCheck) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "plan: {} points x {} targets x {} stations; {} lengths for {} unknowns (redundancy {})",
        check.points,
        check.targets,
        check.stations,
        check.observations,
        check.unknowns,
        check.redundancy
    );
    let _ = writeln!(
        s,
        "noise: {} m + {} ppm of the absolute optical path (beam + dead path {} m) per sample, {} samples averaged per dwell",
        check.noise_model.noise_m,
        check.noise_model.noise_ppm,
        check.noise_model.dead_path_m,
        check.samples_per_dwell
    );
    let _ = writeln!(
        s,
        "\npredicted standard uncertainty (Cramér–Rao bound, inner-constraint datum):"
    );
    let _ = writeln!(
        s,
        "  station   σx [µm]  σy [µm]  σz [µm]   σd [µm] per target"
    );
    for st in &check.station_sigmas {
        let d: Vec<String> = st
            .home_distance_sigma_m
            .iter()
            .map(|v| format!("{:.3}", um(*v)))
            .collect();
        let _ = writeln!(
            s,
            "  {:<8} {:>7.3}  {:>7.3}  {:>7.3}   {}",
            st.id,
            um(st.sigma_m[0]),
            um(st.sigma_m[1]),
            um(st.sigma_m[2]),
            d.join(" ")
        );
    }
    if let Some(p) = &check.point_sigma {
        let _ = writeln!(
            s,
            "  points: RMS σ {:.3} / {:.3} / {:.3} µm, max {:.3} / {:.3} / {:.3} µm (x/y/z); worst {}/{}",
            um(p.rms_sigma_m[0]),
            um(p.rms_sigma_m[1]),
            um(p.rms_sigma_m[2]),
            um(p.max_sigma_m[0]),
            um(p.max_sigma_m[1]),
            um(p.max_sigma_m[2]),
            p.worst_point.0,
            p.worst_point.1
        );
    }
    if let Some(g) = &check.geometric_errors {
        let unidentifiable: Vec<&str> = g["unidentifiable"]
            .as_array()
            .map(|a| a.iter().filter_map(|v| v.as_str()).collect())
            .unwrap_or_default();
        let _ = writeln!(
            s,
            "\n  geometric errors: largest predicted σ per error function (identifiable values):"
        );
        if let Some(axes) = g["axes"].as_object() {
            for (axis, a) in axes {
                let mut parts = Vec::new();
                if let Some(errors) = a["errors"].as_object() {
                    for (name, e) in errors {
                        let max = e["sigma"]
                            .as_array()
                            .map(|v| v.iter().filter_map(|x| x.as_f64()).fold(0.0, f64::max))
                            .unwrap_or(0.0);
                        if max > 0.0 {
                            let unit_um = e["unit"].as_str() == Some("m");
                            parts.push(if unit_um {
                                format!("{name} {:.3} µm", um(max))
                            } else {
                                format!("{name} {:.3} µrad", max * 1e6)
                            });
                        }
                    }
                }
                let _ = writeln!(s, "    {axis}: {}", parts.join(", "));
            }
        }
        if !unidentifiable.is_empty() {
            let _ = writeln!(
                s,
                "    not identifiable with these target offsets: {}",
                unidentifiable.join(", ")
            );
        }
    }
    let id = &check.identifiability;
    if id.analysed {
        let _ = writeln!(
            s,
            "\nidentifiability: rank {} of {} unknowns (6 datum freedoms), deficiency {}, condition number {:.3e}",
            id.rank, id.unknowns, id.deficiency, id.condition_number
        );
        for pair in &id.correlated_pairs {
            let _ = writeln!(
                s,
                "  strongly correlated: {} ~ {} ({:+.3})",
                pair.a, pair.b, pair.correlation
            );
        }
    } else {
        let _ = writeln!(
            s,
            "\nidentifiability: not analysed ({} unknowns is too many for the dense analysis)",
            id.unknowns
        );
    }
    for w in &check.warnings {
        let _ = writeln!(s, "warning: {w}");
    }
    s
}
