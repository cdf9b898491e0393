//! Hexapod hinge calibration (shared/references/ref5): plain damped least squares against the
//! two-stage method (LM, then the grid multi-start on the vertical base hinges), from random
//! initial errors on all 36 coordinates, over many seeds and a few scenarios.
//!
//!     cargo run --release --example hexapod_eval [-- SEEDS]

use geocal::model::hexapod::HexapodGeometry;
use geocal::solve::hexapod::simulation::{
    max_error_m, measure, nominal_geometry, perturbed, random_poses,
};
use geocal::solve::hexapod::{
    coordinate_sigmas_m, leg_singular_values, solve_lm, solve_two_stage, LmOptions, TwoStageOptions,
};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

struct Scenario {
    label: &'static str,
    noise_m: f64,
    initial_error_m: f64,
    tilt_deg: f64,
    /// Poses for LM: the patent's exactly determined set (6 + reference) or all 30.
    patent_search: bool,
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> anyhow::Result<()> {
    let seeds: u64 = std::env::args()
        .nth(1)
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(50);
    let sc = |label, noise_m, initial_error_m, tilt_deg, patent_search| Scenario {
        label,
        noise_m,
        initial_error_m,
        tilt_deg,
        patent_search,
    };
    let scenarios = [
        sc("noise 0, ±5 mm, LM on all", 0.0, 5e-3, 10.0, false),
        sc("noise 0, ±5 mm, LM on 6", 0.0, 5e-3, 10.0, true),
        sc("noise 0, ±20 mm, LM on all", 0.0, 20e-3, 10.0, false),
        sc("noise 0, ±20 mm, LM on 6", 0.0, 20e-3, 10.0, true),
        sc("noise 0, ±20 mm, ±3°, LM on 6", 0.0, 20e-3, 3.0, true),
        sc("noise 0, ±100 mm, LM on 6", 0.0, 100e-3, 10.0, true),
        sc("noise 0, ±100 mm, ±3°, LM on all", 0.0, 100e-3, 3.0, false),
        sc("noise 0, ±150 mm, ±3°, LM on 6", 0.0, 150e-3, 3.0, true),
        sc("1 µm, ±5 mm, LM on all", 1e-6, 5e-3, 10.0, false),
        sc("1 µm, ±5 mm, LM on 6", 1e-6, 5e-3, 10.0, true),
        sc("1 µm, ±20 mm, LM on all", 1e-6, 20e-3, 10.0, false),
        sc("1 µm, ±20 mm, LM on 6", 1e-6, 20e-3, 10.0, true),
    ];
    println!("{seeds} seeds, 30 poses (reference + 29), platform tilts ±10° unless stated;");
    println!(
        "LM on all = damped least squares on all 29 pose changes, LM on 6 = the patent's exactly"
    );
    println!(
        "determined search set (6 changes x 6 legs = 36 equations); the objective uses all 29."
    );
    println!("success: noise 0 → every coordinate within 1 µm; noisy → within 5 σ (Cramér–Rao σ at the truth\nfor the LM pose set).");
    println!(
        "{:<30} {:>7} {:>8} {:>12} {:>12} {:>9} {:>9} {:>8} {:>7}",
        "scenario",
        "LM ok",
        "2st ok",
        "LM med err",
        "2st med err",
        "LM err>0",
        "2st err>0",
        "2st f>0",
        "solves"
    );
    for s in &scenarios {
        let (mut ok_lm, mut ok_two, mut lm_worse, mut two_worse, mut two_f_worse) = (0, 0, 0, 0, 0);
        let (mut err_lm, mut err_two) = (Vec::new(), Vec::new());
        let mut solves = 0;
        for seed in 0..seeds {
            let mut rng = ChaCha8Rng::seed_from_u64(500 + seed);
            let truth = perturbed(&mut rng, &nominal_geometry(), 2e-3);
            let poses = random_poses(&mut rng, 30, s.tilt_deg);
            let mut obs = measure(&mut rng, &truth, &poses, s.noise_m);
            if s.patent_search {
                obs.search_poses = Some((1..=6).collect());
            }
            let start: HexapodGeometry = perturbed(&mut rng, &truth, s.initial_error_m);
            let start_err = max_error_m(&start, &truth);
            let lm = solve_lm(&obs, &start, &LmOptions::default())?;
            // The grid starts at the size of the initial uncertainty (at least the default).
            let opts = TwoStageOptions {
                initial_step_m: s
                    .initial_error_m
                    .max(TwoStageOptions::default().initial_step_m),
                ..Default::default()
            };
            let two = solve_two_stage(&obs, &start, &opts)?;
            // One yardstick for both methods: the Cramér–Rao σ at the truth.
            let sigma = coordinate_sigmas_m(&obs, &truth)?;
            let ok = |g: &HexapodGeometry| -> bool {
                if s.noise_m == 0.0 {
                    max_error_m(g, &truth) < 1e-6
                } else {
                    g.to_vec()
                        .iter()
                        .zip(truth.to_vec())
                        .zip(&sigma)
                        .all(|((x, y), s)| (x - y).abs() <= 5.0 * s)
                }
            };
            let (e_lm, e_two) = (
                max_error_m(&lm.geometry, &truth),
                max_error_m(&two.geometry, &truth),
            );
            ok_lm += ok(&lm.geometry) as usize;
            ok_two += ok(&two.geometry) as usize;
            lm_worse += (e_lm > start_err) as usize;
            two_worse += (e_two > start_err) as usize;
            two_f_worse += (two.objective_m2 > two.objective_initial_m2) as usize;
            err_lm.push(e_lm);
            err_two.push(e_two);
            solves += two.leg_solves;
        }
        let n = seeds as f64;
        println!(
            "{:<30} {:>6.0}% {:>7.0}% {:>9.4} mm {:>9.4} mm {:>9} {:>9} {:>8} {:>7.0}",
            s.label,
            100.0 * ok_lm as f64 / n,
            100.0 * ok_two as f64 / n,
            median(&mut err_lm) * 1e3,
            median(&mut err_two) * 1e3,
            lm_worse,
            two_worse,
            two_f_worse,
            solves as f64 / n
        );
    }
    println!(
        "med err: median over seeds of the largest coordinate error. err>0: runs whose largest"
    );
    println!(
        "coordinate error ended above the start's; f>0: runs whose objective rose (must be 0);"
    );
    println!("solves: per-leg LM runs of the two-stage method.");

    // Identifiability and precision at one truth: 30 poses, ±10°, 1 µm.
    let mut rng = ChaCha8Rng::seed_from_u64(500);
    let truth = perturbed(&mut rng, &nominal_geometry(), 2e-3);
    for (label, search) in [("all 29", None), ("6 (patent)", Some((1..=6).collect()))] {
        let poses = random_poses(&mut rng, 30, 10.0);
        let mut obs = measure(&mut rng, &truth, &poses, 1e-6);
        obs.search_poses = search;
        let sv = leg_singular_values(&obs, &truth);
        let cond = sv.iter().map(|s| s[0] / s[5]).fold(0.0, f64::max);
        let sigma = coordinate_sigmas_m(&obs, &truth)?;
        let pick = |platform: bool, z: bool| -> f64 {
            let off = if platform { 18 } else { 0 };
            let v: Vec<f64> = (0..6)
                .flat_map(|leg| {
                    let base = off + 3 * leg;
                    if z {
                        vec![sigma[base + 2]]
                    } else {
                        vec![sigma[base], sigma[base + 1]]
                    }
                })
                .collect();
            v.iter().sum::<f64>() / v.len() as f64 * 1e6
        };
        println!(
            "LM poses {label:<11}: worst leg condition (all 29 poses) {cond:.0}; mean σ at 1 µm: B xy {:.1} µm, B z {:.1} µm, P xy {:.1} µm, P z {:.1} µm",
            pick(false, false),
            pick(false, true),
            pick(true, false),
            pick(true, true)
        );
    }
    Ok(())
}
