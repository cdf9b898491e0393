//! Compensation tables: each format exported from a calibration, read back as its controller
//! reads it (round trip), the parsers fuzzed, and the closed loop: the demo machine calibrated,
//! LinuxCNC and SINUMERIK tables applied by the simulated controller, the same plan run again.

use crate::common;

use std::path::{Path, PathBuf};

use geocal::compensate::linuxcnc::{CompTable, CompType};
use geocal::compensate::sinumerik::{CecTable, Program, SinumerikOptions};
use geocal::compensate::{
    export, table, Calibration, Export, ExportOptions, TableFormat, AXES, POSITIONING,
};
use proptest::prelude::*;

/// Run `config_text` in `dir`; the results file.
fn calibrate(config_text: &str, dir: &Path) -> PathBuf {
    let config =
        geocal::config::Config::parse(config_text, &dir.join("config.toml")).expect("config");
    let output = geocal::kinds::tracer_plan::run::run(
        &config,
        &geocal::run::RunOptions {
            out_dir: dir.to_path_buf(),
            truth: None,
            progress: false,
            settings: Default::default(),
            control: Default::default(),
        },
    )
    .expect("run");
    output.results_path
}

fn write_all(e: &Export, dir: &Path) {
    std::fs::create_dir_all(dir).expect("dir");
    for f in &e.files {
        std::fs::write(dir.join(&f.name), &f.text).expect("write");
    }
}

fn only_axis(axis: usize) -> ExportOptions {
    ExportOptions {
        axes: vec![axis],
        ..Default::default()
    }
}

/// The deviation d(q) the tables were made from, on the table's own nominals (metres).
fn deviation_at(cal: &Calibration, axis: usize, q_m: f64) -> f64 {
    let curve = cal.positioning(axis).expect("positioning");
    curve.at(q_m).expect("value") - curve.at(curve.positions_m[0]).expect("datum")
}

/// Positioning values and sigmas of every axis of a results file.
fn positioning(cal: &Calibration) -> [(Vec<f64>, Vec<f64>); 3] {
    std::array::from_fn(|k| {
        let c = cal.positioning(k).expect("positioning");
        (
            c.values.iter().map(|v| v.expect("value")).collect(),
            c.sigma.iter().map(|s| s.unwrap_or(0.0)).collect(),
        )
    })
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

#[test]
fn closed_loop_tables_remove_the_positioning_errors() {
    let dir = tempfile::tempdir().expect("tempdir");
    let base = common::DEMO.to_string();
    let before_path = calibrate(&base, &dir.path().join("before"));
    let cal = Calibration::load(&before_path).expect("results");
    let sin = SinumerikOptions::default();

    // x: LinuxCNC type 1, y: LinuxCNC type 0, z: SINUMERIK encoder table.
    let tables = dir.path().join("tables");
    let lx = export(&cal, TableFormat::LinuxcncType1, &only_axis(0), &sin).expect("type 1");
    let ly = export(&cal, TableFormat::LinuxcncType0, &only_axis(1), &sin).expect("type 0");
    let sz = export(&cal, TableFormat::Sinumerik, &only_axis(2), &sin).expect("sinumerik");
    write_all(&lx, &tables.join("lx"));
    write_all(&ly, &tables.join("ly"));
    write_all(&sz, &tables.join("sz"));
    let interp: Vec<f64> = [&lx, &ly, &sz]
        .iter()
        .map(|e| e.steps[0].interpolation_error_m)
        .collect();

    // Round trip: what each controller loads is the deviation with the format's sign.
    let x = CompTable::parse(
        &std::fs::read_to_string(tables.join("lx/comp-x.txt")).expect("x"),
        CompType::Type1,
        Path::new("comp-x.txt"),
    )
    .expect("x table");
    for e in &x.entries {
        let d = deviation_at(&cal, 0, e.nominal * 1e-3);
        assert!(
            (e.fwd_trim as f64 * 1e-3 + d).abs() < 1e-9,
            "x at {}",
            e.nominal
        );
        assert_eq!(e.fwd_trim, e.rev_trim, "no reversal fitted");
    }
    let y = CompTable::parse(
        &std::fs::read_to_string(tables.join("ly/comp-y.txt")).expect("y"),
        CompType::Type0,
        Path::new("comp-y.txt"),
    )
    .expect("y table");
    for e in &y.entries {
        let d = deviation_at(&cal, 1, e.nominal * 1e-3);
        assert!(
            (e.fwd_trim as f64 * 1e-3 + d).abs() < 2e-9,
            "y at {}",
            e.nominal
        );
    }
    let z_text = std::fs::read_to_string(tables.join("sz/eec.ini")).expect("z");
    let z = Program::parse(&z_text, Path::new("eec.ini"))
        .expect("program")
        .enc_comp(0, "Z1", Path::new("eec.ini"))
        .expect("z table");
    for (n, v) in z.values_mm.iter().enumerate() {
        let q_m = (z.min_mm + n as f64 * z.step_mm) * 1e-3;
        assert!(
            (v * 1e-3 - deviation_at(&cal, 2, q_m)).abs() < 1e-9,
            "z point {n}"
        );
    }
    assert!(x.entries.len() <= 256 && z.values_mm.len() <= sin.max_points);

    // The verification run: the same plan on the compensated machine, with noise of its own
    // (the same noise again would cancel the first calibration's error exactly).
    let compensated = |x_file: &Path| {
        format!(
            "{base}noise_seed = 4242\ncompensation = [\n  {{ format = \"linuxcnc-type1\", file = \"{}\", axis = \"x\" }},\n  \
             {{ format = \"linuxcnc-type0\", file = \"{}\", axis = \"y\" }},\n  \
             {{ format = \"sinumerik\", file = \"{}\", axis = \"z\" }},\n]\n",
            x_file.display(),
            tables.join("ly/comp-y.txt").display(),
            tables.join("sz/eec.ini").display()
        )
    };
    let after_path = calibrate(
        &compensated(&tables.join("lx/comp-x.txt")),
        &dir.path().join("after"),
    );
    let after = Calibration::load(&after_path).expect("results after");
    let (b, a) = (positioning(&cal), positioning(&after));
    for k in 0..3 {
        let ((vb, sb), (va, sa)) = (&b[k], &a[k]);
        // The residual carries the first calibration's error and the second's noise.
        let bound: Vec<f64> = (0..va.len())
            .map(|i| 2.0 * sb[i].hypot(sa[i]) + interp[k])
            .collect();
        println!(
            "{}: RMS before {:.3} µm, after {:.3} µm; largest |after|/bound {:.2}; \
             interpolation error {:.2e} µm; σ before {:.3} µm, after {:.3} µm",
            POSITIONING[k],
            rms(vb) * 1e6,
            rms(va) * 1e6,
            va.iter()
                .zip(&bound)
                .map(|(v, b)| v.abs() / b.max(1e-15))
                .fold(0.0, f64::max),
            interp[k] * 1e6,
            rms(sb) * 1e6,
            rms(sa) * 1e6
        );
        let z: Vec<String> = (0..va.len())
            .map(|i| format!("{:.2}", va[i] / sb[i].hypot(sa[i]).max(1e-15)))
            .collect();
        println!("  after/σ per position: {}", z.join(" "));
        // The values along one curve are correlated (each is relative to the datum at the
        // first position), so the curve is judged by its RMS against the RMS of 2σ: a
        // per-position 2σ test over 11 values fails about every second seed by chance.
        let sigma_rms = rms(&(0..va.len())
            .map(|i| sb[i].hypot(sa[i]))
            .collect::<Vec<_>>());
        assert!(
            rms(va) <= 2.0 * sigma_rms + interp[k],
            "{}: RMS {:.4} µm left after compensation, bound 2σ + interpolation = {:.4} µm",
            POSITIONING[k],
            rms(va) * 1e6,
            (2.0 * sigma_rms + interp[k]) * 1e6
        );
        assert!(
            rms(va) < 0.5 * rms(vb),
            "{}: no improvement",
            POSITIONING[k]
        );
    }

    // The session records which tables the simulated controller applied.
    let session = geocal::session::reader::read_session(&after_path.with_file_name("session.mcap"))
        .expect("session");
    let machine = session
        .header
        .devices
        .iter()
        .find(|d| d.kind == "machine")
        .expect("machine device");
    let applied = machine.extra["compensation"].to_string();
    assert!(
        applied.contains("linuxcnc-type1") && applied.contains("comp-x.txt"),
        "{applied}"
    );

    // A table of the wrong sign doubles the error instead of removing it.
    let flipped: String = std::fs::read_to_string(tables.join("lx/comp-x.txt"))
        .expect("x")
        .lines()
        .map(|l| {
            let f: Vec<f64> = l.split(' ').map(|v| v.parse().expect("number")).collect();
            format!("{:.6} {:.6} {:.6}\n", f[0], -f[1], -f[2])
        })
        .collect();
    let flipped_file = tables.join("comp-x-flipped.txt");
    std::fs::write(&flipped_file, flipped).expect("write");
    let wrong = Calibration::load(&calibrate(
        &compensated(&flipped_file),
        &dir.path().join("wrong"),
    ))
    .expect("results wrong sign");
    let (vw, _) = &positioning(&wrong)[0];
    println!(
        "EXX with the wrong sign: RMS {:.3} µm (before {:.3} µm)",
        rms(vw) * 1e6,
        rms(&b[0].0) * 1e6
    );
    assert!(rms(vw) > 1.5 * rms(&b[0].0), "a wrong sign must show");
}

/// The cross pairs (base, compensated) a SINUMERIK export tables.
const CROSS_PAIRS: [(usize, usize); 6] = [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)];

/// Values and sigmas of the cross deviation `compensated` on `base` (straightness with the
/// squareness of the pair, as the `$AN_CEC` table holds it).
fn cross_curve(cal: &Calibration, base: usize, compensated: usize) -> (Vec<f64>, Vec<f64>) {
    let c = cal.cross(base, compensated).expect("identifiable");
    (
        c.values.iter().map(|v| v.expect("value")).collect(),
        c.sigma.iter().map(|s| s.unwrap_or(0.0)).collect(),
    )
}

/// The largest departure of an equally spaced table (mm) from `cal`'s curve of the pair,
/// shifted to zero at the first grid position, sampled finely over the calibrated travel.
fn table_departure(cal: &Calibration, base: usize, compensated: usize, table: &CecTable) -> f64 {
    let curve = cal.cross(base, compensated).expect("identifiable");
    let (lo, hi) = (
        curve.positions_m[0],
        *curve.positions_m.last().expect("grid"),
    );
    let zero = curve.at(lo).expect("value");
    (0..=4000)
        .map(|i| lo + (hi - lo) * f64::from(i) / 4000.0)
        .map(|q| {
            let u = (q * 1e3 - table.min_mm) / table.step_mm;
            let n = (u.floor() as usize).min(table.values_mm.len() - 2);
            let f = u - n as f64;
            let v = table.values_mm[n] + f * (table.values_mm[n + 1] - table.values_mm[n]);
            (v * 1e-3 - (curve.at(q).expect("value") - zero)).abs()
        })
        .fold(0.0, f64::max)
}

#[test]
fn closed_loop_cross_tables_remove_straightness_and_squareness() {
    let dir = tempfile::tempdir().expect("tempdir");
    let base = common::DEMO.to_string();
    let cal = Calibration::load(&calibrate(&base, &dir.path().join("before"))).expect("results");
    let sin = SinumerikOptions::default();
    let tables = dir.path().join("sinumerik");
    let e = export(
        &cal,
        TableFormat::Sinumerik,
        &ExportOptions::default(),
        &sin,
    )
    .expect("export");
    write_all(&e, &tables);
    let cec_file = tables.join("cec.ini");
    let cec = Program::parse(&std::fs::read_to_string(&cec_file).expect("cec"), &cec_file)
        .expect("program")
        .cec_tables(&cec_file)
        .expect("tables");
    assert_eq!(
        cec.len(),
        6,
        "every straightness of the demo is identifiable"
    );
    let axis_of = |name: &str| {
        ["X1", "Y1", "Z1"]
            .iter()
            .position(|n| *n == name)
            .expect("axis")
    };
    let interp: Vec<f64> = CROSS_PAIRS
        .iter()
        .map(|&(b, c)| {
            let t = cec
                .iter()
                .find(|t| axis_of(&t.input_axis) == b && axis_of(&t.output_axis) == c)
                .expect("a table for every pair");
            table_departure(&cal, b, c, t)
        })
        .collect();

    // Every SINUMERIK table: the encoder tables of x, y, z and the cross tables.
    let verify = |cec: &Path, out: &str| {
        let eec = tables.join("eec.ini");
        let text = format!(
            "{base}noise_seed = 4242\ncompensation = [\n\
             {{ format = \"sinumerik\", file = \"{e}\", axis = \"x\" }},\n\
             {{ format = \"sinumerik\", file = \"{e}\", axis = \"y\" }},\n\
             {{ format = \"sinumerik\", file = \"{e}\", axis = \"z\" }},\n\
             {{ format = \"sinumerik\", file = \"{c}\" }},\n]\n",
            e = eec.display(),
            c = cec.display()
        );
        Calibration::load(&calibrate(&text, &dir.path().join(out))).expect("results after")
    };
    let after = verify(&cec_file, "after");
    for (k, &(b, c)) in CROSS_PAIRS.iter().enumerate() {
        let ((vb, sb), (va, sa)) = (cross_curve(&cal, b, c), cross_curve(&after, b, c));
        let sigma: Vec<f64> = sb.iter().zip(&sa).map(|(b, a)| b.hypot(*a)).collect();
        let bound = 2.0 * rms(&sigma) + interp[k];
        println!(
            "{} on {}: RMS before {:.3} µm, after {:.3} µm; RMS σ {:.3} µm (before {:.3}, after \
             {:.3}); interpolation error {:.4} µm; bound {:.3} µm",
            AXES[c],
            AXES[b],
            rms(&vb) * 1e6,
            rms(&va) * 1e6,
            rms(&sigma) * 1e6,
            rms(&sb) * 1e6,
            rms(&sa) * 1e6,
            interp[k] * 1e6,
            bound * 1e6
        );
        assert!(
            rms(&va) <= bound,
            "{} on {}: RMS {:.4} µm left, bound 2σ + interpolation = {:.4} µm",
            AXES[c],
            AXES[b],
            rms(&va) * 1e6,
            bound * 1e6
        );
        assert!(
            rms(&va) < 0.5 * rms(&vb),
            "{} on {}: no improvement",
            AXES[c],
            AXES[b]
        );
    }
    // The encoder tables act alongside.
    let (b, a) = (positioning(&cal), positioning(&after));
    for k in 0..3 {
        println!(
            "{}: RMS before {:.3} µm, after {:.3} µm",
            POSITIONING[k],
            rms(&b[k].0) * 1e6,
            rms(&a[k].0) * 1e6
        );
        assert!(rms(&a[k].0) < 0.5 * rms(&b[k].0), "{}", POSITIONING[k]);
    }

    // Cross tables of the wrong sign double the errors instead of removing them.
    let flipped: String = std::fs::read_to_string(&cec_file)
        .expect("cec")
        .lines()
        .map(
            |l| match l.strip_prefix("$AN_CEC[").and_then(|r| r.split_once("]=")) {
                Some((index, v)) => {
                    let v: f64 = v.parse().expect("number");
                    format!("$AN_CEC[{index}]={:.6}\n", -v)
                }
                None => format!("{l}\n"),
            },
        )
        .collect();
    let flipped_file = tables.join("cec-flipped.ini");
    std::fs::write(&flipped_file, flipped).expect("write");
    let wrong = verify(&flipped_file, "wrong");
    for &(b, c) in &CROSS_PAIRS {
        let (vb, vw) = (cross_curve(&cal, b, c).0, cross_curve(&wrong, b, c).0);
        println!(
            "{} on {} with the wrong sign: RMS {:.3} µm (before {:.3} µm)",
            AXES[c],
            AXES[b],
            rms(&vw) * 1e6,
            rms(&vb) * 1e6
        );
        assert!(
            rms(&vw) > 1.5 * rms(&vb),
            "{} on {}: a wrong sign must show",
            AXES[c],
            AXES[b]
        );
    }
}

#[test]
fn cross_table_entries_are_checked_by_key() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cec = "$AN_CEC[0,0]=0.0\n$AN_CEC[0,1]=0.001\n$AN_CEC_INPUT_AXIS[0]=(X1)\n\
               $AN_CEC_OUTPUT_AXIS[0]=(Y1)\n$AN_CEC_STEP[0]=100.0\n$AN_CEC_MIN[0]=0.0\n\
               $AN_CEC_MAX[0]=100.0\nM17\n";
    std::fs::write(dir.path().join("cec.ini"), cec).expect("write");
    std::fs::write(
        dir.path().join("eec.ini"),
        "$AA_ENC_COMP[0,0,Y1]=0.0\n$AA_ENC_COMP[0,1,Y1]=0.001\n$AA_ENC_COMP_STEP[0,Y1]=100.0\n\
         $AA_ENC_COMP_MIN[0,Y1]=0.0\n$AA_ENC_COMP_MAX[0,Y1]=100.0\nM17\n",
    )
    .expect("write");
    std::fs::write(dir.path().join("comp-y.txt"), "0 0 0\n100 0.001 0.001\n").expect("write");
    let parse = |entries: &str| {
        let text = format!("{}compensation = [{entries}]\n", common::DEMO);
        geocal::config::Config::parse(&text, &dir.path().join("c.toml")).map(|_| ())
    };
    parse(r#"{ format = "sinumerik", file = "cec.ini" }, { format = "sinumerik", file = "eec.ini", axis = "y" }"#)
        .expect("cross and encoder tables of one controller");
    for (entries, key, expect) in [
        (
            r#"{ format = "linuxcnc-type1", file = "comp-y.txt" }"#,
            "sim.compensation[0].axis",
            "missing",
        ),
        (
            r#"{ format = "sinumerik", file = "eec.ini" }"#,
            "sim.compensation[0].file",
            "no $AN_CEC table",
        ),
        (
            r#"{ format = "sinumerik", file = "cec.ini", axis_names = ["A1", "B1"] }"#,
            "sim.compensation[0].axis_names",
            "3 machine axis names",
        ),
        (
            r#"{ format = "sinumerik", file = "cec.ini", axis_names = ["X2", "Y2", "Z2"] }"#,
            "sim.compensation[0].file",
            "input axis `X1`",
        ),
        (
            r#"{ format = "sinumerik", file = "cec.ini" }, { format = "linuxcnc-type1", file = "comp-y.txt", axis = "y" }"#,
            "sim.compensation[1].format",
            "one controller",
        ),
        (
            r#"{ format = "sinumerik", file = "cec.ini" }, { format = "sinumerik", file = "cec.ini" }"#,
            "sim.compensation[1].file",
            "act twice",
        ),
        (
            r#"{ format = "sinumerik", file = "cec.ini", controller_axis = "Y1" }"#,
            "sim.compensation[0].controller_axis",
            "axis_names",
        ),
    ] {
        let e = parse(entries).unwrap_err().to_string();
        assert!(e.contains(key) && e.contains(expect), "{entries}: {e}");
    }
}

#[test]
fn csv_and_json_tables_round_trip() {
    let dir = tempfile::tempdir().expect("tempdir");
    let results = calibrate(common::DEMO, dir.path());
    let cal = Calibration::load(&results).expect("results");
    let options = ExportOptions {
        step_m: Some(0.05),
        ..Default::default()
    };
    let sin = SinumerikOptions::default();
    let csv = export(&cal, TableFormat::Csv, &options, &sin).expect("csv");
    let json = export(&cal, TableFormat::Json, &options, &sin).expect("json");
    let rows = table::parse_csv(&csv.files[0].text, Path::new("errors.csv")).expect("csv back");
    let parsed = table::parse_json(&json.files[0].text, Path::new("errors.json")).expect("json");
    assert_eq!(rows, parsed.rows, "CSV and JSON hold the same values");
    // Each row is the results' own value, interpolated at the table position.
    let mut checked = 0;
    for r in &rows {
        let (Some(axis), Some(q), Some(v)) = (&r.axis, r.position_m, r.value) else {
            continue;
        };
        let k = AXES.iter().position(|a| a == axis).expect("axis");
        let expect = cal.axes[k][&r.error].at(q).expect("identified");
        assert!((v - expect).abs() <= 1e-15 * (1.0 + expect.abs()), "{r:?}");
        checked += 1;
    }
    let names: std::collections::BTreeSet<&str> = rows.iter().map(|r| r.error.as_str()).collect();
    assert_eq!(names.len(), 21, "{names:?}");
    assert!(checked > 100, "{checked}");
    // 5 cm over the 1.2 m of x: 25 positions.
    assert_eq!(csv.steps[0].entries, 25);
}

#[test]
fn results_without_geometric_errors_are_refused_by_name() {
    let e = Calibration::parse(
        r#"{"kind":"rotary_tracer","session_id":"s"}"#,
        Path::new("r.json"),
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("r.json") && e.contains("geometric_errors"),
        "{e}"
    );
    let e = Calibration::parse("{", Path::new("r.json"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("r.json"), "{e}");
}

fn table_text(rows: &[(f64, f64, f64)]) -> String {
    rows.iter()
        .map(|(a, b, c)| format!("{a:.6} {b:.6} {c:.6}\n"))
        .collect()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(500))]

    /// Whatever the bytes, the LinuxCNC reader returns at most 256 strictly increasing entries.
    #[test]
    fn linuxcnc_reader_never_panics(text in ".{0,400}") {
        let t = CompTable::read_as_linuxcnc(&text, CompType::Type1);
        prop_assert!(t.entries.len() <= 256);
        prop_assert!(t.entries.windows(2).all(|w| w[1].nominal > w[0].nominal));
        let _ = CompTable::parse(&text, CompType::Type0, Path::new("f"));
    }

    #[test]
    fn linuxcnc_tables_round_trip(
        start in -1000.0f64..1000.0,
        steps in prop::collection::vec((0.001f64..50.0, -0.5f64..0.5, -0.5f64..0.5), 1..256),
    ) {
        let mut q = start;
        let rows: Vec<(f64, f64, f64)> = steps
            .iter()
            .map(|(dq, f, r)| {
                q += dq;
                (q, *f, *r)
            })
            .collect();
        let t = CompTable::parse(&table_text(&rows), CompType::Type1, Path::new("f"))
            .map_err(|e| TestCaseError::fail(e.to_string()))?;
        prop_assert_eq!(t.entries.len(), rows.len());
        for (e, (q, f, r)) in t.entries.iter().zip(&rows) {
            prop_assert!((e.nominal - q).abs() <= 1e-6);
            prop_assert!((e.fwd_trim as f64 - f).abs() <= 1e-6);
            prop_assert!((e.rev_trim as f64 - r).abs() <= 1e-6);
        }
    }

    #[test]
    fn sinumerik_reader_never_panics(text in "[$A-Z_\\[\\]0-9,.=;() \n-]{0,300}") {
        if let Ok(p) = Program::parse(&text, Path::new("p")) {
            for (e, axis) in p.enc_axes() {
                let _ = p.enc_comp(e, &axis, Path::new("p"));
            }
            let _ = p.cec_tables(Path::new("p"));
        }
    }

    #[test]
    fn sinumerik_tables_round_trip(
        min in -500.0f64..500.0,
        step in 0.5f64..50.0,
        values in prop::collection::vec(-0.9f64..0.9, 2..200),
    ) {
        let mut text = String::from("%_N_AX_EEC_INI\nCHANDATA(1)\n; test\n");
        for (n, v) in values.iter().enumerate() {
            text.push_str(&format!("$AA_ENC_COMP[0,{n},X1]={v:.6}\n"));
        }
        let max = min + (values.len() - 1) as f64 * step;
        text.push_str(&format!(
            "$AA_ENC_COMP_STEP[0,X1]={step}\n$AA_ENC_COMP_MIN[0,X1]={min}\n\
             $AA_ENC_COMP_MAX[0,X1]={max}\n$AA_ENC_COMP_IS_MODULO[0,X1]=0\nM17\n"
        ));
        let t = Program::parse(&text, Path::new("p"))
            .and_then(|p| p.enc_comp(0, "X1", Path::new("p")))
            .map_err(|e| TestCaseError::fail(e.to_string()))?;
        prop_assert_eq!(t.values_mm.len(), values.len());
        for (a, b) in t.values_mm.iter().zip(&values) {
            prop_assert!((a - b).abs() <= 1e-6);
        }
    }

    #[test]
    fn csv_reader_never_panics(text in "[a-zE#,.0-9\n -]{0,300}") {
        let _ = table::parse_csv(&format!("error,axis,position_m,value,unit,sigma\n{text}"), Path::new("c"));
        let _ = table::parse_csv(&text, Path::new("c"));
        let _ = table::parse_json(&text, Path::new("j"));
    }
}

/// Results with EXX = 10 µm/m·(x − 0.1), every other error zero, on `structure`.
fn synthetic_results(structure: &str, reversal_bx_m: Option<f64>) -> String {
    let names = |axis: char| -> Vec<String> {
        let a = axis.to_ascii_uppercase();
        ["X", "Y", "Z", "A", "B", "C"]
            .iter()
            .map(|e| format!("E{e}{a}"))
            .collect()
    };
    let positions = [0.1, 0.5, 0.9];
    let axes: serde_json::Map<String, serde_json::Value> = ['x', 'y', 'z']
        .iter()
        .map(|&axis| {
            let errors: serde_json::Map<String, serde_json::Value> = names(axis)
                .into_iter()
                .map(|n| {
                    let values: Vec<f64> = positions
                        .iter()
                        .map(|q| if n == "EXX" { 10e-6 * (q - 0.1) } else { 0.0 })
                        .collect();
                    let unit = if "XYZ".contains(&n[1..2]) { "m" } else { "rad" };
                    (
                        n,
                        serde_json::json!({"unit": unit, "values": values, "sigma": [0.0, 1e-7, 1e-7]}),
                    )
                })
                .collect();
            (
                axis.to_string(),
                serde_json::json!({"positions_m": positions, "errors": errors}),
            )
        })
        .collect();
    let mut r = serde_json::json!({
        "kind": "multilateration",
        "session_id": "synthetic",
        "geometric_errors": {
            "structure": structure,
            "axes": axes,
            "squareness": {
                "EC0Y": {"value_rad": 0.0, "sigma_rad": 1e-7},
                "EA0Z": {"value_rad": 0.0, "sigma_rad": 1e-7},
                "EB0Z": {"value_rad": 0.0, "sigma_rad": 1e-7}
            }
        }
    });
    if let Some(b) = reversal_bx_m {
        r["effects"] = serde_json::json!({"reversal": {"bx_m": b, "by_m": 0.0, "bz_m": 0.0}});
    }
    r.to_string()
}

#[test]
fn workpiece_branch_flips_the_sign_and_reversal_splits_the_columns() {
    let sin = SinumerikOptions::default();
    let last_trims = |structure: &str, b: Option<f64>| {
        let cal = Calibration::parse(&synthetic_results(structure, b), Path::new("r.json"))
            .expect("results");
        let e = export(&cal, TableFormat::LinuxcncType1, &only_axis(0), &sin).expect("export");
        let t = CompTable::parse(&e.files[0].text, CompType::Type1, Path::new("comp-x.txt"))
            .expect("table");
        let last = *t.entries.last().expect("entries");
        (last.fwd_trim as f64 * 1e-3, last.rev_trim as f64 * 1e-3)
    };
    // EXX at 0.9 m is +8 µm: a tool-branch X is trimmed by −8 µm, a table X by +8 µm.
    let (tool, _) = last_trims("FYXZ", None);
    let (table, _) = last_trims("XFYZ", None);
    assert!((tool + 8e-6).abs() < 1e-10, "{tool}");
    assert!((table - 8e-6).abs() < 1e-10, "{table}");
    // A reversal B = 2 µm: the + approach overshoots by B/2, so its trim is 1 µm more negative.
    let (fwd, rev) = last_trims("FYXZ", Some(2e-6));
    assert!(
        (fwd + 9e-6).abs() < 1e-10 && (rev + 7e-6).abs() < 1e-10,
        "{fwd} {rev}"
    );
    // The LinuxCNC file holds numbers only; the INI fragment carries the description.
    let cal = Calibration::parse(&synthetic_results("FYXZ", None), Path::new("r.json")).unwrap();
    let e = export(
        &cal,
        TableFormat::LinuxcncType0,
        &ExportOptions::default(),
        &sin,
    )
    .unwrap();
    for f in &e.files {
        if f.name.ends_with(".txt") {
            assert!(f
                .text
                .lines()
                .all(|l| geocal::compensate::linuxcnc::scan_three(l).is_some()));
        } else {
            assert!(f.text.contains("[JOINT_0]") && f.text.contains("COMP_FILE_TYPE = 0"));
        }
    }
}

#[test]
fn limits_are_clear_errors() {
    let cal = Calibration::parse(&synthetic_results("FYXZ", None), Path::new("r.json")).unwrap();
    let sin = SinumerikOptions::default();
    let fine = ExportOptions {
        step_m: Some(1e-4),
        ..only_axis(0)
    };
    let e = export(&cal, TableFormat::LinuxcncType1, &fine, &sin)
        .unwrap_err()
        .to_string();
    assert!(e.contains("axis x") && e.contains("256"), "{e}");
    let small = SinumerikOptions {
        max_value_m: 1e-6,
        ..SinumerikOptions::default()
    };
    let e = export(&cal, TableFormat::Sinumerik, &only_axis(0), &small)
        .unwrap_err()
        .to_string();
    assert!(e.contains("X1") && e.contains("limit"), "{e}");
    // A coarse step warns: a curve that kinks at 0.5 m, tabled at 0.1 and 0.9 m only.
    let mut r: serde_json::Value = serde_json::from_str(&synthetic_results("FYXZ", None)).unwrap();
    r["geometric_errors"]["axes"]["x"]["errors"]["EXX"]["values"] =
        serde_json::json!([0.0, 8e-6, 0.0]);
    let cal = Calibration::parse(&r.to_string(), Path::new("r.json")).unwrap();
    let coarse = ExportOptions {
        step_m: Some(0.8),
        ..only_axis(0)
    };
    let e = export(&cal, TableFormat::Sinumerik, &coarse, &sin).unwrap();
    assert!(
        (e.steps[0].interpolation_error_m - 8e-6).abs() < 1e-12,
        "{:?}",
        e.steps
    );
    assert_eq!(e.warnings().count(), 1);
    let fine = export(&cal, TableFormat::Sinumerik, &only_axis(0), &sin).unwrap();
    assert!(fine.steps[0].interpolation_error_m < 1e-12 && fine.warnings().count() == 0);
}

#[test]
fn the_simulated_controller_refuses_a_table_linuxcnc_would_load_empty() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("comp-x.txt");
    std::fs::write(&file, "# nominal fwd rev\n0 0 0\n100 0.001 0.001\n").expect("write");
    let text = format!(
        "{}compensation = [{{ format = \"linuxcnc-type1\", file = \"comp-x.txt\", axis = \"x\" }}]\n",
        common::DEMO
    );
    let e = geocal::config::Config::parse(&text, &dir.path().join("c.toml"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("sim.compensation[0].file") && e.contains("empty table"),
        "{e}"
    );
    let e = geocal::config::Config::parse(
        &text.replace("axis = \"x\"", "axis = \"u\""),
        &dir.path().join("c.toml"),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("sim.compensation[0].axis"), "{e}");
}

#[test]
fn geocal_compensate_writes_the_files_and_names_bad_arguments() {
    let dir = tempfile::tempdir().expect("tempdir");
    let results = dir.path().join("results.json");
    std::fs::write(&results, synthetic_results("FYXZ", Some(1e-6))).expect("write");
    let geocal = |args: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_geocal"))
            .arg("compensate")
            .arg(&results)
            .args(args)
            .output()
            .expect("geocal")
    };
    let out = dir.path().join("lcnc");
    let o = geocal(&[
        "--format",
        "linuxcnc-type1",
        "--out",
        out.to_str().expect("path"),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in ["comp-x.txt", "comp-y.txt", "comp-z.txt", "compensation.ini"] {
        assert!(out.join(f).is_file(), "{f}");
    }
    // Beside the tables and in their description: the results they came from, by SHA-256.
    let sha = geocal::compensate::source::sha256_hex(&std::fs::read(&results).expect("results"));
    let source =
        geocal::compensate::source::Source::load(&out.join("geocal-source.json")).expect("sidecar");
    assert_eq!(
        (source.results_sha256.as_str(), source.session_id.as_str()),
        (sha.as_str(), "synthetic")
    );
    assert_eq!(
        source.results,
        std::fs::canonicalize(&results).expect("path")
    );
    let ini = std::fs::read_to_string(out.join("compensation.ini")).expect("ini");
    assert!(
        ini.contains(&format!("# source results SHA-256: {sha}")),
        "{ini}"
    );
    let o = geocal(&["--format", "csv"]);
    assert!(o.status.success() && String::from_utf8_lossy(&o.stdout).contains("EXX,x,"));
    for (args, expect) in [
        (
            &["--format", "fanuc"][..],
            "linuxcnc-type0, linuxcnc-type1, sinumerik",
        ),
        (
            &["--format", "sinumerik", "--step", "1e-4"][..],
            "more than the controller's 200",
        ),
        (&["--format", "csv", "--axes", "w"][..], "--axes"),
    ] {
        let o = geocal(args);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && stderr.contains(expect),
            "{args:?}: {stderr}"
        );
    }
}
