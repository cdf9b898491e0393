//! The ASCII probe driver against the probe emulator over a pseudo-terminal: scaled values,
//! another dialect, error replies and injected faults (garbage, no answer).

use std::time::{Duration, Instant};

use geocal_drivers::probe::{
    AsciiProbe, ProbeConfig, ProbeEmulator, ProbeEmulatorConfig, ProbeFaults,
};
use geocal_drivers::{DeviceError, Probe};
use tokio_serial::SerialStream;

fn cfg() -> ProbeConfig {
    ProbeConfig {
        timeout_s: 0.2,
        ..ProbeConfig::default()
    }
}

fn rig(
    emu_cfg: ProbeEmulatorConfig,
    value_m: Option<f64>,
    cfg: ProbeConfig,
) -> (ProbeEmulator, AsciiProbe<SerialStream>) {
    let mut emu = ProbeEmulator::spawn_pty(emu_cfg, Box::new(move |_t: f64| value_m)).expect("pty");
    let slave = emu.take_slave().expect("slave");
    (emu, AsciiProbe::from_stream(slave, cfg).expect("driver"))
}

#[tokio::test]
async fn reads_scaled_values() {
    let (_emu, mut p) = rig(ProbeEmulatorConfig::default(), Some(-1.23456e-4), cfg());
    let a = p.read().await.expect("reading");
    let b = p.read().await.expect("reading");
    // The wire carries 4 decimals of mm: 0.1 µm.
    assert!((a.value_m + 1.23456e-4).abs() <= 0.5e-7, "{}", a.value_m);
    assert!(b.t_s > a.t_s && a.t_s >= 0.0);
    assert_eq!(p.id(), "probe");
}

#[tokio::test]
async fn opens_the_slave_by_path_and_speaks_another_dialect() {
    let emu = ProbeEmulator::spawn_pty(
        ProbeEmulatorConfig {
            command: "MEAS?".into(),
            reply_template: "MEASURE={value} mm".into(),
            value_decimals: 3,
            plus_sign: false,
            terminator: "\r\n".into(),
            ..ProbeEmulatorConfig::default()
        },
        Box::new(|_t: f64| Some(-1.234e-3)),
    )
    .expect("pty");
    let port = emu.slave_path().expect("path").to_string();
    let mut p = AsciiProbe::open(ProbeConfig {
        port,
        command: "MEAS?\n".into(),
        value_pattern: r"^MEASURE=\s*(-?\d+(?:\.\d+)?)\s*mm$".into(),
        error_pattern: None,
        ..cfg()
    })
    .expect("open by path");
    let r = p.read().await.expect("reading");
    assert!((r.value_m + 1.234e-3).abs() < 1e-12, "{}", r.value_m);
}

#[tokio::test]
async fn error_reply_is_rejected() {
    let (_emu, mut p) = rig(ProbeEmulatorConfig::default(), None, cfg());
    let err = p.read().await.unwrap_err();
    assert!(matches!(err, DeviceError::Rejected { .. }), "{err}");
    assert!(err.to_string().contains("`ER,M0,01` (code 01)"), "{err}");
}

#[tokio::test]
async fn garbage_is_a_protocol_error_and_the_next_read_works() {
    let (_emu, mut p) = rig(
        ProbeEmulatorConfig {
            faults: ProbeFaults {
                garbage_at_requests: vec![2],
                ..ProbeFaults::default()
            },
            ..ProbeEmulatorConfig::default()
        },
        Some(5e-4),
        cfg(),
    );
    p.read().await.expect("first");
    let err = p.read().await.unwrap_err();
    assert!(matches!(err, DeviceError::Protocol { .. }), "{err}");
    assert!(err.to_string().contains("unrecognised reply \"#"), "{err}");
    let r = p.read().await.expect("third");
    assert!((r.value_m - 5e-4).abs() < 1e-12);
}

#[tokio::test]
async fn no_answer_times_out_and_the_next_read_works() {
    let (emu, mut p) = rig(
        ProbeEmulatorConfig {
            faults: ProbeFaults {
                no_answer_at_requests: vec![1],
                ..ProbeFaults::default()
            },
            ..ProbeEmulatorConfig::default()
        },
        Some(0.0),
        cfg(),
    );
    let t0 = Instant::now();
    let err = p.read().await.unwrap_err();
    assert!(t0.elapsed() >= Duration::from_millis(190));
    assert!(matches!(err, DeviceError::Timeout { .. }), "{err}");
    assert!(err.to_string().contains("reply to `M0`"), "{err}");
    p.read().await.expect("second");
    let n = emu
        .stats()
        .requests
        .load(std::sync::atomic::Ordering::Relaxed);
    assert_eq!(n, 2);
}

#[tokio::test]
async fn seeded_faults_are_reproducible() {
    async fn outcomes(seed: u64) -> Vec<bool> {
        let (_emu, mut p) = rig(
            ProbeEmulatorConfig {
                faults: ProbeFaults {
                    seed,
                    garbage_probability: 0.3,
                    ..ProbeFaults::default()
                },
                ..ProbeEmulatorConfig::default()
            },
            Some(1e-4),
            cfg(),
        );
        let mut v = Vec::new();
        for _ in 0..20 {
            v.push(p.read().await.is_ok());
        }
        v
    }
    let a = outcomes(7).await;
    assert_eq!(a, outcomes(7).await);
    assert!(a.iter().any(|ok| !ok) && a.iter().any(|ok| *ok));
}
