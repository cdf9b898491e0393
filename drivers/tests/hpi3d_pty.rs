//! The real HPI-3D driver against the emulator over a pseudo-terminal: streaming, homing,
//! meteo, and every injected fault. Streams run at 500 Hz so each test takes well under a second.

use std::time::Duration;

use geocal_drivers::hpi3d::{
    EmulatorConfig, FaultConfig, FnSource, Hpi3dConfig, Hpi3dEmulator, Hpi3dTracer,
    MeteoSensorReading, SourceReading, TracerSource, Window,
};
use geocal_drivers::{DeviceError, Environment, Tracer, TracerReading};

const RATE_HZ: f64 = 500.0;

/// 1 m away, moving out at 0.5 m/s for 0.2 s, then standing still at 1.1 m.
fn ramp_source() -> Box<dyn TracerSource> {
    Box::new(FnSource {
        sample: |t_s: f64| SourceReading {
            length_m: 1.0 + 0.5 * t_s.min(0.2),
            beam_ok: true,
            signal: 0.8,
        },
        meteo: vec![
            MeteoSensorReading {
                sensor: 0,
                temperature_k: 293.27,
                humidity_pct: 45.0,
                pressure_pa: 101_320.0,
            },
            MeteoSensorReading {
                sensor: 1,
                temperature_k: 293.65,
                humidity_pct: 0.0,
                pressure_pa: 0.0,
            },
        ],
    })
}

fn emulator_config(faults: FaultConfig) -> EmulatorConfig {
    EmulatorConfig {
        rate_hz: RATE_HZ,
        meteo_period_s: 0.05,
        faults,
    }
}

fn driver_config() -> Hpi3dConfig {
    Hpi3dConfig {
        ack_timeout_s: 0.05,
        retries: 3,
        stream_timeout_s: 0.15,
        flag_clear_interval_s: 0.02,
        stream_rate_hz: RATE_HZ,
        ..Hpi3dConfig::default()
    }
}

async fn connect(faults: FaultConfig, config: Hpi3dConfig) -> (Hpi3dEmulator, Hpi3dTracer) {
    let (emulator, host_end) =
        Hpi3dEmulator::spawn_pty(emulator_config(faults), ramp_source()).unwrap();
    let tracer = Hpi3dTracer::from_io(host_end, config).await.unwrap();
    (emulator, tracer)
}

async fn samples(tracer: &mut Hpi3dTracer, n: usize) -> Vec<TracerReading> {
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        out.push(tracer.next_sample().await.unwrap());
    }
    out
}

/// Read until `pred` holds (at most 5 s of stream), returning the matching sample.
async fn until(
    tracer: &mut Hpi3dTracer,
    mut pred: impl FnMut(&TracerReading) -> bool,
) -> TracerReading {
    for _ in 0..(5.0 * RATE_HZ) as usize {
        let s = tracer.next_sample().await.unwrap();
        if pred(&s) {
            return s;
        }
    }
    panic!("condition never met");
}

#[tokio::test]
async fn streams_with_consecutive_seq() {
    let (emulator, mut tracer) = connect(FaultConfig::default(), driver_config()).await;
    let s = samples(&mut tracer, 200).await;
    for w in s.windows(2) {
        assert_eq!(w[1].seq, w[0].seq + 1);
        assert!(w[1].t_s >= w[0].t_s);
        // Ramp or stillstand: never moves backwards, never faster than 0.5 m/s.
        assert!(w[1].length_m >= w[0].length_m - 1e-9);
    }
    assert!(s.iter().all(|r| r.tracking && r.beam_segment == 0));
    assert!(s.iter().all(|r| (r.signal - 204.0 / 255.0).abs() < 1e-12));
    // Not homed yet: the counter reads the source length.
    let last = s.last().unwrap();
    assert!(last.length_m > 1.0 && last.length_m <= 1.1 + 1e-9);
    let c = tracer.counters();
    assert!(c.distance_frames >= 200);
    assert_eq!(c.frames_corrupted, 0);
    assert_eq!(c.bytes_skipped, 0);
    assert_eq!(c.retries, 0);
    assert_eq!(emulator.stats().acks_sent, 4);
}

/// The emulator's own clock as the length: each frame reads the time it was measured at.
fn tick_time_source() -> Box<dyn TracerSource> {
    Box::new(FnSource {
        sample: |t_s: f64| SourceReading {
            length_m: t_s,
            beam_ok: true,
            signal: 0.8,
        },
        meteo: vec![],
    })
}

/// The emulator on a thread and runtime of its own, so that stalling the test's runtime
/// stalls the driver alone, as a loaded host does; its pty path. It stops when the returned
/// sender is dropped.
fn emulator_on_its_own_thread() -> (String, tokio::sync::oneshot::Sender<()>) {
    let (path_tx, path_rx) = std::sync::mpsc::channel();
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    std::thread::spawn(move || {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        runtime.block_on(async move {
            let (emulator, _host_end) = Hpi3dEmulator::spawn_pty(
                emulator_config(FaultConfig::default()),
                tick_time_source(),
            )
            .unwrap();
            let path = emulator.slave_path().unwrap().display().to_string();
            path_tx.send(path).unwrap();
            let _ = stop_rx.await;
        });
    });
    (path_rx.recv().unwrap(), stop_tx)
}

/// Frames read in a burst after the driver stalled are timed at the ticks they were
/// measured at, not at their reception.
#[tokio::test]
async fn sample_times_follow_the_device_ticks_through_a_burst() {
    let (path, _stop) = emulator_on_its_own_thread();
    // Generous time-outs: a loaded machine may stall this test for longer than the stall.
    let config = Hpi3dConfig {
        port: path,
        ack_timeout_s: 1.0,
        stream_timeout_s: 5.0,
        ..driver_config()
    };
    let mut tracer = Hpi3dTracer::open(config).await.unwrap();
    let mut s = samples(&mut tracer, RATE_HZ as usize).await;
    let before_stall = s.last().unwrap().length_m;
    std::thread::sleep(Duration::from_millis(150));
    s.extend(samples(&mut tracer, RATE_HZ as usize).await);

    // t_s and the emulator's clock differ by a constant (when each started, and the
    // least delay of the line) wherever the times follow the ticks.
    let offset = |r: &TracerReading| r.t_s - r.length_m;
    let warmed_up = &s[(0.2 * RATE_HZ) as usize..];
    let mut sorted: Vec<f64> = warmed_up.iter().map(offset).collect();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    let on_tick = |r: &TracerReading| (offset(r) - median).abs() < 0.005;
    let near = warmed_up.iter().filter(|r| on_tick(r)).count();
    assert!(
        near * 100 >= warmed_up.len() * 95,
        "{near} of {} samples within 5 ms of their tick",
        warmed_up.len()
    );
    // The frames measured during the stall (read together up to 150 ms later); the
    // emulator measures when its task runs, so its own delays add to the tolerance.
    let stalled: Vec<&TracerReading> = s
        .iter()
        .filter(|r| r.length_m > before_stall + 0.01 && r.length_m < before_stall + 0.14)
        .collect();
    assert!(stalled.len() >= 50, "{} frames in the stall", stalled.len());
    let near = stalled.iter().filter(|r| on_tick(r)).count();
    assert!(
        near * 10 >= stalled.len() * 9,
        "{near} of {} frames of the burst within 5 ms of their tick",
        stalled.len()
    );
    for w in s.windows(2) {
        assert!(w[1].t_s >= w[0].t_s, "{w:?}");
    }
}

#[tokio::test]
async fn opens_the_pty_by_path() {
    let (emulator, _host_end) =
        Hpi3dEmulator::spawn_pty(emulator_config(FaultConfig::default()), ramp_source()).unwrap();
    let path = emulator.slave_path().unwrap().to_str().unwrap().to_string();
    let config = Hpi3dConfig {
        port: path,
        ..driver_config()
    };
    let mut tracer = Hpi3dTracer::open(config).await.unwrap();
    let s = samples(&mut tracer, 20).await;
    assert_eq!(s[19].seq, s[0].seq + 19);
}

#[tokio::test]
async fn home_is_acknowledged_and_zeroes_the_length() {
    let (emulator, mut tracer) = connect(FaultConfig::default(), driver_config()).await;
    // Wait for the stillstand at 1.1 m.
    until(&mut tracer, |s| s.t_s > 0.25).await;
    tracer.home().await.unwrap();
    assert_eq!(emulator.stats().homings, 1);
    // Samples queued before the ack still read 1.1 m; the first zero marks the homing.
    until(&mut tracer, |s| s.length_m.abs() < 1e-9).await;
    for s in samples(&mut tracer, 50).await {
        assert!(s.length_m.abs() < 1e-9, "{s:?}");
        assert!(s.tracking);
        // A homing without a beam break does not start a new segment.
        assert_eq!(s.beam_segment, 0);
    }
}

#[tokio::test]
async fn meteo_in_kelvin_and_pascal() {
    let (_emulator, tracer) = connect(FaultConfig::default(), driver_config()).await;
    let mut env = tracer.environment();
    tokio::time::sleep(Duration::from_millis(200)).await;
    let readings = env.poll().await.unwrap();
    assert!(readings.len() >= 2, "{readings:?}");
    for r in &readings {
        assert!((r.air_temp_k - 293.27).abs() < 1e-9);
        assert!((r.pressure_pa - 101_320.0).abs() < 1e-9);
        assert!((r.humidity_pct - 45.0).abs() < 1e-12);
        assert_eq!(r.material_temp_k.len(), 1);
        assert!((r.material_temp_k[0] - 293.65).abs() < 1e-9);
    }
    assert!(readings.windows(2).all(|w| w[1].t_s >= w[0].t_s));
    // Drained: nothing new until the next period.
    assert!(env.poll().await.unwrap().len() <= 1);
}

#[tokio::test]
async fn meteo_off_sends_none() {
    let config = Hpi3dConfig {
        meteo: false,
        ..driver_config()
    };
    let (_emulator, tracer) = connect(FaultConfig::default(), config).await;
    let mut env = tracer.environment();
    tokio::time::sleep(Duration::from_millis(150)).await;
    assert!(env.poll().await.unwrap().is_empty());
}

#[tokio::test]
async fn dropped_corrupted_and_garbage_are_counted_and_resynchronised() {
    let faults = FaultConfig {
        seed: 7,
        drop_fraction: 0.05,
        corrupt_fraction: 0.05,
        garbage_fraction: 0.05,
        ..FaultConfig::default()
    };
    let (emulator, mut tracer) = connect(faults, driver_config()).await;
    let s = samples(&mut tracer, 400).await;
    let e = emulator.stats();
    let c = tracer.counters();
    assert!(e.frames_dropped > 0 && e.frames_corrupted > 0 && e.garbage_bytes > 0);
    assert!(c.frames_corrupted > 0, "{c:?}");
    assert!(c.bytes_skipped > 0);
    // Corrupted frames leave gaps in seq; dropped ones only in t_s.
    let gaps: u64 = s.windows(2).map(|w| w[1].seq - w[0].seq - 1).sum();
    assert!(gaps > 0);
    assert!(s.windows(2).all(|w| w[1].seq > w[0].seq));
    // Whatever got through decoded right: a ramp from 1 m to the stillstand at 1.1 m.
    assert!(s
        .iter()
        .all(|r| r.tracking && r.length_m >= 1.0 - 1e-9 && r.length_m <= 1.1 + 1e-9));
    assert!(s.windows(2).all(|w| w[1].length_m >= w[0].length_m - 1e-9));
}

#[tokio::test]
async fn retries_recover_lost_acks() {
    let faults = FaultConfig {
        seed: 3,
        ack_drop_fraction: 0.5,
        ..FaultConfig::default()
    };
    let config = Hpi3dConfig {
        retries: 10,
        ..driver_config()
    };
    let (emulator, mut tracer) = connect(faults, config).await;
    for _ in 0..3 {
        tracer.home().await.unwrap();
    }
    let e = emulator.stats();
    assert!(e.acks_dropped > 0);
    assert_eq!(tracer.counters().retries, e.acks_dropped);
    assert_eq!(tracer.counters().ack_timeouts, 0);
    tracer.next_sample().await.unwrap();
}

#[tokio::test]
async fn unanswered_commands_time_out_after_retries() {
    let faults = FaultConfig {
        mute_commands: Some(Window {
            from_s: 0.1,
            to_s: 100.0,
        }),
        ..FaultConfig::default()
    };
    let (emulator, mut tracer) = connect(faults, driver_config()).await;
    tokio::time::sleep(Duration::from_millis(150)).await;
    let started = std::time::Instant::now();
    let err = tracer.home().await.unwrap_err();
    assert!(matches!(err, DeviceError::Timeout { .. }), "{err}");
    // Four attempts of 50 ms each.
    assert!(started.elapsed() >= Duration::from_millis(200));
    let c = tracer.counters();
    assert_eq!((c.retries, c.ack_timeouts), (3, 1));
    assert_eq!(emulator.stats().commands_ignored, 4);
    // The stream itself goes on.
    tracer.next_sample().await.unwrap();
}

#[tokio::test]
async fn beam_break_then_new_segment_after_home() {
    let faults = FaultConfig {
        beam_break: Some(Window {
            from_s: 0.3,
            to_s: 0.4,
        }),
        ..FaultConfig::default()
    };
    let (_emulator, mut tracer) = connect(faults, driver_config()).await;
    let broken = until(&mut tracer, |s| !s.tracking).await;
    assert_eq!(broken.beam_segment, 0);
    assert_eq!(broken.signal, 0.0);
    // The latched flag is cleared by the driver, so tracking shows again, same segment.
    let back = until(&mut tracer, |s| s.tracking).await;
    assert!(back.t_s >= 0.35, "{back:?}");
    assert_eq!(back.beam_segment, 0);
    tracer.home().await.unwrap();
    let rehomed = until(&mut tracer, |s| s.beam_segment == 1).await;
    assert!(rehomed.tracking);
    assert!(rehomed.length_m.abs() < 1e-9);
    for s in samples(&mut tracer, 20).await {
        assert_eq!(s.beam_segment, 1);
        assert!(s.tracking);
    }
}

#[tokio::test]
async fn silence_times_out_next_sample() {
    let faults = FaultConfig {
        silence: Some(Window {
            from_s: 0.2,
            to_s: 100.0,
        }),
        ..FaultConfig::default()
    };
    let (_emulator, mut tracer) = connect(faults, driver_config()).await;
    let started = std::time::Instant::now();
    let mut last_t_s = 0.0;
    let err = loop {
        match tracer.next_sample().await {
            Ok(s) => last_t_s = s.t_s,
            Err(e) => break e,
        }
        assert!(started.elapsed() < Duration::from_secs(3));
    };
    match err {
        DeviceError::Timeout { after_s, .. } => assert_eq!(after_s, 0.15),
        e => panic!("{e}"),
    }
    assert!((0.15..0.5).contains(&last_t_s), "{last_t_s}");
}
