//! Device connections kept open between runs by a long-running caller (the daemon): each
//! device is connected when a run first needs it, lent to one run at a time, reconnected
//! when its settings change or after a run saw it fail, and closed after a configured idle
//! time. The connections' reader tasks and I/O live on the holder's own runtime, which
//! outlives the runs; a run on held devices is driven on that runtime too.

use std::any::Any;
use std::collections::BTreeMap;
use std::future::Future;
use std::ops::{Deref, DerefMut};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use async_trait::async_trait;
use geocal_drivers::{
    DeviceError, Hexapod, HexapodState, LegReading, LinkFault, Machine, MachineState, PlatformPose,
    Probe, ProbeReading, RotaryState, RotaryTable, Tracer, TracerReading,
};
use serde::Serialize;
use tokio::sync::OwnedMutexGuard;

/// A driver that can be lent to a run again after an earlier run used it.
#[async_trait]
pub trait Holdable: Send + 'static {
    /// Bring the device to the state a freshly opened driver starts in (restart streams,
    /// drop what arrived while it was idle).
    async fn reuse(&mut self) -> Result<(), DeviceError> {
        Ok(())
    }
}

#[async_trait]
impl Holdable for geocal_drivers::hpi3d::Hpi3dTracer {
    async fn reuse(&mut self) -> Result<(), DeviceError> {
        self.start_streams().await
    }
}

impl<S: Send + 'static> Holdable for geocal_drivers::grbl::GrblMachine<S> {}

#[async_trait]
impl Holdable for geocal_drivers::linuxcnc::LinuxCncMachine {
    /// The connection may have been closed while idle: a query shows it (and reconnects).
    /// Then the start of a run, as a fresh connection makes it (the state found, the checks
    /// that may refuse, MDI mode).
    async fn reuse(&mut self) -> Result<(), DeviceError> {
        self.ping().await?;
        self.begin_run().await
    }
}
impl<S: Send + 'static> Holdable for geocal_drivers::probe::AsciiProbe<S> {}
impl Holdable for geocal_drivers::modbus_table::ModbusTable {}
impl Holdable for geocal_drivers::modbus_hexapod::ModbusHexapod {}

/// One held connection's state, as `/v1/devices` shows it.
#[derive(Debug, Clone, Serialize, serde::Deserialize, PartialEq, utoipa::ToSchema)]
pub struct HeldStatus {
    pub id: String,
    /// Lent to the running job.
    pub in_use: bool,
    /// Seconds since it was connected.
    pub connected_s: f64,
    /// Seconds since its last run ended (absent while in use or before its first run ended).
    pub idle_s: Option<f64>,
    /// Connections opened for this device id since the holder started.
    pub opens: u64,
    /// Runs it was lent to on this connection.
    pub leases: u64,
}

struct Slot {
    /// The settings the connection was opened with (their JSON).
    settings: String,
    /// An `Arc<tokio::sync::Mutex<T>>` for the driver type `T`.
    device: Box<dyn Any + Send + Sync>,
    state: Arc<SlotState>,
    connected_at: Instant,
}

#[derive(Default)]
struct SlotState {
    in_use: AtomicBool,
    /// A run saw a disconnection or time-out: reconnect before lending it again.
    faulted: AtomicBool,
    idle_since: Mutex<Option<Instant>>,
    leases: AtomicU64,
}

/// The held connections, by device id.
pub struct DeviceHolder {
    runtime: Option<tokio::runtime::Runtime>,
    slots: Arc<Mutex<BTreeMap<String, Slot>>>,
    opens: Arc<Mutex<BTreeMap<String, u64>>>,
}

impl DeviceHolder {
    /// A holder whose idle connections are closed after `release_idle_after` (never if
    /// `None`).
    pub fn new(release_idle_after: Option<Duration>) -> anyhow::Result<Arc<DeviceHolder>> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("geocal-devices")
            .enable_all()
            .build()
            .context("starting the devices' runtime")?;
        let holder = Arc::new(DeviceHolder {
            runtime: Some(runtime),
            slots: Arc::default(),
            opens: Arc::default(),
        });
        if let (Some(after), Some(runtime)) = (release_idle_after, &holder.runtime) {
            let slots = Arc::downgrade(&holder.slots);
            runtime.spawn(async move {
                let period = (after / 4).clamp(Duration::from_millis(50), Duration::from_secs(5));
                loop {
                    tokio::time::sleep(period).await;
                    let Some(slots) = slots.upgrade() else { break };
                    release_idle(&slots, after);
                }
            });
        }
        Ok(holder)
    }

    /// The runtime a run on held devices is driven on.
    pub fn handle(&self) -> Option<tokio::runtime::Handle> {
        self.runtime.as_ref().map(|r| r.handle().clone())
    }

    /// Lend the device `id` to a run: the held connection if it was opened with the same
    /// `settings` and no run saw it fail, else a new one from `open` (closing the old one).
    /// Must run on the holder's runtime (`handle`).
    pub async fn lend<T, F, Fut>(
        &self,
        id: &str,
        settings: &impl Serialize,
        open: F,
    ) -> anyhow::Result<Held<T>>
    where
        T: Holdable,
        F: FnOnce() -> Fut,
        Fut: Future<Output = anyhow::Result<T>>,
    {
        let settings = serde_json::to_string(settings)
            .with_context(|| format!("device {id}: its settings as JSON"))?;
        if let Some((device, state)) = self.reusable::<T>(id, &settings) {
            let mut guard = device
                .try_lock_owned()
                .map_err(|_| anyhow::anyhow!("device {id} is in use by another run"))?;
            match guard.reuse().await {
                Ok(()) => return Ok(Held::new(guard, state)),
                Err(e) => {
                    tracing::warn!(
                        device = id,
                        "held connection failed on reuse ({e}); reconnecting"
                    );
                    drop(guard);
                    self.release(id);
                }
            }
        }
        let driver = open().await?;
        *self
            .opens
            .lock()
            .map_err(|_| anyhow::anyhow!("device holder poisoned"))?
            .entry(id.to_string())
            .or_default() += 1;
        let device = Arc::new(tokio::sync::Mutex::new(driver));
        let state = Arc::new(SlotState::default());
        let guard = device
            .clone()
            .try_lock_owned()
            .map_err(|_| anyhow::anyhow!("device {id}: a new connection is already locked"))?;
        let slot = Slot {
            settings,
            device: Box::new(device),
            state: state.clone(),
            connected_at: Instant::now(),
        };
        if let Ok(mut slots) = self.slots.lock() {
            slots.insert(id.to_string(), slot);
        }
        tracing::info!(device = id, "connected; held between runs");
        Ok(Held::new(guard, state))
    }

    /// The held connection for `id` if it can be lent again as a `T` with these settings;
    /// a connection that cannot is closed.
    fn reusable<T: Holdable>(
        &self,
        id: &str,
        settings: &str,
    ) -> Option<(Arc<tokio::sync::Mutex<T>>, Arc<SlotState>)> {
        let mut slots = self.slots.lock().ok()?;
        let slot = slots.get(id)?;
        let device = slot.device.downcast_ref::<Arc<tokio::sync::Mutex<T>>>();
        match device {
            Some(device)
                if slot.settings == settings && !slot.state.faulted.load(Ordering::Relaxed) =>
            {
                Some((device.clone(), slot.state.clone()))
            }
            _ => {
                let why = if slot.state.faulted.load(Ordering::Relaxed) {
                    "a run saw it fail"
                } else {
                    "its settings changed"
                };
                tracing::info!(device = id, "closing the held connection: {why}");
                slots.remove(id);
                None
            }
        }
    }

    /// Close the held connection of `id`, if any (a run still using it keeps it until it
    /// ends).
    pub fn release(&self, id: &str) {
        if let Ok(mut slots) = self.slots.lock() {
            slots.remove(id);
        }
    }

    pub fn status(&self) -> Vec<HeldStatus> {
        let opens = self.opens.lock().map(|o| o.clone()).unwrap_or_default();
        let Ok(slots) = self.slots.lock() else {
            return Vec::new();
        };
        let now = Instant::now();
        slots
            .iter()
            .map(|(id, slot)| {
                let in_use = slot.state.in_use.load(Ordering::Relaxed);
                let idle_since = slot.state.idle_since.lock().ok().and_then(|t| *t);
                HeldStatus {
                    id: id.clone(),
                    in_use,
                    connected_s: now.duration_since(slot.connected_at).as_secs_f64(),
                    idle_s: idle_since
                        .filter(|_| !in_use)
                        .map(|t| now.duration_since(t).as_secs_f64()),
                    opens: opens.get(id).copied().unwrap_or(0),
                    leases: slot.state.leases.load(Ordering::Relaxed),
                }
            })
            .collect()
    }
}

impl Drop for DeviceHolder {
    fn drop(&mut self) {
        if let Ok(mut slots) = self.slots.lock() {
            slots.clear();
        }
        // Dropping a runtime blocks; the daemon may drop its holder inside async code.
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_background();
        }
    }
}

/// Close the connections idle for at least `after`.
fn release_idle(slots: &Mutex<BTreeMap<String, Slot>>, after: Duration) {
    let Ok(mut slots) = slots.lock() else { return };
    slots.retain(|id, slot| {
        let in_use = slot.state.in_use.load(Ordering::Relaxed);
        let idle_since = slot.state.idle_since.lock().ok().and_then(|t| *t);
        let keep = in_use || idle_since.is_none_or(|t| t.elapsed() < after);
        if !keep {
            tracing::info!(
                device = id,
                "idle for {} s: connection closed",
                after.as_secs_f64()
            );
        }
        keep
    });
}

/// A held driver lent to one run; the connection returns to the holder when this is
/// dropped.
pub struct Held<T> {
    driver: OwnedMutexGuard<T>,
    state: Arc<SlotState>,
}

impl<T> Held<T> {
    fn new(driver: OwnedMutexGuard<T>, state: Arc<SlotState>) -> Self {
        state.in_use.store(true, Ordering::Relaxed);
        state.leases.fetch_add(1, Ordering::Relaxed);
        if let Ok(mut idle) = state.idle_since.lock() {
            *idle = None;
        }
        Held { driver, state }
    }

    /// Pass a driver's answer on, noting a failure the connection may not survive.
    fn noted<R>(&self, result: Result<R, DeviceError>) -> Result<R, DeviceError> {
        if matches!(
            result,
            Err(DeviceError::Disconnected { .. }
                | DeviceError::Timeout { .. }
                | DeviceError::EndOfStream { .. })
        ) {
            self.state.faulted.store(true, Ordering::Relaxed);
        }
        result
    }
}

impl<T> Drop for Held<T> {
    fn drop(&mut self) {
        if let Ok(mut idle) = self.state.idle_since.lock() {
            *idle = Some(Instant::now());
        }
        self.state.in_use.store(false, Ordering::Relaxed);
    }
}

impl<T> Deref for Held<T> {
    type Target = T;
    fn deref(&self) -> &T {
        &self.driver
    }
}

impl<T> DerefMut for Held<T> {
    fn deref_mut(&mut self) -> &mut T {
        &mut self.driver
    }
}

#[async_trait]
impl<T: Tracer + Holdable> Tracer for Held<T> {
    fn id(&self) -> &str {
        self.driver.id()
    }
    async fn next_sample(&mut self) -> Result<TracerReading, DeviceError> {
        let r = self.driver.next_sample().await;
        self.noted(r)
    }
    async fn home(&mut self) -> Result<(), DeviceError> {
        let r = self.driver.home().await;
        self.noted(r)
    }
    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        self.driver.take_link_faults()
    }
}

#[async_trait]
impl<T: Machine + Holdable> Machine for Held<T> {
    fn id(&self) -> &str {
        self.driver.id()
    }
    async fn start_move(
        &mut self,
        target: &geocal_drivers::AxisPositions,
    ) -> Result<(), DeviceError> {
        let r = self.driver.start_move(target).await;
        self.noted(r)
    }
    async fn state(&mut self) -> Result<MachineState, DeviceError> {
        let r = self.driver.state().await;
        self.noted(r)
    }
    async fn unlock(&mut self) -> Result<(), DeviceError> {
        let r = self.driver.unlock().await;
        self.noted(r)
    }
    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        self.driver.take_link_faults()
    }
    async fn finish(&mut self) -> Result<(), DeviceError> {
        let r = self.driver.finish().await;
        self.noted(r)
    }
}

#[async_trait]
impl<T: RotaryTable + Holdable> RotaryTable for Held<T> {
    fn id(&self) -> &str {
        self.driver.id()
    }
    async fn start_rotation(&mut self, commanded_rad: f64) -> Result<(), DeviceError> {
        let r = self.driver.start_rotation(commanded_rad).await;
        self.noted(r)
    }
    async fn state(&mut self) -> Result<RotaryState, DeviceError> {
        let r = self.driver.state().await;
        self.noted(r)
    }
    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        self.driver.take_link_faults()
    }
}

#[async_trait]
impl<T: Probe + Holdable> Probe for Held<T> {
    fn id(&self) -> &str {
        self.driver.id()
    }
    async fn read(&mut self) -> Result<ProbeReading, DeviceError> {
        let r = self.driver.read().await;
        self.noted(r)
    }
}

#[async_trait]
impl<T: Hexapod + Holdable> Hexapod for Held<T> {
    fn id(&self) -> &str {
        self.driver.id()
    }
    async fn start_move(&mut self, pose: &PlatformPose) -> Result<(), DeviceError> {
        let r = self.driver.start_move(pose).await;
        self.noted(r)
    }
    async fn state(&mut self) -> Result<HexapodState, DeviceError> {
        let r = self.driver.state().await;
        self.noted(r)
    }
    async fn read_legs(&mut self) -> Result<LegReading, DeviceError> {
        let r = self.driver.read_legs().await;
        self.noted(r)
    }
    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        self.driver.take_link_faults()
    }
}

/// A driver for a run: lent by the holder when there is one, else opened for this run only.
pub async fn lend_or_open<T, F, Fut>(
    holder: Option<&DeviceHolder>,
    id: &str,
    settings: &impl Serialize,
    open: F,
) -> anyhow::Result<Box<Held<T>>>
where
    T: Holdable,
    F: FnOnce() -> Fut,
    Fut: Future<Output = anyhow::Result<T>>,
{
    let held = match holder {
        Some(holder) => holder.lend(id, settings, open).await?,
        // A private holder: the connection closes when the run drops it.
        None => {
            let device = Arc::new(tokio::sync::Mutex::new(open().await?));
            let guard = device
                .try_lock_owned()
                .map_err(|_| anyhow::anyhow!("device {id}: a new connection is already locked"))?;
            Held::new(guard, Arc::default())
        }
    };
    Ok(Box::new(held))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tracer whose every connection has a number, failing on demand.
    struct Fake {
        connection: u64,
        fail_next: bool,
        reused: u32,
    }

    #[async_trait]
    impl Holdable for Fake {
        async fn reuse(&mut self) -> Result<(), DeviceError> {
            self.reused += 1;
            Ok(())
        }
    }

    #[async_trait]
    impl Tracer for Fake {
        fn id(&self) -> &str {
            "fake"
        }
        async fn next_sample(&mut self) -> Result<TracerReading, DeviceError> {
            if std::mem::take(&mut self.fail_next) {
                return Err(DeviceError::Disconnected {
                    device: "fake".into(),
                    message: "cable pulled".into(),
                });
            }
            Ok(TracerReading {
                seq: self.connection,
                t_s: 0.0,
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

    fn opener(counter: &Arc<AtomicU64>) -> impl Future<Output = anyhow::Result<Fake>> {
        let connection = counter.fetch_add(1, Ordering::Relaxed) + 1;
        async move {
            Ok(Fake {
                connection,
                fail_next: false,
                reused: 0,
            })
        }
    }

    async fn connection_of(held: &mut Held<Fake>) -> u64 {
        match held.next_sample().await {
            Ok(r) => r.seq,
            Err(e) => panic!("{e}"),
        }
    }

    #[test]
    fn a_connection_is_lent_again_until_its_settings_change_or_it_fails() {
        let holder = DeviceHolder::new(None).expect("holder");
        let handle = holder.handle().expect("runtime");
        let opened = Arc::new(AtomicU64::new(0));
        handle.block_on(async {
            let lend = |settings: &'static str| {
                let opened = opened.clone();
                let holder = holder.clone();
                async move {
                    holder
                        .lend::<Fake, _, _>("t", &settings, || opener(&opened))
                        .await
                        .expect("lend")
                }
            };
            let mut first = lend("a").await;
            assert_eq!(connection_of(&mut first).await, 1);
            // Lent to one run at a time.
            let busy = holder
                .lend::<Fake, _, _>("t", &"a", || opener(&opened))
                .await;
            assert!(busy.is_err_and(|e| e.to_string().contains("in use")));
            drop(first);

            let mut again = lend("a").await;
            assert_eq!(
                connection_of(&mut again).await,
                1,
                "same settings: same connection"
            );
            assert_eq!(again.reused, 1, "made ready for its new run");
            let status = holder.status();
            assert_eq!(
                (status[0].opens, status[0].leases, status[0].in_use),
                (1, 2, true)
            );
            drop(again);

            let mut changed = lend("b").await;
            assert_eq!(
                connection_of(&mut changed).await,
                2,
                "new settings: reconnected"
            );
            changed.fail_next = true;
            assert!(changed.next_sample().await.is_err());
            drop(changed);

            let mut after_fault = lend("b").await;
            assert_eq!(
                connection_of(&mut after_fault).await,
                3,
                "failed: reconnected"
            );
            assert_eq!(holder.status()[0].opens, 3);
        });
    }

    #[test]
    fn idle_connections_are_closed_after_the_configured_time() {
        let holder = DeviceHolder::new(Some(Duration::from_millis(200))).expect("holder");
        let handle = holder.handle().expect("runtime");
        let opened = Arc::new(AtomicU64::new(0));
        let held = handle.block_on(holder.lend::<Fake, _, _>("t", &"a", || opener(&opened)));
        let held = held.expect("lend");
        // In use: never released, however long the run.
        std::thread::sleep(Duration::from_millis(600));
        assert_eq!(holder.status().len(), 1);
        drop(held);
        let deadline = Instant::now() + Duration::from_secs(30);
        while !holder.status().is_empty() {
            assert!(Instant::now() < deadline, "idle connection never closed");
            std::thread::sleep(Duration::from_millis(50));
        }
        let mut next = handle
            .block_on(holder.lend::<Fake, _, _>("t", &"a", || opener(&opened)))
            .expect("lend");
        assert_eq!(
            handle.block_on(connection_of(&mut next)),
            2,
            "reconnected lazily"
        );
    }
}
