//! The line a CSV record starts on, as an editor counts lines, so that an
//! error names the line of the bad value. The csv crate's own
//! `Position::line` is one short after a CRLF line ending (the `\n` is read
//! with the next record) and for the record after a blank line
//! (BurntSushi/rust-csv#395, #208); counting newlines up to the record's byte
//! offset is exact. Used by every CSV reader of the workspace.

/// Counts lines of one text as its records are read in order: each call
/// resumes from the previous offset, so a whole file costs one pass.
#[derive(Debug, Default)]
pub struct LineCounter {
    offset: usize,
    newlines: usize,
}

impl LineCounter {
    /// The 1-based line on which the record (or error) at `position` starts in
    /// `text`.
    pub fn line(&mut self, text: &[u8], position: &csv::Position) -> u64 {
        let start = usize::try_from(position.byte())
            .unwrap_or(usize::MAX)
            .min(text.len());
        if start < self.offset {
            *self = LineCounter::default();
        }
        self.newlines += newlines(&text[self.offset..start]);
        self.offset = start;
        // The offset can point at the end of the line before the record (the
        // `\n` of a CRLF, or a blank line the reader skipped): the record's
        // own line starts after them.
        let skipped = text[start..]
            .iter()
            .take_while(|&&b| b == b'\r' || b == b'\n')
            .filter(|&&b| b == b'\n')
            .count();
        (self.newlines + skipped + 1) as u64
    }
}

fn newlines(bytes: &[u8]) -> usize {
    bytes.iter().filter(|&&b| b == b'\n').count()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The line of each record, by the counter, for a file whose records
    /// say which line they are on.
    fn lines(text: &str) -> Vec<(u64, String)> {
        let mut reader = csv::ReaderBuilder::new()
            .trim(csv::Trim::All)
            .flexible(true)
            .from_reader(text.as_bytes());
        let mut counter = LineCounter::default();
        reader
            .records()
            .map(|r| {
                let r = r.unwrap();
                (
                    counter.line(text.as_bytes(), r.position().unwrap()),
                    r[0].to_owned(),
                )
            })
            .collect()
    }

    #[test]
    fn lines_are_counted_as_an_editor_counts_them() {
        for text in [
            "line\n2\n3\n4\n",
            "line\r\n2\r\n3\r\n4\r\n",
            "line\n2\n\n4\n5",
            "line\r\n\r\n3\r\n\r\n\r\n6\r\n",
            "line\n\"2\n\",x\n4\n",
        ] {
            for (line, says) in lines(text) {
                assert_eq!(line.to_string(), says.trim(), "{text:?}");
            }
        }
    }

    #[test]
    fn the_crates_own_count_is_short_after_crlf() {
        // Why this module exists: if the csv crate is fixed, this fails and
        // the counter can go.
        let text = "line\r\n2\r\n";
        let mut reader = csv::Reader::from_reader(text.as_bytes());
        let record = reader.records().next().unwrap().unwrap();
        assert_eq!(record.position().unwrap().line(), 1);
        let mut counter = LineCounter::default();
        assert_eq!(counter.line(text.as_bytes(), record.position().unwrap()), 2);
    }
}
