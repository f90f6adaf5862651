//! The log: one line per event on standard error, for people (coloured on a
//! terminal) or, with `GANGWAY_LOG_FORMAT=json`, one JSON object per line for
//! log shippers, filtered by `RUST_LOG`.
//!
//! Log lines carry text from outside (a topic, a payload's unknown key, a
//! device id, a file's line): a newline or an escape sequence in it must not
//! start a forged line or recolour the terminal. Rather than trusting every
//! call site to escape what it logs, the human format's writer escapes every
//! control character of an event but the newline that ends it, so a line is
//! one event whatever its fields hold (the JSON format escapes by itself).

use std::io::{self, IsTerminal, Write};

use tracing_subscriber::EnvFilter;
use tracing_subscriber::fmt::MakeWriter;

/// Installs the log for the process.
pub fn init() {
    // RUST_LOG filters. The embedded broker's chatter stays at warn, and its
    // connection and routing modules are silenced: they log every client
    // disconnect as an error (`router-drop`, and at shutdown "no-connection
    // id 0 is already gone"), and its one real failure, a busy port, is
    // checked before it starts (`mqtt::broker`).
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| {
        EnvFilter::new("info,rumqttd=warn,rumqttd::server::broker=off,rumqttd::router::routing=off")
    });
    let json = std::env::var("GANGWAY_LOG_FORMAT").is_ok_and(|f| f.eq_ignore_ascii_case("json"));
    let builder = tracing_subscriber::fmt().with_env_filter(filter);
    if json {
        builder.json().with_writer(io::stderr).init();
    } else {
        let ansi = io::stderr().is_terminal();
        builder
            .with_ansi(ansi)
            .with_writer(OneLinePerEvent { ansi })
            .init();
    }
}

/// Standard error, with each event's control characters escaped.
#[derive(Clone, Copy)]
struct OneLinePerEvent {
    /// Whether the formatter colours (its own escape sequences stay).
    ansi: bool,
}

impl<'a> MakeWriter<'a> for OneLinePerEvent {
    type Writer = EscapingWriter;

    fn make_writer(&'a self) -> EscapingWriter {
        EscapingWriter { ansi: self.ansi }
    }
}

struct EscapingWriter {
    ansi: bool,
}

impl Write for EscapingWriter {
    /// Takes one formatted event (the formatter writes each in one call).
    fn write(&mut self, event: &[u8]) -> io::Result<usize> {
        io::stderr().lock().write_all(&escaped(event, self.ansi))?;
        Ok(event.len())
    }

    fn flush(&mut self) -> io::Result<()> {
        io::stderr().flush()
    }
}

/// `event` with every control character but its final newline (and tabs,
/// and with `ansi` the formatter's own colour sequences) written as `\n`,
/// `\r`, `\u{1b}`…
fn escaped(event: &[u8], ansi: bool) -> Vec<u8> {
    let text = String::from_utf8_lossy(event);
    let body = text.strip_suffix('\n').unwrap_or(&text);
    let mut out = String::with_capacity(body.len() + 1);
    let mut chars = body.chars().peekable();
    while let Some(c) = chars.next() {
        // The formatter's colours are `ESC [ digits/; m`; anything else
        // after an ESC is not its own.
        if ansi && c == '\u{1b}' && chars.peek() == Some(&'[') {
            let sequence: String = chars
                .clone()
                .skip(1)
                .take_while(|c| c.is_ascii_digit() || *c == ';')
                .collect();
            if chars.clone().nth(1 + sequence.len()) == Some('m') {
                out.push(c);
                out.extend(chars.by_ref().take(2 + sequence.len()));
                continue;
            }
        }
        if c.is_control() && c != '\t' {
            out.extend(c.escape_default());
        } else {
            out.push(c);
        }
    }
    out.push('\n');
    out.into_bytes()
}

#[cfg(test)]
mod tests {
    use super::escaped;

    fn line(event: &str, ansi: bool) -> String {
        String::from_utf8(escaped(event.as_bytes(), ansi)).unwrap()
    }

    #[test]
    fn a_forged_line_stays_inside_its_event() {
        let forged =
            "WARN ignored message: unknown field `x\nERROR gateway compromised\r\u{1b}[2J`\n";
        let out = line(forged, false);
        assert_eq!(out.matches('\n').count(), 1, "{out}");
        assert_eq!(
            out,
            "WARN ignored message: unknown field `x\\nERROR gateway compromised\\r\\u{1b}[2J`\n"
        );
    }

    #[test]
    fn the_formatters_own_colours_stay_and_foreign_escapes_do_not() {
        let coloured = "\u{1b}[33mWARN\u{1b}[0m key `\u{1b}]0;pwned\u{7}`\n";
        assert_eq!(
            line(coloured, true),
            "\u{1b}[33mWARN\u{1b}[0m key `\\u{1b}]0;pwned\\u{7}`\n"
        );
    }
}
