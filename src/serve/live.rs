//! The live view: a Foxglove WebSocket server that republishes every message a run records,
//! on the same topic with the same encoding and schema, logged at its recorded log time.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

use anyhow::Context as _;
use foxglove::{Context, PartialMetadata, RawChannel, Schema, WebSocketServerHandle};

pub use super::live_guard::LiveAccess;
use super::live_guard::{front, ChannelCreation, Front, RunEnds};
use crate::session::tap::{MessageTap, TapChannel, TappedMessage};

/// Messages waiting for the publisher thread; beyond this the live view drops (the recorded
/// session never does).
const QUEUE_CAPACITY: usize = 8192;

struct Pending {
    channel: Arc<TapChannel>,
    log_time_ns: u64,
    data: Vec<u8>,
}

/// A live view address as given on the command line or in the daemon configuration: a port
/// alone binds loopback (`8765` is `127.0.0.1:8765`); `HOST:PORT` binds that address.
pub fn parse_address(text: &str) -> anyhow::Result<SocketAddr> {
    let text = text.trim();
    if let Ok(port) = text.parse::<u16>() {
        return Ok(SocketAddr::from(([127, 0, 0, 1], port)));
    }
    text.parse::<SocketAddr>().map_err(|_| {
        anyhow::anyhow!(
            "live view address {text:?}: expected a port (e.g. 8765, on loopback) or \
             IP:PORT (e.g. 127.0.0.1:8765, [::1]:8765, 0.0.0.0:8765 for every interface)"
        )
    })
}

/// A running live view. Dropping it (or `stop`) stops the server.
pub struct LiveView {
    address: SocketAddr,
    sender: Mutex<Option<SyncSender<Pending>>>,
    dropped: Arc<AtomicU64>,
    published: Arc<AtomicU64>,
    publisher: Mutex<Option<JoinHandle<()>>>,
    server: Mutex<Option<(WebSocketServerHandle, tokio::runtime::Runtime)>>,
    /// Disconnects the viewers when a run ends (the daemon's live view outlives its runs).
    run_ends: Arc<RunEnds>,
}

impl LiveView {
    /// Start a Foxglove WebSocket server on `address` (port 0: any free port; see `address`)
    /// open to native clients and the Foxglove app's origins, without a token.
    pub fn start(address: SocketAddr) -> anyhow::Result<LiveView> {
        LiveView::start_guarded(address, LiveAccess::default())
    }

    /// Start the live view on `address`, admitting only what `access` allows: the Foxglove
    /// server listens on an internal loopback port behind the checking front (`live_guard`).
    /// Safe to call from inside or outside an async runtime: the server has its own.
    pub fn start_guarded(address: SocketAddr, access: LiveAccess) -> anyhow::Result<LiveView> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("geocal-live")
            .enable_all()
            .build()
            .context("starting the live view's runtime")?;
        let context = Context::new();
        let handle = runtime.handle().clone();
        let server = context
            .websocket_server()
            .name("geocal")
            .bind("127.0.0.1", 0)
            .tokio_runtime(&handle);
        // `block_on` may not run on an async worker thread, so start from a plain one.
        let (started, listener) = std::thread::scope(|s| {
            s.spawn(|| {
                let listener = handle.block_on(tokio::net::TcpListener::bind(address));
                (handle.block_on(server.start()), listener)
            })
            .join()
            .map_err(|_| anyhow::anyhow!("the live view's start thread panicked"))
        })?;
        let started =
            started.with_context(|| format!("starting the Foxglove live view on {address}"))?;
        let listener =
            listener.with_context(|| format!("listening for the live view on {address}"))?;
        let bound = listener
            .local_addr()
            .context("reading the live view's bound address")?;
        let inner = SocketAddr::from(([127, 0, 0, 1], started.port()));
        let run_ends = Arc::new(RunEnds::default());
        let creation = Arc::new(ChannelCreation::default());
        handle.spawn(front(
            listener,
            Arc::new(Front {
                inner,
                access,
                run_ends: run_ends.clone(),
                creation: creation.clone(),
            }),
        ));

        let (sender, receiver) = sync_channel(QUEUE_CAPACITY);
        let published = Arc::new(AtomicU64::new(0));
        let publisher = {
            let published = published.clone();
            std::thread::Builder::new()
                .name("geocal-live-publish".into())
                .spawn(move || publish(context, receiver, published, &creation))
                .context("starting the live view's publisher thread")?
        };
        tracing::info!(address = %bound, "live view: Foxglove WebSocket server listening");
        Ok(LiveView {
            address: bound,
            sender: Mutex::new(Some(sender)),
            dropped: Arc::new(AtomicU64::new(0)),
            published,
            publisher: Mutex::new(Some(publisher)),
            server: Mutex::new(Some((started, runtime))),
            run_ends,
        })
    }

    /// The address the server is bound to (with the real port when 0 was asked for).
    pub fn address(&self) -> SocketAddr {
        self.address
    }

    /// Messages the live view dropped because its queue was full.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Messages handed to the server.
    pub fn published(&self) -> u64 {
        self.published.load(Ordering::Relaxed)
    }

    /// Publish what is queued, then stop the server and close its connections.
    pub fn stop(&self) {
        let sender = self.sender.lock().ok().and_then(|mut s| s.take());
        drop(sender);
        let publisher = self.publisher.lock().ok().and_then(|mut p| p.take());
        if let Some(publisher) = publisher {
            if publisher.join().is_err() {
                tracing::error!("live view: the publisher thread panicked");
            }
        }
        let server = self.server.lock().ok().and_then(|mut s| s.take());
        if let Some((handle, runtime)) = server {
            // Waiting blocks, which an async caller's thread may not do: wait on a plain one.
            let stopped = std::thread::spawn(move || {
                handle.stop().wait_blocking();
                runtime.shutdown_background();
            })
            .join();
            if stopped.is_err() {
                tracing::error!("live view: stopping the server panicked");
            }
            let dropped = self.dropped();
            if dropped > 0 {
                tracing::warn!(dropped, "live view: messages dropped (queue full)");
            }
        }
    }
}

impl Drop for LiveView {
    fn drop(&mut self) {
        self.stop();
    }
}

impl MessageTap for LiveView {
    fn message(&self, message: &TappedMessage<'_>) {
        let Ok(guard) = self.sender.try_lock() else {
            self.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        };
        let Some(sender) = guard.as_ref() else {
            return;
        };
        let pending = Pending {
            channel: message.channel.clone(),
            log_time_ns: message.log_time_ns,
            data: message.data.to_vec(),
        };
        match sender.try_send(pending) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
            }
            Err(TrySendError::Disconnected(_)) => {}
        }
    }

    fn run_ended(&self) {
        self.run_ends.end();
    }
}

/// The publisher thread: one Foxglove channel per recorded channel, created on first use.
fn publish(
    context: Arc<Context>,
    receiver: Receiver<Pending>,
    published: Arc<AtomicU64>,
    creation: &ChannelCreation,
) {
    let mut channels: HashMap<u16, Option<Arc<RawChannel>>> = HashMap::new();
    while let Ok(message) = receiver.recv() {
        let channel = channels.entry(message.channel.id).or_insert_with(|| {
            creation.hold_clients_during(|| live_channel(&context, &message.channel))
        });
        if let Some(channel) = channel {
            channel.log_with_meta(
                &message.data,
                PartialMetadata {
                    log_time: Some(message.log_time_ns),
                },
            );
            published.fetch_add(1, Ordering::Relaxed);
        }
    }
    for channel in channels.values().flatten() {
        channel.close();
    }
}

fn live_channel(context: &Arc<Context>, recorded: &TapChannel) -> Option<Arc<RawChannel>> {
    let schema = recorded
        .schema
        .as_ref()
        .map(|(name, encoding, data)| Schema::new(name.clone(), encoding.clone(), data.clone()));
    match context
        .channel_builder(recorded.topic.clone())
        .message_encoding(recorded.message_encoding.clone())
        .schema(schema)
        .build_raw()
    {
        Ok(channel) => Some(channel),
        Err(e) => {
            tracing::warn!(topic = %recorded.topic, "live view: cannot publish this topic: {e}");
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses_default_to_loopback() {
        assert_eq!(
            parse_address("8765").unwrap(),
            "127.0.0.1:8765".parse().unwrap()
        );
        assert_eq!(
            parse_address("0.0.0.0:9000").unwrap(),
            "0.0.0.0:9000".parse().unwrap()
        );
        let e = parse_address("localhost:x").unwrap_err().to_string();
        assert!(
            e.starts_with("live view address \"localhost:x\": expected a port"),
            "{e}"
        );
    }

    #[test]
    fn binds_loopback_on_a_free_port_and_stops() {
        let view = LiveView::start("127.0.0.1:0".parse().unwrap()).unwrap();
        let address = view.address();
        assert!(address.ip().is_loopback());
        assert_ne!(address.port(), 0);
        assert!(std::net::TcpStream::connect(address).is_ok());
        let channel = Arc::new(TapChannel {
            id: 1,
            topic: "/t".into(),
            message_encoding: "json".into(),
            schema: Some(("T".into(), "jsonschema".into(), b"{}".to_vec())),
        });
        view.message(&TappedMessage {
            channel: &channel,
            sequence: 0,
            log_time_ns: 5,
            publish_time_ns: 5,
            data: b"{}",
            queue_depth: 0,
        });
        view.stop();
        assert_eq!(view.published(), 1);
        assert_eq!(view.dropped(), 0);
        // The listener closes as its runtime winds down in the background.
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
        while std::net::TcpStream::connect(address).is_ok() {
            assert!(std::time::Instant::now() < deadline, "still listening");
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
    }
}
