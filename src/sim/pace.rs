//! Pacing of a simulated run (`[sim] pace`): a tracer wrapper that holds each sample back
//! until wall time has caught up with its device time divided by the pace.

use std::time::{Duration, Instant};

use async_trait::async_trait;
use geocal_drivers::{DeviceError, Tracer, TracerReading};

pub struct PacedTracer {
    inner: Box<dyn Tracer>,
    /// Virtual seconds per wall second.
    pace: f64,
    /// Wall instant and device time of the first sample.
    start: Option<(Instant, f64)>,
}

impl PacedTracer {
    pub fn new(inner: Box<dyn Tracer>, pace: f64) -> Self {
        Self {
            inner,
            pace,
            start: None,
        }
    }
}

#[async_trait]
impl Tracer for PacedTracer {
    fn id(&self) -> &str {
        self.inner.id()
    }
    async fn next_sample(&mut self) -> Result<TracerReading, DeviceError> {
        let reading = self.inner.next_sample().await?;
        let (wall0, t0) = *self.start.get_or_insert((Instant::now(), reading.t_s));
        let due_s = (reading.t_s - t0) / self.pace;
        if due_s.is_finite() && due_s > 0.0 {
            let due = wall0 + Duration::from_secs_f64(due_s);
            let now = Instant::now();
            if due > now {
                tokio::time::sleep(due - now).await;
            }
        }
        Ok(reading)
    }
    async fn home(&mut self) -> Result<(), DeviceError> {
        self.inner.home().await
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Stream(f64);

    #[async_trait]
    impl Tracer for Stream {
        fn id(&self) -> &str {
            "t"
        }
        async fn next_sample(&mut self) -> Result<TracerReading, DeviceError> {
            self.0 += 0.1;
            Ok(TracerReading {
                seq: 0,
                t_s: self.0,
                length_m: 0.0,
                signal: 1.0,
                tracking: true,
                beam_segment: 0,
            })
        }
        async fn home(&mut self) -> Result<(), DeviceError> {
            Ok(())
        }
    }

    #[tokio::test]
    async fn samples_wait_for_wall_time() {
        let mut t = PacedTracer::new(Box::new(Stream(0.0)), 50.0);
        let start = Instant::now();
        for _ in 0..11 {
            t.next_sample().await.unwrap();
        }
        // 1 s of device time at 50x cannot take less than 20 ms of wall time.
        assert!(
            start.elapsed() >= Duration::from_millis(20),
            "{:?}",
            start.elapsed()
        );
    }
}
