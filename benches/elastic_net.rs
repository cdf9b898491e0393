//! Elastic-net benchmark on a realistic decomposition design (FYXZ, one target offset): timings
//! of single fits and of the CV, and agreement with scikit-learn when Python has it.
//!
//! Run: `cargo bench --bench elastic_net`. Writes X, y and the Rust fits to a temp directory and
//! runs bench/elastic_net_compare.py there (needs `pip install scikit-learn numpy`).

use std::fmt::Write as _;
use std::process::Command;
use std::time::Instant;

use geocal::model::kinematics::Structure;
use geocal::sim::truth::{ErrorSizes, TruthErrors};
use geocal::solve::elastic_net::{cross_validate, ElasticNet, ElasticNetOptions};
use geocal::solve::geometric_errors::{
    elastic_net_design, simulate_observations, DecompositionOptions,
};

const TRAVEL_M: [[f64; 2]; 3] = [[0.0, 0.8], [0.0, 1.0], [-0.5, 0.0]];

fn grid(n: [usize; 3]) -> [Vec<f64>; 3] {
    std::array::from_fn(|a| {
        let [lo, hi] = TRAVEL_M[a];
        (0..n[a])
            .map(|i| lo + (hi - lo) * i as f64 / (n[a] - 1) as f64)
            .collect()
    })
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let structure = Structure::parse("FYXZ")?;
    let truth = TruthErrors::random(7, TRAVEL_M, &ErrorSizes::default());
    let dir = std::env::temp_dir().join("geocal-elastic-net-bench");
    std::fs::create_dir_all(&dir)?;
    let mut cases = Vec::new();

    println!("elastic net on the FYXZ one-offset decomposition design (50 nm noise)");
    println!(
        "{:>10} {:>6} {:>5} {:>10} {:>6} {:>8} {:>7} {:>10}",
        "grid", "rows", "cols", "λ/λmax", "α", "active", "sweeps", "fit ms"
    );
    for n in [[5, 5, 4], [9, 9, 6]] {
        let g = grid(n);
        let pts = simulate_observations(&structure, &truth, &g, &[[0.0, 0.0, -0.12]], 50e-9, 3);
        let design = elastic_net_design(&structure, &g, &pts, &DecompositionOptions::default())?;
        let tag = format!("{}x{}x{}", n[0], n[1], n[2]);
        // Raw columns, no intercept: scikit-learn's ElasticNet(fit_intercept=False) solves the
        // same problem on the same matrix.
        let raw = ElasticNetOptions {
            standardize: false,
            fit_intercept: false,
            tolerance: 1e-13,
            max_sweeps: 2_000_000,
        };
        let net = ElasticNet::new(&design.x, &design.y, None, raw)?;
        let mut fits = Vec::new();
        for alpha in [0.5, 1.0] {
            for ratio in [1e-1, 1e-2, 1e-3] {
                let lambda = net.lambda_max(alpha) * ratio;
                let start = Instant::now();
                let fit = net.fit(lambda, alpha)?;
                let ms = start.elapsed().as_secs_f64() * 1e3;
                println!(
                    "{tag:>10} {:>6} {:>5} {ratio:>10.0e} {alpha:>6} {:>8} {:>7} {ms:>10.2}",
                    design.x.nrows(),
                    design.x.ncols(),
                    fit.n_active(),
                    fit.sweeps,
                );
                let coefs: Vec<String> =
                    fit.coefficients.iter().map(|c| format!("{c:e}")).collect();
                fits.push(format!(
                    "{{\"lambda\": {lambda:e}, \"alpha\": {alpha}, \"seconds\": {:e}, \"converged\": {}, \"coef\": [{}]}}",
                    ms / 1e3,
                    fit.converged,
                    coefs.join(", ")
                ));
            }
        }
        let mut x_csv = String::new();
        for row in design.x.row_iter() {
            let cells: Vec<String> = row.iter().map(|v| format!("{v:e}")).collect();
            writeln!(x_csv, "{}", cells.join(","))?;
        }
        let y_csv: String = design.y.iter().map(|v| format!("{v:e}\n")).collect();
        std::fs::write(dir.join(format!("X_{tag}.csv")), x_csv)?;
        std::fs::write(dir.join(format!("y_{tag}.csv")), y_csv)?;
        cases.push(format!(
            "{{\"name\": \"{tag}\", \"fits\": [{}]}}",
            fits.join(", ")
        ));

        // The decomposition's CV: 4 α × 50 λ × 5 folds on standardised columns.
        let start = Instant::now();
        let cv = cross_validate(
            &design.x,
            &design.y,
            None,
            Some(&design.groups),
            &DecompositionOptions::default().cv,
        )?;
        println!(
            "{tag:>10}: CV over 4 α x 50 λ x 5 folds: {:.3} s, chose λ = {:.3e}, α = {}, cv_mse = {:.3}",
            start.elapsed().as_secs_f64(),
            cv.lambda,
            cv.alpha,
            cv.cv_mse
        );
    }
    std::fs::write(
        dir.join("rust_fits.json"),
        format!("{{\"cases\": [{}]}}", cases.join(", ")),
    )?;
    println!("matrices and Rust fits written to {}", dir.display());

    let has_sklearn = Command::new("python3")
        .args(["-c", "import sklearn, numpy"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if !has_sklearn {
        println!(
            "scikit-learn not found: `pip install scikit-learn numpy`, then rerun, or run \
             python3 bench/elastic_net_compare.py {}",
            dir.display()
        );
        return Ok(());
    }
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/bench/elastic_net_compare.py");
    let status = Command::new("python3").arg(script).arg(&dir).status()?;
    if !status.success() {
        return Err(format!("{script} failed: {status}").into());
    }
    Ok(())
}
