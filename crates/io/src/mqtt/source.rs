//! The broker as a source: what the gateway subscribes to (route requests,
//! cancels, feedback, phone scans, other gateways' sightings), read by the
//! [`Inbox`] and handed to the runtime as [`Inbound`] messages. A message
//! that cannot be used is logged here (at most once per ten seconds, with how
//! many were not) and counted by the runtime.

use std::time::Duration;

use futures::future::BoxFuture;
use tokio::sync::mpsc;

use super::Received;
use super::inbound::{Inbox, Rejected};
use crate::source::unix_now;
use crate::source::{Source, SourceContext};

use crate::event::Inbound;
use crate::throttle::Throttle;

/// At most one line per this period about refused messages.
const WARN_EVERY: Duration = Duration::from_secs(10);

/// Messages from the broker, read.
pub struct MqttSource {
    inbound: mpsc::Receiver<Received>,
    inbox: Inbox,
}

impl MqttSource {
    pub(super) fn new(inbound: mpsc::Receiver<Received>, inbox: Inbox) -> MqttSource {
        MqttSource { inbound, inbox }
    }
}

impl Source for MqttSource {
    fn name(&self) -> &'static str {
        "mqtt"
    }

    fn run(self: Box<Self>, mut cx: SourceContext) -> BoxFuture<'static, anyhow::Result<()>> {
        let MqttSource { mut inbound, inbox } = *self;
        let mut refused = Throttle::new(WARN_EVERY);
        Box::pin(async move {
            loop {
                let message = tokio::select! {
                    message = inbound.recv() => message,
                    () = cx.shutdown.recv() => return Ok(()),
                };
                let Some(message) = message else {
                    anyhow::bail!("the MQTT link stopped");
                };
                let read =
                    inbox.read_sized(&message.topic, &message.payload, message.size, unix_now());
                let read = match read {
                    Ok(read) => read,
                    Err(Rejected::Own { .. } | Rejected::NotAnIbeacon { .. }) => continue,
                    Err(e) => {
                        if let Some(more) = refused.ready() {
                            tracing::warn!(not_logged = more, "ignored message: {e}");
                        }
                        Inbound::Refused {
                            oversized: e.is_oversized(),
                        }
                    }
                };
                if cx.inbound(read).await.is_err() {
                    return Ok(());
                }
            }
        })
    }
}
