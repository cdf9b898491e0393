//! The NC program of a passive run (`geocal export-nc`): the plan's moves, dwells and operator
//! stops in the sequencer's exact order, as blocks and as ISO G-code (millimetres only here).

pub use crate::config::passive::PassiveConfig;
use crate::config::Config;
use crate::plan::{Plan, PlanTarget};

/// One block of the program.
#[derive(Debug, Clone, PartialEq)]
pub enum NcBlock {
    /// M0: the control waits for the operator (cycle start).
    Stop { message: String },
    /// G1 to absolute axis positions at a feed; `label` names the plan point.
    Move {
        axes_m: [f64; 3],
        feed_m_s: f64,
        label: String,
    },
    /// G4: dwell, seconds.
    Dwell { s: f64 },
}

/// The dwell the program holds at a point: long enough for the sequencer to see the stop
/// (stillstand window), dwell `plan.dwell_s`, plus the margin; at point 0 one more window,
/// since the tracer is homed there and must settle again.
pub fn dwell_s(plan: &Plan, point: usize, passive: &PassiveConfig) -> f64 {
    let homing = if point == 0 {
        plan.stillstand_window_s
    } else {
        0.0
    };
    plan.stillstand_window_s + plan.dwell_s + passive.dwell_margin_s + homing
}

/// The program's blocks, in the sequencer's order: per station an M0 to place the tracer,
/// an M0 whenever another reflector is to be mounted, then every pass's points with a dwell.
pub fn program(config: &Config, plan: &Plan) -> Vec<NcBlock> {
    let passive = config.devices.machine.passive.clone().unwrap_or_default();
    let feed_m_s = config.devices.machine.feed_m_s;
    let mut blocks = Vec::new();
    let mut mounted: Option<&PlanTarget> = None;
    for station in &plan.stations {
        let near = station.hint_m.map_or(String::new(), |h| {
            format!(" near X{} Y{} Z{} mm", mm(h[0]), mm(h[1]), mm(h[2]))
        });
        blocks.push(NcBlock::Stop {
            message: format!("place the tracer on station {}{near}", station.id),
        });
        for target in &plan.targets {
            if mounted != Some(target) {
                blocks.push(NcBlock::Stop {
                    message: format!("mount reflector {}", target.id),
                });
                mounted = Some(target);
            }
            for (pass, &direction) in plan.passes.iter().enumerate() {
                for point in plan.pass_order(direction) {
                    blocks.push(NcBlock::Move {
                        axes_m: plan.points[point].axes_m,
                        feed_m_s,
                        label: format!("{} {} pass {pass} point {point}", station.id, target.id),
                    });
                    blocks.push(NcBlock::Dwell {
                        s: dwell_s(plan, point, &passive),
                    });
                }
            }
        }
    }
    blocks
}

/// Metres to the program's millimetres, 0.1 µm resolution.
fn mm(m: f64) -> String {
    format!("{:.4}", m * 1000.0)
}

/// ISO G-code (G90 absolute, G21 millimetres, G94 feed per minute; G4 P in seconds).
pub fn to_gcode(blocks: &[NcBlock], title: &str) -> String {
    let mut out = String::from("%\n");
    out.push_str(&format!("({})\n", clean(title)));
    out.push_str(
        "(geocal works in metres and seconds: positions here are millimetres, feeds mm/min,)\n\
         (converted only when writing this program. G4 P is the dwell in seconds.)\n",
    );
    out.push_str("G90 G21 G94\n");
    for block in blocks {
        match block {
            NcBlock::Stop { message } => out.push_str(&format!("M0 ({})\n", clean(message))),
            NcBlock::Move {
                axes_m,
                feed_m_s,
                label,
            } => out.push_str(&format!(
                "({})\nG1 X{} Y{} Z{} F{:.1}\n",
                clean(label),
                mm(axes_m[0]),
                mm(axes_m[1]),
                mm(axes_m[2]),
                feed_m_s * 60_000.0
            )),
            NcBlock::Dwell { s } => out.push_str(&format!("G4 P{s:.3}\n")),
        }
    }
    out.push_str("M30\n%\n");
    out
}

/// Parentheses end a G-code comment: keep them out of the text.
fn clean(text: &str) -> String {
    text.replace(['(', ')'], " ")
}

/// Reads back what `to_gcode` writes (and simple programs like it): moves, dwells, stops;
/// errors name the line.
pub fn parse_gcode(text: &str) -> Result<Vec<NcBlock>, String> {
    let mut blocks = Vec::new();
    let mut axes_m = [0.0; 3];
    let mut feed_m_s = 0.0;
    let mut label = String::new();
    for (n, line) in text.lines().enumerate() {
        let (code, comment) = match line.split_once('(') {
            Some((c, rest)) => (c, rest.trim_end().trim_end_matches(')').trim()),
            None => (line, ""),
        };
        let words: Vec<&str> = code.split_whitespace().collect();
        if words.is_empty() {
            if !comment.is_empty() {
                label = comment.to_string();
            }
            continue;
        }
        let value = |w: &str| -> Result<f64, String> {
            w[1..]
                .parse::<f64>()
                .map_err(|e| format!("line {}: `{w}`: {e}", n + 1))
        };
        match words[0] {
            "G1" | "G01" => {
                for w in &words[1..] {
                    match w.chars().next() {
                        Some('X') => axes_m[0] = value(w)? / 1000.0,
                        Some('Y') => axes_m[1] = value(w)? / 1000.0,
                        Some('Z') => axes_m[2] = value(w)? / 1000.0,
                        Some('F') => feed_m_s = value(w)? / 60_000.0,
                        _ => return Err(format!("line {}: unexpected word `{w}`", n + 1)),
                    }
                }
                blocks.push(NcBlock::Move {
                    axes_m,
                    feed_m_s,
                    label: std::mem::take(&mut label),
                });
            }
            "G4" | "G04" => {
                let p = words
                    .iter()
                    .find(|w| w.starts_with('P'))
                    .ok_or_else(|| format!("line {}: G4 without P", n + 1))?;
                blocks.push(NcBlock::Dwell { s: value(p)? });
            }
            "M0" | "M00" => blocks.push(NcBlock::Stop {
                message: comment.to_string(),
            }),
            "G90" | "M30" | "%" => {}
            other => return Err(format!("line {}: unsupported block `{other}`", n + 1)),
        }
    }
    Ok(blocks)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config() -> Config {
        let text = include_str!("../../config/demo-multilateration.toml")
            .replace("count = 5 }", "count = 3 }")
            .replace("count = 4 }", "count = 2 }")
            .replace(
                "driver = \"sim\"\nfeed_m_s",
                "driver = \"passive\"\nfeed_m_s",
            );
        Config::parse(&text, std::path::Path::new("demo.toml")).unwrap()
    }

    /// Parsed back, the program's moves are the plan's points in the sequencer's order, each
    /// followed by its dwell; an M0 precedes each station.
    #[test]
    fn the_program_reads_back_as_the_plan() {
        let config = config();
        let plan = Plan::from_config(&config);
        let text = to_gcode(&program(&config, &plan), "test");
        assert!(text.contains("G90 G21 G94"));
        let blocks = parse_gcode(&text).unwrap();
        let mut it = blocks.iter();
        let passive = PassiveConfig::default();
        for station in &plan.stations {
            match it.next() {
                Some(NcBlock::Stop { message }) => assert!(message.contains(&station.id)),
                other => panic!("expected M0 for {}, found {other:?}", station.id),
            }
            if station.id == plan.stations[0].id {
                assert!(
                    matches!(it.next(), Some(NcBlock::Stop { message }) if message.contains("t0"))
                );
            }
            for &direction in &plan.passes {
                for point in plan.pass_order(direction) {
                    match it.next() {
                        Some(NcBlock::Move {
                            axes_m, feed_m_s, ..
                        }) => {
                            let want = plan.points[point].axes_m;
                            assert!(axes_m.iter().zip(want).all(|(a, w)| (a - w).abs() < 1e-7));
                            assert!((feed_m_s - config.devices.machine.feed_m_s).abs() < 1e-9);
                        }
                        other => panic!("expected G1 to point {point}, found {other:?}"),
                    }
                    match it.next() {
                        Some(NcBlock::Dwell { s }) => {
                            let want = dwell_s(&plan, point, &passive);
                            assert!((s - want).abs() < 1e-3 && *s > plan.dwell_s);
                        }
                        other => panic!("expected G4 at point {point}, found {other:?}"),
                    }
                }
            }
        }
        assert_eq!(it.next(), None);
    }

    #[test]
    fn passive_settings_are_checked() {
        let text = include_str!("../../config/demo-multilateration.toml").replace(
            "driver = \"sim\"\nfeed_m_s",
            "driver = \"passive\"\nfeed_m_s",
        );
        let bad = format!("{text}\n[devices.machine.passive]\nhint_tolerance_m = -1.0\n");
        let e = Config::parse(&bad, std::path::Path::new("p.toml")).unwrap_err();
        assert!(e.to_string().contains("hint_tolerance_m"), "{e}");
        let rotary = include_str!("../../config/rotary-tracer.toml").replace(
            "driver = \"sim\"\nfeed_m_s",
            "driver = \"passive\"\nfeed_m_s",
        );
        assert!(rotary.contains("\"passive\""));
        let e = Config::parse(&rotary, std::path::Path::new("r.toml")).unwrap_err();
        assert!(e.to_string().contains("rotary"), "{e}");
    }

    #[test]
    fn bad_blocks_name_their_line() {
        let e = parse_gcode("G90\nG1 X1 Q2\n").unwrap_err();
        assert!(e.contains("line 2") && e.contains("Q2"), "{e}");
        let e = parse_gcode("G4\n").unwrap_err();
        assert!(e.contains("line 1"), "{e}");
    }
}
