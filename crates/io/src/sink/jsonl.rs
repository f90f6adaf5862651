//! The messages the gateway publishes, as JSON Lines: one
//! `{"topic": …, "payload": {…}}` object per line, written by the MQTT
//! encoder ([`Topics::encode`]) so a line holds exactly what a subscriber
//! gets. On stdout it is `--print`; in a file it is `--out FILE` (the file
//! is created, or truncated, at start, and flushed at every pause and at
//! shutdown, so `tail -f` follows it).

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use anyhow::Context;
use futures::future::BoxFuture;

use super::Sink;
use crate::publish::Output;
use crate::topics::{Message, Topics};

/// JSON Lines of the published messages, to any writer.
pub struct JsonLines<W: Write + Send> {
    topics: Topics,
    out: BufWriter<W>,
    /// What errors name: `stdout` or the file.
    target: String,
}

impl<W: Write + Send> JsonLines<W> {
    /// JSON Lines to `out`; errors name it `target`.
    pub fn new(topics: Topics, out: W, target: &str) -> Self {
        JsonLines {
            topics,
            out: BufWriter::new(out),
            target: target.to_owned(),
        }
    }
}

impl<W: Write + Send> JsonLines<W> {
    /// `{"topic":…,"payload":…}` and a newline: a JSON string, then the
    /// payload as written for the broker.
    fn write(&mut self, message: &Message) -> std::io::Result<()> {
        self.out.write_all(b"{\"topic\":")?;
        serde_json::to_writer(&mut self.out, &message.topic)?;
        self.out.write_all(b",\"payload\":")?;
        self.out.write_all(&message.payload)?;
        self.out.write_all(b"}\n")
    }
}

impl JsonLines<std::io::Stdout> {
    /// `--print`.
    pub fn stdout(topics: Topics) -> Self {
        JsonLines::new(topics, std::io::stdout(), "stdout")
    }
}

impl JsonLines<File> {
    /// `--out FILE`.
    pub fn create(topics: Topics, path: &Path) -> anyhow::Result<Self> {
        let file =
            File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
        Ok(JsonLines::new(topics, file, &path.display().to_string()))
    }
}

impl<W: Write + Send + 'static> Sink for JsonLines<W> {
    fn name(&self) -> &'static str {
        "jsonl"
    }

    fn send(&mut self, outputs: &[Output]) -> anyhow::Result<()> {
        for output in outputs {
            if let Some(message) = self.topics.encode(output) {
                self.write(&message)
                    .with_context(|| format!("writing to {}", self.target))?;
            }
        }
        Ok(())
    }

    fn flush(&mut self) -> BoxFuture<'_, anyhow::Result<()>> {
        let flushed = self
            .out
            .flush()
            .with_context(|| format!("writing to {}", self.target));
        Box::pin(std::future::ready(flushed))
    }

    fn shutdown(mut self: Box<Self>) -> BoxFuture<'static, anyhow::Result<()>> {
        let flushed = self
            .out
            .flush()
            .with_context(|| format!("writing to {}", self.target));
        Box::pin(std::future::ready(flushed))
    }
}
