//! A sixth plan kind (tests/ball_bar/, written against the `Kind` trait alone) joins the
//! registry with one line and is then checked, run, solved and reported through it as the
//! five built-in kinds are: the commands' dispatch needs nothing else of a kind.

use crate::ball_bar;

use geocal::kinds::{Registry, RunFlags};
use geocal::run::RunOptions;
use geocal::session::reader::read_session;

const CONFIG: &str = "kind = \"ball_bar\"

[ball_bar]
nominal_radius_m = 0.15
noise_m = 2.0e-7
readings = 400
true_deviation_m = 1.2e-6
seed = 5
";

#[test]
fn a_sixth_kind_runs_through_the_registry_with_one_line() {
    let kinds = Registry::standard().with(&ball_bar::BallBar);
    let dir = tempfile::tempdir().expect("temp dir");
    let config = dir.path().join("ball-bar.toml");
    std::fs::write(&config, CONFIG).expect("config");

    let kind = kinds.of_config(&config).expect("the kind of the config");
    assert_eq!(kind.name(), ball_bar::KIND);
    assert!(
        kinds.names().ends_with("hexapod, ball_bar"),
        "{}",
        kinds.names()
    );
    // The standard registry does not know it, and says which kinds it knows.
    let unknown = Registry::standard()
        .of_config(&config)
        .err()
        .expect("unknown kind");
    assert!(
        unknown.to_string().contains("known: multilateration"),
        "{unknown}"
    );

    let check = kind.check(&config).expect("plan check");
    let predicted = check.json["deviation_sigma_m"]
        .as_f64()
        .expect("predicted σ");
    assert!((predicted - 2.0e-7 / 20.0).abs() < 1e-15, "{predicted}");

    let options = RunOptions {
        out_dir: dir.path().join("run"),
        truth: None,
        progress: false,
        settings: Default::default(),
        control: Default::default(),
    };
    let out = kind
        .run(&config, &options, &RunFlags::default())
        .expect("run");
    let r = out
        .results
        .get::<ball_bar::BallBarResults>()
        .expect("ball bar results");
    let z = (r.deviation_m - 1.2e-6) / r.deviation_sigma_m;
    println!(
        "deviation {:.4e} m, σ {:.2e} m, z {z:.2}; {}",
        r.deviation_m, r.deviation_sigma_m, out.recorded
    );
    assert!(z.abs() < 4.0, "error {z:.2} σ");
    assert_eq!(r.deviation_sigma_m, predicted);

    // A recorded session of the kind is solved through the registry from its header.
    let session = read_session(&out.session_path).expect("session");
    let again = kinds
        .solve_session(&session, &Default::default())
        .expect("solve through the registry");
    assert_eq!(again.to_json_pretty(), out.results.to_json_pretty());
    let written = std::fs::read_to_string(&out.results_path).expect("results.json");
    assert_eq!(written, out.results.to_json_pretty());
    assert!(again.report().starts_with("ball bar: radius deviation"));
    assert!(again.multilateration().is_none());
    // Commands it does not implement say so in the kind's name.
    let resume = kind
        .resume(dir.path(), None, &options)
        .err()
        .expect("no resume");
    assert!(resume.to_string().contains("ball_bar"), "{resume}");
}
