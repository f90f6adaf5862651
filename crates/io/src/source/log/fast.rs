//! The advert line read by hand: the one line shape that is nearly all of a
//! replay, exactly as [`super::LogWriter`] writes it.
//!
//! Written by hand because it is faster. Replaying to mosquitto (the
//! `throughput` example under `perf record`), reading advert lines with
//! `serde_json` took a quarter of the gateway's CPU samples (25%, with the
//! uuid parse), and this path 12%: a replay costs a fifth less CPU
//! (BENCHMARKS.md, "Replay throughput"). `sonic-rs` was slower. It is an exact
//! matcher, not a JSON parser: the keys in the writer's order, no whitespace,
//! no escapes, numbers in the plain forms the writer prints. Anything else
//! (another line type, another order, an unknown field, a number out of
//! range) returns `None` and the line goes to `serde_json`, so every other
//! line and every error message stay as `serde_json` makes them. What it
//! accepts it reads to the same [`Line`] as `serde_json`:
//!
//! - integers in JSON's grammar (no `+`, no leading zeros), parsed by std
//!   into the field's type, so out of range is `None` as it is an error there;
//! - `t` with at most [`MAX_T_DIGITS`] digits and no exponent: its
//!   significand and power of ten are then exact in an `f64`, so std's
//!   correctly rounded parse and `serde_json`'s (with or without its
//!   `float_roundtrip` feature, which only dev-dependencies turn on) give the
//!   same bits; an integer `t` is read as an integer and converted, as
//!   `serde_json` does (so `-0` is `0.0`);
//! - strings without a backslash or a control character (with those,
//!   `serde_json` unescapes or rejects); the uuid through [`Uuid`]'s `FromStr`,
//!   which is what its `Deserialize` calls.

use std::borrow::Cow;
use std::str::FromStr;

use uuid::Uuid;

use super::{Kind, Line, Text};
use crate::sighting::Mac;

/// Most digits of a `t` read here; a longer one goes to `serde_json`. 15
/// digits keep the significand below 2⁵³ and the power of ten at most 10¹⁴.
const MAX_T_DIGITS: usize = 15;

/// The advert line as the writer emits it, or `None` for `serde_json` to read.
pub(super) fn advert(line: &str) -> Option<Line<'_>> {
    let mut s = Scan(line);
    s.literal(r#"{"type":"advert","t":"#)?;
    let t = s.seconds()?;
    s.literal(r#","observer":""#)?;
    let observer = s.string()?;
    s.literal(r#","uuid":""#)?;
    let uuid = Uuid::from_str(s.string()?).ok()?;
    s.literal(r#","major":"#)?;
    let major = s.integer()?;
    s.literal(r#","minor":"#)?;
    let minor = s.integer()?;
    s.literal(r#","rssi":"#)?;
    let rssi = s.integer()?;
    let tx_power = if s.literal(r#","tx_power":"#).is_some() {
        Some(s.integer()?)
    } else {
        None
    };
    let mac = if s.literal(r#","mac":""#).is_some() {
        Some(Mac::from_str(s.string()?).ok()?)
    } else {
        None
    };
    s.literal("}")?;
    if !s.0.is_empty() {
        return None;
    }
    Some(Line {
        observer: Some(Text(Cow::Borrowed(observer))),
        uuid: Some(uuid),
        major: Some(major),
        minor: Some(minor),
        rssi: Some(rssi),
        tx_power,
        mac,
        ..Line::new(Kind::Advert, t)
    })
}

/// The rest of the line.
struct Scan<'a>(&'a str);

impl<'a> Scan<'a> {
    fn literal(&mut self, text: &str) -> Option<()> {
        self.0 = self.0.strip_prefix(text)?;
        Some(())
    }

    /// The bytes up to the first one `part` rejects.
    fn take(&mut self, part: impl Fn(u8) -> bool) -> &'a str {
        let end = self
            .0
            .bytes()
            .position(|b| !part(b))
            .unwrap_or(self.0.len());
        let (taken, rest) = self.0.split_at(end);
        self.0 = rest;
        taken
    }

    /// A string's contents after its opening quote, and its closing quote.
    fn string(&mut self) -> Option<&'a str> {
        let text = self.take(|b| b != b'"' && b != b'\\' && b >= 0x20);
        self.literal("\"")?;
        Some(text)
    }

    fn integer<T: FromStr>(&mut self) -> Option<T> {
        let text = self.take(|b| b.is_ascii_digit() || b == b'-');
        json_integer(text)?;
        text.parse().ok()
    }

    fn seconds(&mut self) -> Option<f64> {
        let text = self.take(|b| b.is_ascii_digit() || b == b'-' || b == b'.');
        let (whole, fraction) = match text.split_once('.') {
            Some((whole, fraction)) => (whole, Some(fraction)),
            None => (text, None),
        };
        let digits = json_integer(whole)?;
        match fraction {
            None if digits <= MAX_T_DIGITS => text.parse::<i64>().ok().map(|t| t as f64),
            Some(f)
                if !f.is_empty()
                    && f.bytes().all(|b| b.is_ascii_digit())
                    && digits + f.len() <= MAX_T_DIGITS =>
            {
                text.parse().ok()
            }
            _ => None,
        }
    }
}

/// The number of digits of an integer in JSON's grammar (`-?(0|[1-9][0-9]*)`).
fn json_integer(text: &str) -> Option<usize> {
    let digits = text.strip_prefix('-').unwrap_or(text);
    let plain = !digits.is_empty()
        && digits.bytes().all(|b| b.is_ascii_digit())
        && (digits == "0" || !digits.starts_with('0'));
    plain.then_some(digits.len())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The line as `serde_json` reads it, written back: equal texts are
    /// equal lines, bit for bit (`ryu` prints `-0.0` and `0.0` apart).
    fn by_serde(line: &str) -> Option<String> {
        let line: Line = serde_json::from_str(line).ok()?;
        Some(serde_json::to_string(&line).unwrap())
    }

    fn by_hand(line: &str) -> Option<String> {
        advert(line).map(|line| serde_json::to_string(&line).unwrap())
    }

    const WRITTEN: &str = r#"{"type":"advert","t":1767225600.097,"observer":"walker-01","uuid":"5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84","major":1,"minor":3003,"rssi":-67,"tx_power":-59}"#;

    #[test]
    fn reads_what_the_writer_writes() {
        let macs = [None, Some(Mac([0xE0, 0x78, 0xA3, 0x3D, 0xB5, 0xD6]))];
        for (tx_power, advertiser_mac) in [Some(-59), None].into_iter().zip(macs) {
            let event = crate::event::Event::Advert(crate::sighting::Sighting {
                advertiser_mac,
                t: 1767225600.097,
                observer: "walker-01".into(),
                advertiser: crate::sighting::BeaconId {
                    uuid: Uuid::from_str("5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84").unwrap(),
                    major: 1,
                    minor: 3003,
                },
                tx_power,
                rssi: -67,
            });
            let mut out = Vec::new();
            super::super::LogWriter::new(&mut out)
                .write(&event)
                .unwrap();
            let line = std::str::from_utf8(&out).unwrap().trim_end();
            assert!(by_hand(line).is_some(), "{line}");
            assert_eq!(by_hand(line), by_serde(line));
        }
        assert_eq!(by_hand(WRITTEN), by_serde(WRITTEN));
    }

    #[test]
    fn leaves_every_other_shape_to_serde_json() {
        let cases = [
            (r#"{"type":"advert","t":"#, r#"{"t":"#), // other key order
            (r#""t":"#, r#""t": "#),                  // whitespace
            ("walker-01", r"walker\u002d01"),         // escape
            ("walker-01", "walker\t01"),              // control character
            (r#""major":1"#, r#""major":65536"#),     // out of range
            (r#""major":1"#, r#""major":-1"#),
            (r#""major":1"#, r#""major":01"#), // leading zero
            (r#""major":1"#, r#""major":+1"#),
            (r#""major":1"#, r#""major":1.0"#), // other type
            (r#""major":1"#, r#""major":"1""#),
            (r#""rssi":-67"#, r#""rssi":-32769"#),
            (r#""rssi":-67"#, r#""rssi":--67"#),
            (r#""tx_power":-59"#, r#""tx_power":-129"#),
            (r#""tx_power":-59"#, r#""tx_power":null"#),
            ("1767225600.097", "1767225600.0970001"), // too many digits
            ("1767225600.097", "1.767225600097e9"),   // exponent
            ("1767225600.097", "1767225600."),
            ("1767225600.097", ".097"),
            ("1767225600.097", "01767225600.097"),
            ("1767225600.097", "\"1767225600.097\""),
            ("9e84", "9e8"),                                           // not a uuid
            (r#""tx_power":-59}"#, r#""tx_power":-59,"device":"p"}"#), // extra field
            (r#""tx_power":-59}"#, r#""tx_power":-59}}"#),
            (r#""tx_power":-59}"#, r#""tx_power":-59,"mac":"E0:78"}"#), // not a MAC
            (r#""tx_power":-59}"#, r#""tx_power":-59"#),                // cut short
            (r#""type":"advert""#, r#""type":"truth""#),
        ];
        for (from, to) in cases {
            assert!(WRITTEN.contains(from), "{from}");
            let line = WRITTEN.replacen(from, to, 1);
            assert_eq!(advert(&line).map(|_| ()), None, "{line}");
        }
    }

    /// A `t` as the writer prints it, or in a form it does not.
    fn t_text() -> impl Strategy<Value = String> {
        prop_oneof![
            (0u64..4_000_000_000_000)
                .prop_map(|ms| serde_json::to_string(&(ms as f64 / 1e3)).unwrap()),
            any::<f64>().prop_map(|t| serde_json::to_string(&t).unwrap()),
            "-?[0-9]{1,17}(\\.[0-9]{0,9})?([eE][-+]?[0-9]{1,3})?",
        ]
    }

    /// An observer, written as JSON: plain, or needing escapes.
    fn observer_text() -> impl Strategy<Value = String> {
        prop_oneof![
            "[a-z0-9-]{1,12}".prop_map(|o| format!("\"{o}\"")),
            any::<String>().prop_map(|o| serde_json::to_string(&o).unwrap()),
            "[a-z\\\\\"/\u{1}é]{0,6}".prop_map(|o| format!("\"{o}\"")),
        ]
    }

    fn line(
        t: &str,
        observer: &str,
        uuid: u128,
        (major, minor, rssi): (i64, i64, i64),
        tx_power: Option<i64>,
    ) -> String {
        let uuid = Uuid::from_u128(uuid);
        let tx_power = tx_power.map_or(String::new(), |p| format!(r#","tx_power":{p}"#));
        format!(
            r#"{{"type":"advert","t":{t},"observer":{observer},"uuid":"{uuid}","major":{major},"minor":{minor},"rssi":{rssi}{tx_power}}}"#
        )
    }

    proptest! {
        #[test]
        fn reads_a_line_as_serde_json_does_or_not_at_all(
            t in t_text(),
            observer in observer_text(),
            uuid in any::<u128>(),
            numbers in (-70_000i64..70_000, -70_000i64..70_000, -40_000i64..40_000),
            tx_power in proptest::option::of(-300i64..300),
        ) {
            let line = line(&t, &observer, uuid, numbers, tx_power);
            if let Some(by_hand) = by_hand(&line) {
                prop_assert_eq!(Some(by_hand), by_serde(&line), "{}", line);
            }
        }

        #[test]
        fn reads_every_line_the_writer_writes(
            ms in 0u64..4_000_000_000_000,
            observer in "[a-z0-9-]{1,12}",
            uuid in any::<u128>(),
            numbers in (0i64..=65_535, 0i64..=65_535, -32_768i64..=32_767),
            tx_power in proptest::option::of(-128i64..=127),
        ) {
            let t = serde_json::to_string(&(ms as f64 / 1e3)).unwrap();
            let line = line(&t, &format!("\"{observer}\""), uuid, numbers, tx_power);
            prop_assert!(by_hand(&line).is_some(), "{}", line);
            prop_assert_eq!(by_hand(&line), by_serde(&line));
        }
    }
}
