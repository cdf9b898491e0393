//! SINUMERIK interpolatory compensation as NC program fragments: the measuring-system error
//! tables (`$AA_ENC_COMP`, one per axis) and the sag/angularity cross tables (`$AN_CEC`), the
//! reader of their assignments, and how the control applies an encoder table.

use std::collections::BTreeMap;
use std::path::Path;

use super::{
    common_header, input_error, sample, Calibration, CompensateError, Export, ExportOptions,
    OutputFile, TableFormat, AXES,
};

#[derive(Debug, Clone)]
pub struct SinumerikOptions {
    /// Machine axis names of x, y, z.
    pub axis_names: [String; 3],
    /// `MD38000 $MM_ENC_COMP_MAX_POINTS` (and the cross tables' `MD18342`): points per table.
    pub max_points: usize,
    /// Largest compensation value the tables may hold, metres (`MD32720 $MA_CEC_MAX_SUM`,
    /// default 1 mm).
    pub max_value_m: f64,
}

impl Default for SinumerikOptions {
    fn default() -> Self {
        SinumerikOptions {
            axis_names: ["X1", "Y1", "Z1"].map(String::from),
            max_points: 200,
            max_value_m: 1e-3,
        }
    }
}

pub const EEC_FILE: &str = "eec.ini";
pub const CEC_FILE: &str = "cec.ini";

fn check_values(values_m: &[f64], what: &str, o: &SinumerikOptions) -> Result<(), CompensateError> {
    if let Some(v) = values_m
        .iter()
        .find(|v| !v.is_finite() || v.abs() > o.max_value_m)
    {
        return Err(CompensateError::Limit(format!(
            "{what}: value {:.4} mm beyond the control's limit of {:.4} mm (MD32720 CEC_MAX_SUM; \
             set the limit the machine has)",
            v * 1e3,
            o.max_value_m * 1e3
        )));
    }
    Ok(())
}

/// `eec.ini` (one `$AA_ENC_COMP` table per axis) and `cec.ini` (cross tables for every
/// identifiable straightness, with the squareness between the pair).
pub fn export(
    calibration: &Calibration,
    options: &ExportOptions,
    o: &SinumerikOptions,
) -> Result<Export, CompensateError> {
    let header: Vec<String> = common_header(calibration, TableFormat::Sinumerik)
        .into_iter()
        .map(|l| format!("; {l}"))
        .collect();
    let mut eec = vec!["%_N_AX_EEC_INI".to_string(), "CHANDATA(1)".to_string()];
    eec.extend(header.iter().cloned());
    eec.push(
        "; Linear axes in mm. Value = +deviation (tool to workpiece, carriage error with the sign"
            .into(),
    );
    eec.push("; flipped on the workpiece branch): the control adds it to the actual position value, so a".into());
    eec.push(
        "; positive value moves the axis in -, the opposite sign of a LinuxCNC trim (K3).".into(),
    );
    if calibration.reversal_fitted {
        eec.push(
            "; The reversal is not in these tables: set it as backlash (MD32450 BACKLASH).".into(),
        );
    }
    let mut steps = Vec::new();
    for &axis in &options.axes {
        let name = &o.axis_names[axis];
        let curve = calibration.positioning(axis)?;
        let s = sample(&curve, axis, options, o.max_points)?;
        check_values(&s.values_m, &format!("$AA_ENC_COMP of {name}"), o)?;
        let r = &s.report;
        eec.push(format!(
            "; axis {} = {name}: {} points, step {:.4} mm, value zero at the reference point {:.3} mm; \
             interpolation error {:.4} µm (calibration σ {:.4} µm){}",
            AXES[axis],
            r.entries,
            r.step_m * 1e3,
            s.reference_m * 1e3,
            r.interpolation_error_m * 1e6,
            r.sigma_m * 1e6,
            if r.warning.is_some() { ", WARNING: coarser than σ" } else { "" }
        ));
        for (n, v) in s.values_m.iter().enumerate() {
            eec.push(format!("$AA_ENC_COMP[0,{n},{name}]={:.6}", v * 1e3));
        }
        // STEP, MIN and MAX in full precision: MAX = MIN + (points − 1)·STEP must hold.
        eec.push(format!("$AA_ENC_COMP_STEP[0,{name}]={}", r.step_m * 1e3));
        eec.push(format!(
            "$AA_ENC_COMP_MIN[0,{name}]={}",
            s.nominals_m[0] * 1e3
        ));
        eec.push(format!(
            "$AA_ENC_COMP_MAX[0,{name}]={}",
            s.nominals_m.last().copied().unwrap_or(0.0) * 1e3
        ));
        eec.push(format!("$AA_ENC_COMP_IS_MODULO[0,{name}]=0"));
        steps.push(s.report);
    }
    eec.push("M17".into());

    let mut cec = vec!["%_N_NC_CEC_INI".to_string(), "CHANDATA(1)".to_string()];
    cec.extend(header);
    cec.push("; Sag and angularity: value (mm) of the compensation axis's deviation as the base axis moves".into());
    cec.push("; (straightness, branch-signed, plus the squareness between the pair), same sign as $AA_ENC_COMP.".into());
    let mut table = 0;
    for &base in &options.axes {
        for comp in (0..3).filter(|&c| c != base) {
            let Some(curve) = calibration.cross(base, comp) else {
                cec.push(format!(
                    "; E{}{} not identifiable: no table for {} on {}",
                    AXES[comp].to_uppercase(),
                    AXES[base].to_uppercase(),
                    o.axis_names[comp],
                    o.axis_names[base]
                ));
                continue;
            };
            let s = sample(&curve, base, options, o.max_points)?;
            let what = format!(
                "$AN_CEC[{table}] ({} on {})",
                o.axis_names[comp], o.axis_names[base]
            );
            check_values(&s.values_m, &what, o)?;
            cec.push(format!(
                "; table {table}: {} deviation as {} moves, {} points, step {:.4} mm, interpolation error {:.4} µm",
                o.axis_names[comp],
                o.axis_names[base],
                s.report.entries,
                s.report.step_m * 1e3,
                s.report.interpolation_error_m * 1e6
            ));
            for (n, v) in s.values_m.iter().enumerate() {
                cec.push(format!("$AN_CEC[{table},{n}]={:.6}", v * 1e3));
            }
            cec.push(format!(
                "$AN_CEC_INPUT_AXIS[{table}]=({})",
                o.axis_names[base]
            ));
            cec.push(format!(
                "$AN_CEC_OUTPUT_AXIS[{table}]=({})",
                o.axis_names[comp]
            ));
            cec.push(format!("$AN_CEC_STEP[{table}]={}", s.report.step_m * 1e3));
            cec.push(format!("$AN_CEC_MIN[{table}]={}", s.nominals_m[0] * 1e3));
            cec.push(format!(
                "$AN_CEC_MAX[{table}]={}",
                s.nominals_m.last().copied().unwrap_or(0.0) * 1e3
            ));
            cec.push(format!("$AN_CEC_DIRECTION[{table}]=0"));
            cec.push(format!("$AN_CEC_MULT_BY_TABLE[{table}]=0"));
            cec.push(format!("$AN_CEC_IS_MODULO[{table}]=0"));
            table += 1;
        }
    }
    cec.push("M17".into());
    Ok(Export {
        files: vec![
            OutputFile {
                name: EEC_FILE.into(),
                text: eec.join("\n") + "\n",
            },
            OutputFile {
                name: CEC_FILE.into(),
                text: cec.join("\n") + "\n",
            },
        ],
        steps,
    })
}

/// An equally spaced table as the control holds it (machine units mm).
#[derive(Debug, Clone, PartialEq)]
pub struct EncCompTable {
    pub values_mm: Vec<f64>,
    pub step_mm: f64,
    pub min_mm: f64,
    pub max_mm: f64,
}

impl EncCompTable {
    /// The compensation value at actual position `p_m`: linear interpolation between points,
    /// the first and last values beyond the table (metres).
    pub fn value_m(&self, p_m: f64) -> f64 {
        equally_spaced_value_m(&self.values_mm, self.min_mm, self.step_mm, p_m)
    }

    /// Where the axis's encoder stands when the control has it in position at `q_m`: the
    /// compensated actual value p + c(p) equals the command, so p = q − c(p).
    pub fn servo_position_m(&self, q_m: f64) -> f64 {
        let mut p = q_m;
        // c varies by µm over mm: a contraction by ~1e-3 per step, converged in a few.
        for _ in 0..6 {
            p = q_m - self.value_m(p);
        }
        p
    }
}

/// Linear interpolation in an equally spaced table (mm), the first and last values beyond it
/// (K3: "the compensation value of interpolation point 0 is used for all positions smaller
/// than the initial position", likewise the last beyond the end position); metres.
fn equally_spaced_value_m(values_mm: &[f64], min_mm: f64, step_mm: f64, p_m: f64) -> f64 {
    let n = values_mm.len();
    if n == 0 {
        return 0.0;
    }
    let u = (p_m * 1e3 - min_mm) / step_mm;
    if u.is_nan() || u <= 0.0 {
        return values_mm[0] * 1e-3;
    }
    if u >= (n - 1) as f64 {
        return values_mm[n - 1] * 1e-3;
    }
    let i = u.floor() as usize;
    let f = u - i as f64;
    (values_mm[i] + f * (values_mm[i + 1] - values_mm[i])) * 1e-3
}

/// A cross (sag/angularity) table as read.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CecTable {
    pub values_mm: Vec<f64>,
    pub input_axis: String,
    pub output_axis: String,
    pub step_mm: f64,
    pub min_mm: f64,
    pub max_mm: f64,
    /// `$AN_CEC_DIRECTION`: 0 both directions of the base axis, +1 only while it moves +,
    /// −1 only while it moves −.
    pub direction: i32,
}

impl CecTable {
    /// The value the table gives the compensation axis at the base axis's position setpoint
    /// `base_m` (K3: "the programmed position setpoint is always used"), metres: linear
    /// interpolation, the end values beyond the table.
    pub fn value_m(&self, base_m: f64) -> f64 {
        equally_spaced_value_m(&self.values_mm, self.min_mm, self.step_mm, base_m)
    }

    /// Does the table act after a move of its base axis in direction `approach` (+1, −1, 0
    /// before the base axis moved)? A direction-dependent table acts only in its direction.
    pub fn acts(&self, approach: f64) -> bool {
        match self.direction {
            0 => true,
            d => approach != 0.0 && approach.signum() == f64::from(d.signum()),
        }
    }
}

#[derive(Default)]
struct TableBuilder {
    points: BTreeMap<usize, f64>,
    step: Option<f64>,
    min: Option<f64>,
    max: Option<f64>,
    modulo: Option<f64>,
    input: Option<String>,
    output: Option<String>,
    direction: Option<f64>,
    mult_by_table: Option<f64>,
}

/// The assignments of a compensation program, read as the control reads them.
#[derive(Default)]
pub struct Program {
    enc: BTreeMap<(u32, String), TableBuilder>,
    cec: BTreeMap<u32, TableBuilder>,
}

fn parse_number(s: &str) -> Option<f64> {
    let v: f64 = s.trim().parse().ok()?;
    v.is_finite().then_some(v)
}

impl Program {
    /// Parse the program: `;` comments, `%_N_…` and `CHANDATA(n)` lines, `M17`, and the
    /// `$AA_ENC_COMP…` / `$AN_CEC…` assignments; anything else is an error naming the line.
    pub fn parse(text: &str, file: &Path) -> Result<Program, CompensateError> {
        let mut p = Program::default();
        for (n, raw) in text.lines().enumerate() {
            let err = |message: String| CompensateError::Line {
                file: file.to_path_buf(),
                line: n + 1,
                message,
            };
            let line = raw.split(';').next().unwrap_or("").trim();
            if line.is_empty() || line.starts_with("%_N_") || line == "M17" || line == "M30" {
                continue;
            }
            if line.starts_with("CHANDATA(") && line.ends_with(')') {
                continue;
            }
            let Some((lhs, rhs)) = line.split_once('=') else {
                return Err(err("expected `$NAME[...]=value`".to_string()));
            };
            let lhs = lhs.trim();
            let rhs = rhs.trim();
            let (name, index) = lhs
                .strip_suffix(']')
                .and_then(|l| l.split_once('['))
                .ok_or_else(|| err("expected `$NAME[...]` left of `=`".to_string()))?;
            let idx: Vec<&str> = index.split(',').map(str::trim).collect();
            let uint = |s: &str| {
                s.parse::<usize>()
                    .map_err(|_| err("an index is not a whole number".to_string()))
            };
            let number = || {
                parse_number(rhs).ok_or_else(|| err("the value is not a finite number".to_string()))
            };
            let axis_ref = || {
                rhs.strip_prefix('(')
                    .and_then(|r| r.strip_suffix(')'))
                    .map(|r| r.trim().to_string())
                    .filter(|r| !r.is_empty())
                    .ok_or_else(|| err("expected an axis such as `(X1)` as the value".to_string()))
            };
            let enc_key = |i: &[&str], want: usize| -> Result<(u32, String), CompensateError> {
                if i.len() != want {
                    return Err(err(format!("`{name}`: expected {want} indices")));
                }
                let e = uint(i[0])? as u32;
                Ok((e, i[want - 1].to_string()))
            };
            match name {
                "$AA_ENC_COMP" => {
                    let key = enc_key(&idx, 3)?;
                    let point = uint(idx[1])?;
                    let v = number()?;
                    if p.enc
                        .entry(key)
                        .or_default()
                        .points
                        .insert(point, v)
                        .is_some()
                    {
                        return Err(err(format!("`{name}` with these indices assigned twice")));
                    }
                }
                "$AA_ENC_COMP_STEP"
                | "$AA_ENC_COMP_MIN"
                | "$AA_ENC_COMP_MAX"
                | "$AA_ENC_COMP_IS_MODULO" => {
                    let key = enc_key(&idx, 2)?;
                    let v = number()?;
                    let t = p.enc.entry(key).or_default();
                    match name {
                        "$AA_ENC_COMP_STEP" => t.step = Some(v),
                        "$AA_ENC_COMP_MIN" => t.min = Some(v),
                        "$AA_ENC_COMP_MAX" => t.max = Some(v),
                        _ => t.modulo = Some(v),
                    }
                }
                "$AN_CEC" => {
                    if idx.len() != 2 {
                        return Err(err(format!("`{name}`: expected 2 indices")));
                    }
                    let t = uint(idx[0])? as u32;
                    let point = uint(idx[1])?;
                    let v = number()?;
                    if p.cec
                        .entry(t)
                        .or_default()
                        .points
                        .insert(point, v)
                        .is_some()
                    {
                        return Err(err(format!("`{name}` with these indices assigned twice")));
                    }
                }
                "$AN_CEC_INPUT_AXIS"
                | "$AN_CEC_OUTPUT_AXIS"
                | "$AN_CEC_STEP"
                | "$AN_CEC_MIN"
                | "$AN_CEC_MAX"
                | "$AN_CEC_DIRECTION"
                | "$AN_CEC_MULT_BY_TABLE"
                | "$AN_CEC_IS_MODULO" => {
                    if idx.len() != 1 {
                        return Err(err(format!("`{name}`: expected 1 index")));
                    }
                    let t = p.cec.entry(uint(idx[0])? as u32).or_default();
                    match name {
                        "$AN_CEC_INPUT_AXIS" => t.input = Some(axis_ref()?),
                        "$AN_CEC_OUTPUT_AXIS" => t.output = Some(axis_ref()?),
                        "$AN_CEC_STEP" => t.step = Some(number()?),
                        "$AN_CEC_MIN" => t.min = Some(number()?),
                        "$AN_CEC_MAX" => t.max = Some(number()?),
                        "$AN_CEC_DIRECTION" => t.direction = Some(number()?),
                        "$AN_CEC_IS_MODULO" => t.modulo = Some(number()?),
                        _ => t.mult_by_table = Some(number()?),
                    }
                }
                _ => {
                    return Err(err(
                        "unknown variable: expected `$AA_ENC_COMP…` or `$AN_CEC…`".to_string(),
                    ))
                }
            }
        }
        Ok(p)
    }

    /// The encoder axes with a table, as (encoder, axis).
    pub fn enc_axes(&self) -> Vec<(u32, String)> {
        self.enc.keys().cloned().collect()
    }

    /// The `$AA_ENC_COMP` table of encoder `e` of `axis`, checked as the control would
    /// need it: contiguous points from 0, step > 0, MAX = MIN + (points − 1)·STEP, no modulo.
    pub fn enc_comp(
        &self,
        e: u32,
        axis: &str,
        file: &Path,
    ) -> Result<EncCompTable, CompensateError> {
        let t = self.enc.get(&(e, axis.to_string())).ok_or_else(|| {
            input_error(
                file,
                format!(
                    "no $AA_ENC_COMP table for encoder {e} of axis {axis} (tables: {:?})",
                    self.enc_axes()
                ),
            )
        })?;
        let what = format!("$AA_ENC_COMP[{e},…,{axis}]");
        let (values_mm, step_mm, min_mm, max_mm) = checked(t, &what, file)?;
        if t.modulo.unwrap_or(0.0) != 0.0 {
            return Err(input_error(
                file,
                format!("{what}: modulo tables are for rotary axes"),
            ));
        }
        Ok(EncCompTable {
            values_mm,
            step_mm,
            min_mm,
            max_mm,
        })
    }

    /// Every `$AN_CEC` table, in table order.
    pub fn cec_tables(&self, file: &Path) -> Result<Vec<CecTable>, CompensateError> {
        self.cec
            .iter()
            .map(|(i, t)| {
                let what = format!("$AN_CEC[{i}]");
                let (values_mm, step_mm, min_mm, max_mm) = checked(t, &what, file)?;
                let missing = |k: &str| input_error(file, format!("{what}: no {k}"));
                let bad = |m: String| input_error(file, format!("{what}: {m}"));
                let direction = t.direction.unwrap_or(0.0);
                if ![-1.0, 0.0, 1.0].contains(&direction) {
                    return Err(bad(format!(
                        "$AN_CEC_DIRECTION {direction}: expected 0 (both directions), 1 or -1"
                    )));
                }
                if t.modulo.unwrap_or(0.0) != 0.0 {
                    return Err(bad("modulo tables are for rotary axes".into()));
                }
                if t.mult_by_table.unwrap_or(0.0) != 0.0 {
                    return Err(bad(
                        "$AN_CEC_MULT_BY_TABLE: table multiplication is not simulated".into(),
                    ));
                }
                Ok(CecTable {
                    values_mm,
                    input_axis: t
                        .input
                        .clone()
                        .ok_or_else(|| missing("$AN_CEC_INPUT_AXIS"))?,
                    output_axis: t
                        .output
                        .clone()
                        .ok_or_else(|| missing("$AN_CEC_OUTPUT_AXIS"))?,
                    step_mm,
                    min_mm,
                    max_mm,
                    direction: direction as i32,
                })
            })
            .collect()
    }
}

fn checked(
    t: &TableBuilder,
    what: &str,
    file: &Path,
) -> Result<(Vec<f64>, f64, f64, f64), CompensateError> {
    let bad = |m: String| input_error(file, format!("{what}: {m}"));
    let step = t.step.ok_or_else(|| bad("no STEP".into()))?;
    let min = t.min.ok_or_else(|| bad("no MIN".into()))?;
    let max = t.max.ok_or_else(|| bad("no MAX".into()))?;
    if step <= 0.0 {
        return Err(bad(format!("STEP {step} mm: expected > 0")));
    }
    let n = t.points.len();
    if n < 2 || t.points.keys().enumerate().any(|(i, k)| i != *k) {
        return Err(bad(
            "expected points 0, 1, 2, … without gaps (at least 2)".into()
        ));
    }
    let expect_max = min + (n - 1) as f64 * step;
    if (expect_max - max).abs() > 1e-6 * step.max(1.0) {
        return Err(bad(format!(
            "MAX {max} mm, but MIN + (points − 1)·STEP = {expect_max} mm"
        )));
    }
    Ok((t.points.values().copied().collect(), step, min, max))
}

#[cfg(test)]
mod tests {
    use super::*;

    const PROGRAM: &str = "%_N_AX_EEC_INI\nCHANDATA(1)\n; header\n\
        $AA_ENC_COMP[0,0,X1]=0.0\n$AA_ENC_COMP[0,1,X1]=0.010 ; +10 µm\n$AA_ENC_COMP[0,2,X1]=0.012\n\
        $AA_ENC_COMP_STEP[0,X1]=100.0\n$AA_ENC_COMP_MIN[0,X1]=0.0\n$AA_ENC_COMP_MAX[0,X1]=200.0\n\
        $AA_ENC_COMP_IS_MODULO[0,X1]=0\nM17\n";

    #[test]
    fn reads_the_manual_style_program_and_applies_it() {
        let p = Program::parse(PROGRAM, Path::new("eec.ini")).unwrap();
        let t = p.enc_comp(0, "X1", Path::new("eec.ini")).unwrap();
        assert_eq!(t.values_mm, vec![0.0, 0.010, 0.012]);
        assert!((t.value_m(0.05) - 0.005e-3).abs() < 1e-15);
        assert!((t.value_m(1.0) - 0.012e-3).abs() < 1e-15);
        assert!((t.value_m(-1.0)).abs() < 1e-15);
        // In position at q the encoder reads q − c: a positive value moves the axis in −.
        let p_m = t.servo_position_m(0.1);
        assert!((p_m + t.value_m(p_m) - 0.1).abs() < 1e-15);
        assert!(p_m < 0.1);
    }

    #[test]
    fn bad_programs_name_the_line() {
        for (text, expect) in [
            ("$AA_ENC_COMP[0,0,X1]=1,5\n", "line 1"),
            ("CHANDATA(1)\nG01 X10\n", "line 2"),
            ("$AA_ENC_FOO[0,X1]=1\n", "unknown variable"),
            ("$AA_ENC_COMP[0,0,X1]=1\n$AA_ENC_COMP[0,0,X1]=2\n", "twice"),
        ] {
            let e = Program::parse(text, Path::new("p.ini")).err().expect(text);
            assert!(e.to_string().contains(expect), "{text}: {e}");
        }
        let gap = PROGRAM.replace("$AA_ENC_COMP[0,1,X1]=0.010 ; +10 µm\n", "");
        let p = Program::parse(&gap, Path::new("p.ini")).unwrap();
        assert!(p.enc_comp(0, "X1", Path::new("p.ini")).is_err());
        let wrong_max = PROGRAM.replace("MAX[0,X1]=200.0", "MAX[0,X1]=300.0");
        let p = Program::parse(&wrong_max, Path::new("p.ini")).unwrap();
        let e = p.enc_comp(0, "X1", Path::new("p.ini")).unwrap_err();
        assert!(e.to_string().contains("MAX 300"), "{e}");
    }
}
