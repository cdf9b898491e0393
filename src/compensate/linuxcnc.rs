//! LinuxCNC joint compensation files (`[JOINT_n] COMP_FILE`, `COMP_FILE_TYPE` 0 and 1): the
//! numbers-only table, its INI fragment, the reader as LinuxCNC reads it, and its application.

use std::path::Path;

use super::{
    common_header, sample, Calibration, CompensateError, Export, ExportOptions, OutputFile,
    TableFormat, AXES,
};

/// LinuxCNC's `EMCMOT_COMP_SIZE` (motion.h): the most entries a joint's table holds.
pub const MAX_ENTRIES: usize = 256;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CompType {
    /// Columns: nominal, actual reached moving +, actual reached moving − (trim = nominal − actual).
    Type0,
    /// Columns: nominal, forward trim, reverse trim.
    Type1,
}

impl CompType {
    pub fn number(self) -> u8 {
        match self {
            CompType::Type0 => 0,
            CompType::Type1 => 1,
        }
    }

    fn format(self) -> TableFormat {
        match self {
            CompType::Type0 => TableFormat::LinuxcncType0,
            CompType::Type1 => TableFormat::LinuxcncType1,
        }
    }
}

/// The file name of axis `axis`'s table.
pub fn file_name(axis: usize) -> String {
    format!("comp-{}.txt", AXES[axis])
}

/// One file per joint plus `compensation.ini`, the fragment that names them and describes them
/// (LinuxCNC's tables cannot hold a comment: any line that is not three numbers ends the
/// table, so a header would leave it empty).
pub fn export(
    calibration: &Calibration,
    comp_type: CompType,
    options: &ExportOptions,
) -> Result<Export, CompensateError> {
    let mut files = Vec::new();
    let mut steps = Vec::new();
    let mut ini = common_header(calibration, comp_type.format())
        .into_iter()
        .map(|l| format!("# {l}"))
        .collect::<Vec<_>>();
    ini.push(
        "# Machine units: mm (LINEAR_UNITS = mm); joint n = axis x, y, z -> 0, 1, 2 (trivkins)."
            .into(),
    );
    ini.push(match comp_type {
        CompType::Type0 => {
            "# COMP_FILE_TYPE 0 columns: nominal, position reached moving +, moving - (mm); \
                            LinuxCNC adds the trim nominal - actual to the commanded position."
                .into()
        }
        CompType::Type1 => "# COMP_FILE_TYPE 1 columns: nominal, forward trim, reverse trim (mm); \
                            the trim is added to the commanded position (trim = -deviation)."
            .into(),
    });
    ini.push("# Deviation = tool-to-workpiece positioning error along the joint (carriage error, sign flipped on the workpiece branch).".into());
    for &axis in &options.axes {
        let curve = calibration.positioning(axis)?;
        let s = sample(&curve, axis, options, MAX_ENTRIES)?;
        if let Some(bad) = s.values_m.iter().find(|v| !v.is_finite()) {
            return Err(CompensateError::Limit(format!(
                "axis {}: value {bad} is not a number LinuxCNC can load",
                AXES[axis]
            )));
        }
        let half_b = 0.5 * calibration.reversal_m[axis];
        let mut text = String::new();
        for (q, d) in s.nominals_m.iter().zip(&s.values_m) {
            let (plus, minus) = (d + half_b, d - half_b);
            let (c1, c2) = match comp_type {
                CompType::Type0 => (q + plus, q + minus),
                CompType::Type1 => (-plus, -minus),
            };
            text.push_str(&format!("{:.6} {:.6} {:.6}\n", q * 1e3, c1 * 1e3, c2 * 1e3));
        }
        let r = &s.report;
        ini.push(String::new());
        ini.push(format!(
            "# axis {}: {} entries, step {:.4} mm, {:.3}..{:.3} mm, zero at the reference point {:.3} mm",
            AXES[axis],
            r.entries,
            r.step_m * 1e3,
            s.nominals_m[0] * 1e3,
            s.nominals_m.last().copied().unwrap_or(0.0) * 1e3,
            s.reference_m * 1e3
        ));
        ini.push(format!(
            "# interpolation error of the step against the fitted curve {:.4} µm (calibration σ {:.4} µm){}",
            r.interpolation_error_m * 1e6,
            r.sigma_m * 1e6,
            if r.warning.is_some() { ": WARNING, coarser than σ" } else { "" }
        ));
        ini.push(format!("[JOINT_{axis}]"));
        ini.push(format!("COMP_FILE = {}", file_name(axis)));
        ini.push(format!("COMP_FILE_TYPE = {}", comp_type.number()));
        files.push(OutputFile {
            name: file_name(axis),
            text,
        });
        steps.push(s.report);
    }
    files.push(OutputFile {
        name: "compensation.ini".into(),
        text: ini.join("\n") + "\n",
    });
    Ok(Export { files, steps })
}

/// One loaded entry: trims as LinuxCNC stores them (32-bit floats), in machine units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Entry {
    pub nominal: f64,
    pub fwd_trim: f32,
    pub rev_trim: f32,
}

/// A joint's table as LinuxCNC holds it after loading.
#[derive(Debug, Clone, PartialEq)]
pub struct CompTable {
    pub entries: Vec<Entry>,
    /// What LinuxCNC would have reported while loading (dropped lines, a full table).
    pub messages: Vec<String>,
    /// Machine units per metre (1000 for mm).
    pub units_per_m: f64,
}

/// `strtod`'s longest prefix of `s` that is a number: (value, bytes used); None if none.
fn strtod_prefix(s: &str) -> Option<(f64, usize)> {
    let b = s.as_bytes();
    let mut i = 0;
    if i < b.len() && (b[i] == b'+' || b[i] == b'-') {
        i += 1;
    }
    let lower = s[i..].to_ascii_lowercase();
    for word in ["infinity", "inf", "nan"] {
        if lower.starts_with(word) {
            let end = i + word.len();
            return s[..end].parse::<f64>().ok().map(|v| (v, end));
        }
    }
    let digits_start = i;
    while i < b.len() && b[i].is_ascii_digit() {
        i += 1;
    }
    let mut digits = i - digits_start;
    if i < b.len() && b[i] == b'.' {
        i += 1;
        let f = i;
        while i < b.len() && b[i].is_ascii_digit() {
            i += 1;
        }
        digits += i - f;
    }
    if digits == 0 {
        return None;
    }
    let mantissa_end = i;
    if i < b.len() && (b[i] == b'e' || b[i] == b'E') {
        let mut j = i + 1;
        if j < b.len() && (b[j] == b'+' || b[j] == b'-') {
            j += 1;
        }
        let e = j;
        while j < b.len() && b[j].is_ascii_digit() {
            j += 1;
        }
        if j > e {
            i = j;
        }
    }
    let end = if i > mantissa_end { i } else { mantissa_end };
    let text = s[..end].trim_end_matches('.');
    let text = if text.is_empty() || text == "+" || text == "-" {
        return None;
    } else {
        text
    };
    text.parse::<f64>().ok().map(|v| (v, end))
}

/// `sscanf(line, "%lf %lf %lf")`: the three numbers, or None (fewer than three matched).
pub fn scan_three(line: &str) -> Option<[f64; 3]> {
    let mut rest = line;
    let mut out = [0.0; 3];
    for slot in &mut out {
        rest = rest.trim_start_matches([' ', '\t', '\n', '\r', '\x0b', '\x0c']);
        let (v, used) = strtod_prefix(rest)?;
        *slot = v;
        rest = &rest[used..];
    }
    Some(out)
}

impl CompTable {
    /// Read a table as LinuxCNC does (`usrmotLoadComp`, then `EMCMOT_SET_JOINT_COMP` per
    /// line): stop at the first line that is not three numbers, drop a line whose nominal does
    /// not increase, drop lines beyond 256 entries. The result may be empty: LinuxCNC loads an
    /// empty table silently, so the caller decides whether that is an error.
    pub fn read_as_linuxcnc(text: &str, comp_type: CompType) -> CompTable {
        let mut entries: Vec<Entry> = Vec::new();
        let mut messages = Vec::new();
        for (n, line) in text.split('\n').enumerate() {
            let Some([nominal, a, b]) = scan_three(line) else {
                break;
            };
            let (fwd, rev) = match comp_type {
                CompType::Type0 => (nominal - a, nominal - b),
                CompType::Type1 => (a, b),
            };
            if entries.len() >= MAX_ENTRIES {
                messages.push(format!(
                    "line {}: table full ({MAX_ENTRIES} entries)",
                    n + 1
                ));
                continue;
            }
            // Anything but "greater" is dropped, so a NaN nominal is dropped too, as the
            // controller's compare does.
            if entries.last().is_some_and(|e| {
                nominal.partial_cmp(&e.nominal) != Some(std::cmp::Ordering::Greater)
            }) {
                messages.push(format!(
                    "line {}: nominal {nominal} does not increase",
                    n + 1
                ));
                continue;
            }
            entries.push(Entry {
                nominal,
                fwd_trim: fwd as f32,
                rev_trim: rev as f32,
            });
        }
        CompTable {
            entries,
            messages,
            units_per_m: 1e3,
        }
    }

    /// Read a table strictly: what LinuxCNC would load, and an error naming the line where it
    /// would silently lose data (a header, a dropped line, an empty table, a non-finite value).
    pub fn parse(
        text: &str,
        comp_type: CompType,
        file: &Path,
    ) -> Result<CompTable, CompensateError> {
        let table = CompTable::read_as_linuxcnc(text, comp_type);
        let line_error = |line: usize, message: String| CompensateError::Line {
            file: file.to_path_buf(),
            line,
            message,
        };
        if let Some(m) = table.messages.first() {
            return Err(CompensateError::Input {
                file: file.to_path_buf(),
                message: format!("LinuxCNC would drop a line: {m}"),
            });
        }
        let read = table.entries.len();
        let rest: Vec<(usize, &str)> = text
            .split('\n')
            .enumerate()
            .skip(read)
            .filter(|(_, l)| !l.trim().is_empty())
            .collect();
        if let Some((n, _)) = rest.first() {
            return Err(line_error(
                n + 1,
                format!(
                    "not three numbers: LinuxCNC stops reading here{}",
                    if read == 0 {
                        " and loads an empty table"
                    } else {
                        ""
                    }
                ),
            ));
        }
        if read == 0 {
            return Err(CompensateError::Input {
                file: file.to_path_buf(),
                message: "no entries: LinuxCNC would load an empty table".into(),
            });
        }
        for (n, e) in table.entries.iter().enumerate() {
            if !(e.nominal.is_finite() && e.fwd_trim.is_finite() && e.rev_trim.is_finite()) {
                return Err(line_error(n + 1, "expected finite numbers".into()));
            }
        }
        Ok(table)
    }

    /// The trims at `q` in machine units: linear interpolation, constant beyond the ends.
    fn trims_at(&self, q: f64) -> (f64, f64) {
        let e = &self.entries;
        let Some(first) = e.first() else {
            return (0.0, 0.0);
        };
        let last = e[e.len() - 1];
        if q <= first.nominal {
            return (first.fwd_trim as f64, first.rev_trim as f64);
        }
        if q >= last.nominal {
            return (last.fwd_trim as f64, last.rev_trim as f64);
        }
        let i = e.partition_point(|x| x.nominal <= q).clamp(1, e.len() - 1);
        let (a, b) = (e[i - 1], e[i]);
        let f = (q - a.nominal) / (b.nominal - a.nominal);
        (
            a.fwd_trim as f64 + f * (b.fwd_trim as f64 - a.fwd_trim as f64),
            a.rev_trim as f64 + f * (b.rev_trim as f64 - a.rev_trim as f64),
        )
    }

    /// The trim LinuxCNC adds to the commanded position `q_m` (metres): the forward column
    /// after a move in +, the reverse column after a move in −; none before the joint moved.
    pub fn trim_m(&self, q_m: f64, approach: f64) -> f64 {
        let (fwd, rev) = self.trims_at(q_m * self.units_per_m);
        let trim = if approach > 0.0 {
            fwd
        } else if approach < 0.0 {
            rev
        } else {
            0.0
        };
        trim / self.units_per_m
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scan_reads_like_sscanf() {
        assert_eq!(scan_three("1 2 3"), Some([1.0, 2.0, 3.0]));
        assert_eq!(
            scan_three("  1.5\t-2e-3 +3. trailing"),
            Some([1.5, -2e-3, 3.0])
        );
        assert_eq!(scan_three("1 2"), None);
        assert_eq!(scan_three("# nominal fwd rev"), None);
        assert_eq!(scan_three("1,5 2 3"), None);
        assert_eq!(scan_three(""), None);
        assert_eq!(
            scan_three("1e 2 3"),
            None,
            "`1e` leaves `e` unread, then `e 2` fails"
        );
        assert_eq!(scan_three(".5 .25 -.125"), Some([0.5, 0.25, -0.125]));
    }

    #[test]
    fn a_header_line_gives_an_empty_table_and_a_strict_error() {
        let text = "# x compensation\n0 0 0\n100 0.001 0.002\n";
        assert!(CompTable::read_as_linuxcnc(text, CompType::Type1)
            .entries
            .is_empty());
        let e = CompTable::parse(text, CompType::Type1, Path::new("x.txt")).unwrap_err();
        assert!(e.to_string().contains("x.txt: line 1"), "{e}");
        assert!(e.to_string().contains("empty table"), "{e}");
    }

    #[test]
    fn non_increasing_lines_are_dropped_and_the_table_applies_by_direction() {
        let t = CompTable::read_as_linuxcnc("0 0 0\n0 5 5\n100 0.01 -0.01\n", CompType::Type1);
        assert_eq!(t.entries.len(), 2);
        assert_eq!(t.messages.len(), 1);
        // Halfway: half the trims; beyond the ends: constant; metres in and out.
        assert!((t.trim_m(0.05, 1.0) - 0.005e-3).abs() < 1e-12);
        assert!((t.trim_m(0.05, -1.0) + 0.005e-3).abs() < 1e-12);
        assert!((t.trim_m(0.5, 1.0) - 0.01e-3).abs() < 1e-12);
        assert!((t.trim_m(-1.0, -1.0)).abs() < 1e-15);
        // Type 0 stores nominal − actual.
        let t0 = CompTable::read_as_linuxcnc("0 0 0\n100 100.01 99.98\n", CompType::Type0);
        assert!((t0.trim_m(0.1, 1.0) + 0.01e-3).abs() < 1e-9);
        assert!((t0.trim_m(0.1, -1.0) - 0.02e-3).abs() < 1e-9);
    }

    #[test]
    fn entries_beyond_256_are_dropped() {
        let text: String = (0..300).map(|i| format!("{i} 0 0\n")).collect();
        let t = CompTable::read_as_linuxcnc(&text, CompType::Type1);
        assert_eq!(t.entries.len(), MAX_ENTRIES);
        assert!(CompTable::parse(&text, CompType::Type1, Path::new("x")).is_err());
    }
}
