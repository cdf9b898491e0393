//! Laser probe installation on a 5-axis CMM: improved GA vs LM on the same simulated readings,
//! and the sphere radius measured before and after calibration (Fei et al. 2011, table 3).
//!
//! Run: `cargo run --release --example probe_install_eval`

use geocal::model::probe_install::{InstallParams, N_PARAMS, PARAM_NAMES};
use geocal::solve::genetic::GeneticOptions;
use geocal::solve::probe_install::{
    example_nominal, example_truth, measured_radius_m, penalty_objective, published_postures_rad,
    simulate, solve_ga, solve_lm, LmOptions, ProbeInstallProblem, SearchBox, SimulationSpec,
    PUBLISHED_PENALTY,
};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

const RADIUS_M: f64 = 6e-3;
const NOISE_M: f64 = 1e-6;

fn errors(p: &InstallParams, truth: &InstallParams) -> [f64; N_PARAMS] {
    let d = p.to_vector() - truth.to_vector();
    std::array::from_fn(|k| d[k])
}

fn main() -> anyhow::Result<()> {
    let truth = example_truth();
    let nominal = example_nominal();
    let mut rng = ChaCha8Rng::seed_from_u64(2011);
    let spec = SimulationSpec {
        postures_rad: published_postures_rad(),
        points_per_posture: 25,
        cap_half_angle_rad: 60f64.to_radians(),
        reading_half_range_m: 2e-3,
        noise_sigma_m: NOISE_M,
    };
    let problem = ProbeInstallProblem {
        nominal,
        sphere_radius_m: RADIUS_M,
        observations: simulate(&truth, RADIUS_M, &spec, &mut rng),
    };
    // The sphere is then measured from five postures, one of them (−90°, 90°) not used for
    // calibration, and one sphere is fitted through all of the points.
    let q = std::f64::consts::FRAC_PI_2;
    let check_spec = SimulationSpec {
        postures_rad: vec![(0.0, 0.0), (q, 0.0), (-q, 0.0), (q, q), (-q, q)],
        points_per_posture: 40,
        ..spec.clone()
    };
    let check = simulate(&truth, RADIUS_M, &check_spec, &mut rng);

    let lm = solve_lm(&problem, &nominal, &LmOptions::default())?;
    let mut ga_runs = Vec::new();
    for (population, generations) in [(100usize, 2000usize), (200, 5000)] {
        let opts = GeneticOptions {
            population,
            generations,
            seed: 1,
            ..Default::default()
        };
        let ga = solve_ga(&problem, &SearchBox::default(), PUBLISHED_PENALTY, &opts)?;
        ga_runs.push((format!("GA N={population} G={generations}"), ga));
    }

    println!(
        "simulated: {} readings at (A,B) = (0,0), (90,0), (-90,0), (90,90) deg, sigma {} um, sphere r = {} mm",
        problem.observations.len(),
        NOISE_M * 1e6,
        RADIUS_M * 1e3
    );
    println!(
        "objective at nominal: {:.4e}, at truth: {:.4e}",
        penalty_objective(&problem, &nominal, PUBLISHED_PENALTY),
        penalty_objective(&problem, &truth, PUBLISHED_PENALTY)
    );
    println!();
    println!(
        "| solver | objective G (mm^2 units, M=1e4) | h = l^2+m^2+n^2-1 | evaluations / iterations | wall time (s) | r before (mm) | r after (mm) |"
    );
    println!("|---|---|---|---|---|---|---|");
    let r_before = measured_radius_m(&nominal, &check)? * 1e3;
    let r_lm = measured_radius_m(&lm.params, &check)? * 1e3;
    println!(
        "| LM (2 beam angles) | {:.4e} | {:.1e} | {} it | {:.5} | {:.4} | {:.4} |",
        lm.objective, lm.unit_norm_violation, lm.iterations, lm.wall_time_s, r_before, r_lm
    );
    for (name, ga) in &ga_runs {
        let r = measured_radius_m(&ga.params, &check)? * 1e3;
        println!(
            "| {name} | {:.4e} | {:.1e} | {} ev | {:.3} | {:.4} | {:.4} |",
            ga.objective, ga.unit_norm_violation, ga.evaluations, ga.wall_time_s, r_before, r
        );
    }
    println!("| published (Fei et al. 2011, table 3, run 1 / 5) | | | | | 6.0128 | 6.0003 |");
    println!();
    println!("parameter errors against truth (LM sigma beside LM error):");
    println!(
        "| parameter | truth | nominal error | LM error | LM sigma | {} | {} |",
        ga_runs[0].0, ga_runs[1].0
    );
    println!("|---|---|---|---|---|---|---|");
    let en = errors(&nominal, &truth);
    let el = errors(&lm.params, &truth);
    let eg0 = errors(&ga_runs[0].1.params, &truth);
    let eg1 = errors(&ga_runs[1].1.params, &truth);
    let tv = truth.to_vector();
    for k in 0..N_PARAMS {
        println!(
            "| {} | {:.6e} | {:.2e} | {:.2e} | {:.2e} | {:.2e} | {:.2e} |",
            PARAM_NAMES[k], tv[k], en[k], el[k], lm.sigma[k], eg0[k], eg1[k]
        );
    }
    println!();
    println!(
        "LM: chi2/dof = {:.3} ({} dof), residual rms = {:.3} um",
        lm.chi2 / lm.dof as f64,
        lm.dof,
        lm.residual_rms_m * 1e6
    );
    Ok(())
}
