//! Plan check of the kinds rotary_sphere, probe_install and hexapod: from the plan and the noise
//! model alone, every parameter's predicted σ (Cramér–Rao) and what the plan cannot identify.
//!
//! Each kind linearises its own model (the Jacobians the solvers use) at the nominal / design
//! values with exact, noise-free readings. Where the plan identifies everything, the σ are the
//! solver's own covariance propagated at that point (the solver run on the noise-free plan);
//! where it does not, the block analysis (`linear`) names the null directions and gives σ only
//! for what stays identifiable.

pub mod linear;

use serde::Serialize;

pub use linear::NullDirection;

/// The prediction for one plan of one of these kinds (`geocal check --json`).
#[derive(Debug, Clone, Serialize)]
pub struct KindPlanCheck {
    pub kind: String,
    /// The plan in one line (counts).
    pub plan: String,
    /// The noise model every σ follows from, in words.
    pub noise_model: String,
    /// Observations the plan makes (the solver's residuals) and unknowns it solves for.
    pub observations: usize,
    pub unknowns: usize,
    pub identifiability: KindIdentifiability,
    /// Predicted σ of every parameter (null: not identifiable on its own).
    pub parameters: Vec<PredictedSigma>,
    /// RMS and largest σ per group of like parameters.
    pub summary: Vec<GroupSummary>,
    /// Kind-specific predictions (harmonic coefficients, validation, ...).
    pub details: serde_json::Value,
    /// Things an engineer should know or fix before measuring.
    pub warnings: Vec<String>,
}

#[derive(Debug, Clone, Serialize)]
pub struct KindIdentifiability {
    /// Rank of the whitened Jacobian summed over the solver's blocks, and the unknowns.
    pub rank: usize,
    pub unknowns: usize,
    /// Directions the plan cannot see (0 for a plan that identifies everything).
    pub deficiency: usize,
    /// Largest condition number over the blocks (columns scaled to unit norm).
    pub condition_number: f64,
    /// Parameters that are not identifiable on their own.
    pub unidentifiable: Vec<String>,
    /// The directions the plan cannot see, as parameter combinations.
    pub null_directions: Vec<NullDirection>,
    /// Freedoms the solver fixes by convention (not a defect of the plan).
    pub conventions: Vec<String>,
}

#[derive(Debug, Clone, Serialize)]
pub struct PredictedSigma {
    pub name: String,
    /// `m`, `rad` or `1` (unit-free, e.g. a beam direction cosine).
    pub unit: &'static str,
    pub sigma: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct GroupSummary {
    pub group: String,
    pub unit: &'static str,
    pub count: usize,
    pub identifiable: usize,
    pub rms_sigma: f64,
    pub max_sigma: f64,
}

/// Group summaries of `parameters` by `group_of(name)`, in first-seen order.
pub(crate) fn summarise(
    parameters: &[PredictedSigma],
    group_of: impl Fn(&str) -> String,
) -> Vec<GroupSummary> {
    let mut out: Vec<(GroupSummary, f64)> = Vec::new();
    for p in parameters {
        let g = group_of(&p.name);
        let i = match out.iter().position(|(s, _)| s.group == g) {
            Some(i) => i,
            None => {
                out.push((
                    GroupSummary {
                        group: g,
                        unit: p.unit,
                        count: 0,
                        identifiable: 0,
                        rms_sigma: 0.0,
                        max_sigma: 0.0,
                    },
                    0.0,
                ));
                out.len() - 1
            }
        };
        let (s, sum2) = &mut out[i];
        s.count += 1;
        if let Some(v) = p.sigma {
            s.identifiable += 1;
            *sum2 += v * v;
            s.max_sigma = s.max_sigma.max(v);
        }
    }
    out.into_iter()
        .map(|(mut s, sum2)| {
            s.rms_sigma = if s.identifiable > 0 {
                (sum2 / s.identifiable as f64).sqrt()
            } else {
                f64::NAN
            };
            s
        })
        .collect()
}

/// Merge block analyses into one identifiability record.
pub(crate) fn merge(
    blocks: &[&linear::BlockAnalysis],
    unknowns: usize,
    names: &[Vec<String>],
    conventions: Vec<String>,
) -> KindIdentifiability {
    let rank = blocks.iter().map(|b| b.rank).sum();
    let mut unidentifiable = Vec::new();
    for (b, n) in blocks.iter().zip(names) {
        for (k, s) in b.sigma.iter().enumerate() {
            if s.is_none() {
                unidentifiable.push(n[k].clone());
            }
        }
    }
    KindIdentifiability {
        rank,
        unknowns,
        deficiency: unknowns.saturating_sub(rank),
        condition_number: blocks
            .iter()
            .map(|b| b.condition_number)
            .fold(0.0, f64::max),
        unidentifiable,
        null_directions: blocks
            .iter()
            .flat_map(|b| b.null_directions.iter().cloned())
            .collect(),
        conventions,
    }
}

/// σ in a readable unit: µm for metres, µrad for radians.
fn show(sigma: Option<f64>, unit: &str) -> String {
    match (sigma, unit) {
        (None, _) => "not identifiable".into(),
        (Some(s), "m") => format!("{:.3} µm", s * 1e6),
        (Some(s), "rad") => format!("{:.3} µrad", s * 1e6),
        (Some(s), _) => format!("{s:.3e}"),
    }
}

/// The text report of a kind plan check.
pub fn text(c: &KindPlanCheck) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(s, "plan check ({}): {}", c.kind, c.plan);
    let _ = writeln!(s, "  noise model: {}", c.noise_model);
    let id = &c.identifiability;
    let _ = writeln!(
        s,
        "  {} observations, {} unknowns; rank {} of {}, condition number {:.3e}",
        c.observations, c.unknowns, id.rank, id.unknowns, id.condition_number
    );
    let _ = writeln!(s, "  predicted standard uncertainties (Cramér–Rao):");
    for g in &c.summary {
        if g.identifiable == 0 {
            let _ = writeln!(s, "    {:28} {} values: not identifiable", g.group, g.count);
        } else {
            let _ = writeln!(
                s,
                "    {:28} rms {:>16}  max {:>16}  ({} of {} identifiable)",
                g.group,
                show(Some(g.rms_sigma), g.unit),
                show(Some(g.max_sigma), g.unit),
                g.identifiable,
                g.count
            );
        }
    }
    if c.parameters.len() <= 40 {
        for p in &c.parameters {
            let _ = writeln!(s, "      {:28} σ {}", p.name, show(p.sigma, p.unit));
        }
    }
    if id.deficiency == 0 {
        let _ = writeln!(s, "  the plan identifies every parameter");
    } else {
        let listed = 16;
        let mut alone = id
            .unidentifiable
            .iter()
            .take(listed)
            .cloned()
            .collect::<Vec<_>>()
            .join(", ");
        if id.unidentifiable.len() > listed {
            alone.push_str(&format!(", ... ({} in all)", id.unidentifiable.len()));
        }
        let _ = writeln!(
            s,
            "  the plan cannot identify {} direction(s); not identifiable alone: {alone}",
            id.deficiency
        );
        let shown = 12;
        for d in id.null_directions.iter().take(shown) {
            let _ = writeln!(s, "    unseen: {}", d.combination);
        }
        if id.null_directions.len() > shown {
            let _ = writeln!(
                s,
                "    ... and {} more (--json lists them all)",
                id.null_directions.len() - shown
            );
        }
    }
    for conv in &id.conventions {
        let _ = writeln!(s, "  convention: {conv}");
    }
    for w in &c.warnings {
        let _ = writeln!(s, "  warning: {w}");
    }
    s
}
