//! A sixth plan kind, written outside geocal against its `Kind` trait alone: a ball bar of
//! nominal radius R read N times while the machine circles. The run simulates the readings
//! (radius deviation + Gaussian noise), records them as a session on `/probe/<id>/reading`,
//! and the solve estimates the radius deviation with σ = noise_m / √N.

use std::path::Path;

use anyhow::Context;
use geocal::kinds::{Kind, KindCheck, KindRunOutput, RunFlags};
use geocal::method::{KindResults, MethodError, Results, SolveSettings};
use geocal::run::RunOptions;
use geocal::session::messages::{
    DeviceInfo, MachineInfo, ProbeSample, SessionHeader, SESSION_FORMAT,
};
use geocal::session::reader::{read_session, Session};
use geocal::session::{Recorder, RecorderOptions};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

pub const KIND: &str = "ball_bar";
const PROBE: &str = "bb0";

/// `kind = "ball_bar"` and its `[ball_bar]` table.
#[derive(Debug, Deserialize)]
struct BallBarFile {
    ball_bar: BallBarConfig,
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct BallBarConfig {
    pub nominal_radius_m: f64,
    pub noise_m: f64,
    pub readings: usize,
    /// The simulated bar's true radius deviation (the truth a test compares with).
    pub true_deviation_m: f64,
    pub seed: u64,
}

impl BallBarConfig {
    fn load(path: &Path) -> anyhow::Result<BallBarConfig> {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let file: BallBarFile =
            toml::from_str(&text).with_context(|| format!("{}: [ball_bar]", path.display()))?;
        let c = file.ball_bar;
        anyhow::ensure!(
            c.readings >= 2 && c.noise_m > 0.0 && c.nominal_radius_m > 0.0,
            "{}: [ball_bar] needs readings >= 2, noise_m > 0 and nominal_radius_m > 0",
            path.display()
        );
        Ok(c)
    }

    fn predicted_sigma_m(&self) -> f64 {
        self.noise_m / (self.readings as f64).sqrt()
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct BallBarResults {
    pub kind: &'static str,
    pub readings: usize,
    pub deviation_m: f64,
    pub deviation_sigma_m: f64,
}

impl KindResults for BallBarResults {
    fn report(&self) -> String {
        format!(
            "ball bar: radius deviation {:.3} µm ± {:.3} µm from {} readings\n",
            self.deviation_m * 1e6,
            self.deviation_sigma_m * 1e6,
            self.readings
        )
    }
}

#[derive(Debug, thiserror::Error)]
pub enum BallBarError {
    #[error("ball_bar: the session has {0} readings of {PROBE}; the solve needs at least 2")]
    TooFewReadings(usize),
    #[error("ball_bar: the session header declares no noise_m for {PROBE}")]
    NoNoise,
}

pub struct BallBar;

impl Kind for BallBar {
    fn name(&self) -> &'static str {
        KIND
    }

    fn check(&self, path: &Path) -> anyhow::Result<KindCheck> {
        let c = BallBarConfig::load(path)?;
        let sigma = c.predicted_sigma_m();
        Ok(KindCheck {
            json: serde_json::json!({ "kind": KIND, "deviation_sigma_m": sigma }),
            text: format!("ball bar: predicted σ of the radius deviation {sigma:.3e} m\n"),
        })
    }

    fn run(
        &self,
        path: &Path,
        options: &RunOptions,
        _flags: &RunFlags,
    ) -> anyhow::Result<KindRunOutput> {
        let c = BallBarConfig::load(path)?;
        std::fs::create_dir_all(&options.out_dir)?;
        let session_path = options.out_dir.join("session.mcap");
        let recorder = Recorder::create(&session_path, RecorderOptions::default())?;
        let handle = recorder.handle();
        let epoch_ns = 1_800_000_000_000_000_000;
        handle.session(&header(&c), epoch_ns);
        let mut rng = rand::rngs::StdRng::seed_from_u64(c.seed);
        let noise = Normal::new(0.0, c.noise_m)?;
        for k in 0..c.readings {
            let t_s = k as f64 * 0.01;
            let sample = ProbeSample {
                seq: k as u64 + 1,
                t_s,
                value_m: Some(c.true_deviation_m + noise.sample(&mut rng)),
            };
            handle.probe(PROBE, &sample, epoch_ns + (t_s * 1e9) as u64);
        }
        recorder.finish()?;
        let results = self.solve(&read_session(&session_path)?, &options.settings)?;
        let results_path = options.out_dir.join("results.json");
        std::fs::write(&results_path, results.to_json_pretty())?;
        Ok(KindRunOutput {
            session_path,
            results_path,
            results,
            recorded: format!("{} readings", c.readings),
        })
    }

    fn solve(&self, session: &Session, _: &SolveSettings) -> Result<Results, MethodError> {
        let noise_m = session
            .header
            .devices
            .iter()
            .find(|d| d.id == PROBE)
            .and_then(|d| d.noise_m)
            .ok_or(MethodError::of_kind(BallBarError::NoNoise))?;
        let values: Vec<f64> = session
            .probes
            .get(PROBE)
            .map(|v| v.iter().filter_map(|s| s.msg.value_m).collect())
            .unwrap_or_default();
        if values.len() < 2 {
            return Err(MethodError::of_kind(BallBarError::TooFewReadings(
                values.len(),
            )));
        }
        let n = values.len();
        Ok(Results::new(BallBarResults {
            kind: KIND,
            readings: n,
            deviation_m: values.iter().sum::<f64>() / n as f64,
            deviation_sigma_m: noise_m / (n as f64).sqrt(),
        }))
    }
}

fn header(c: &BallBarConfig) -> SessionHeader {
    SessionHeader {
        format: SESSION_FORMAT.to_string(),
        session_id: format!("ball-bar-{}", c.seed),
        started_at: "2026-11-25T00:00:00Z".into(),
        kind: KIND.into(),
        machine: MachineInfo {
            name: "toy".into(),
            structure: "FXYZ".into(),
            axes: vec!["x".into(), "y".into(), "z".into()],
            travel_m: Default::default(),
            targets: Vec::new(),
        },
        devices: vec![DeviceInfo {
            id: PROBE.into(),
            kind: "probe".into(),
            driver: "sim".into(),
            noise_m: Some(c.noise_m),
            noise_ppm: None,
            dead_path_m: None,
            wavelength_m: None,
            compensated: None,
            extra: Default::default(),
        }],
        plan: serde_json::to_value(c).unwrap_or_default(),
    }
}
