//! What a checkpoint after every point costs the recorder: the demo's stream (25 Hz samples,
//! a point every ~3 s of device time, i.e. ~75 samples and 2 events per point) recorded as
//! fast as possible, with and without a checkpoint (chunk close + fsync) at each point_end.
//!
//! cargo run --release --example checkpoint_cost [POINTS]

use std::time::{Duration, Instant};

use geocal::session::messages::{RunEvent, TracerSample};
use geocal::session::reader::read_session;
use geocal::session::recorder::{Recorder, RecorderOptions};

/// Records `points` points; `gap` between points stands for a real run's motion and dwell.
fn record(points: usize, checkpoints: bool, gap: Duration) -> (f64, u64, u64, f64) {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("s.mcap");
    let start = Instant::now();
    let rec = Recorder::create(&path, RecorderOptions::default()).expect("recorder");
    let h = rec.handle();
    let header = serde_json::json!({
        "format": "geocal-session/1", "session_id": "bench", "started_at": "",
        "kind": "multilateration",
        "machine": {"structure": "FYXZ", "axes": ["x", "y", "z"]}
    });
    h.session(&serde_json::from_value(header).expect("header"), 0);
    let mut t_ns = 1;
    let mut seq = 0;
    for point in 0..points {
        for _ in 0..75 {
            t_ns += 40_000_000;
            seq += 1;
            let s = TracerSample {
                seq,
                t_s: t_ns as f64 * 1e-9,
                length_m: 0.5 + seq as f64 * 1e-7,
                signal: 0.9,
                tracking: true,
                beam_segment: 0,
            };
            h.tracer("tracer0", &s, t_ns);
        }
        let end = RunEvent::PointEnd {
            station: "s1".into(),
            point,
            pass: 0,
        };
        h.event(&end, t_ns);
        if checkpoints {
            h.checkpoint();
        }
        std::thread::sleep(gap);
    }
    let stats = rec.finish().expect("finish");
    let write_s = start.elapsed().as_secs_f64() - gap.as_secs_f64() * points as f64;
    let start = Instant::now();
    let s = read_session(&path).expect("read");
    assert_eq!(s.tracers["tracer0"].len(), points * 75);
    (
        write_s,
        stats.bytes,
        stats.flushes,
        start.elapsed().as_secs_f64(),
    )
}

fn main() {
    let points: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(1000);
    println!("points x 75 samples (the demo's stream); write s = wall time less the gaps");
    println!("| points | gap between points | checkpoints | write s | per point ms | fsyncs | file bytes | read s |");
    println!("|---|---|---|---|---|---|---|---|");
    let real = Duration::from_millis(110);
    for (n, checkpoints, gap) in [
        (points, false, Duration::ZERO),
        (points, true, Duration::ZERO),
        (points / 10, false, real),
        (points / 10, true, real),
    ] {
        let (w, bytes, flushes, r) = record(n, checkpoints, gap);
        println!(
            "| {n} | {} ms | {} | {w:.3} | {:.3} | {flushes} | {bytes} | {r:.3} |",
            gap.as_millis(),
            if checkpoints {
                "every point"
            } else {
                "1 s timer only"
            },
            w * 1e3 / n as f64
        );
    }
}
