//! Each command's examples: shown after `gangway <command> --help` and as the
//! EXAMPLES section of its man page (`examples/deb_assets.rs`). One place for
//! all of them so a test can parse every line with the CLI itself: an example
//! whose flags drift from the code fails the test instead of misleading a user.
//!
//! Every example is one line, `gangway …` then two spaces, `# `, and what it
//! does; paths are the packaged ones (`/etc/gangway/…`) or a user's own files.

/// The heading both `--help` and the man page put above the lines.
pub const HEADING: &str = "Examples:";

pub(super) const GANGWAY: &str = "\
Examples:
  gangway check  # validate the config, its site and its models
  gangway run  # the daemon, as the systemd unit runs it
  gangway replay capture.btsnoop --device phone-1 --print  # what a recorded capture would publish
  gangway plan --from \"west entrance\" --to \"help desk\" --profile wheelchair  # one route";

pub(super) const RECORD: &str = "\
Examples:
  gangway record --out walk.btsnoop --duration 60  # 60 s of adverts; opens in Wireshark
  gangway record --out walk.jsonl --duration 60 --observer gw-lobby  # as JSON Lines, heard by gw-lobby";

pub(super) const REPLAY: &str = "\
Examples:
  gangway replay walk.jsonl --print  # one JSON line per location, route and guidance step
  gangway replay btsnoop_hci.log --device phone-1 --print  # an Android HCI snoop log
  gangway replay survey.csv --score --json  # accuracy against the positions the rows carry
  gangway replay capture.btsnoop --heard  # every iBeacon heard, and which ones the site lacks
  gangway replay walk.jsonl --speed 1 --web 127.0.0.1:8080  # in real time, on the live map";

pub(super) const SIMULATE: &str = "\
Examples:
  gangway simulate --site /etc/gangway/sites/waldo.toml --out sim.jsonl --walkers 5  # adverts, truth and requests
  gangway simulate --site /etc/gangway/sites/waldo.toml --trajectories --out walks.jsonl --seed 1  # walks to train on";

pub(super) const RUN: &str = "\
Examples:
  gangway run  # the daemon with the default config
  gangway run --config /etc/gangway/gangway.toml --mqtt-url mqtts://broker.example:8883  # another broker
  gangway run --replay walk.jsonl --speed 1  # a capture instead of the radio, no broker needed";

pub(super) const CALIBRATE: &str = "\
Examples:
  gangway calibrate --from scans.csv --out /etc/gangway/sites/site-calibration.toml  # per-beacon radio models
  gangway calibrate --from a.btsnoop b.btsnoop --out calibration.toml --cells  # and a per-cell radio map";

pub(super) const CHECK: &str = "\
Examples:
  gangway check  # the default config
  GANGWAY_CONFIG=/etc/gangway/test.toml gangway check  # another config
  gangway check --site mall.toml  # a site or building file alone, with the default settings";

pub(super) const PLAN: &str = "\
Examples:
  gangway plan --from \"west entrance\" --to \"help desk\"  # with the config's planner
  gangway plan --from 3,4 --to 20,7 --profile wheelchair --json  # between cells, as JSON
  gangway plan --site site.toml --models trained --mode desire --from 3,4 --to 20,7 --svg route.svg  # a trained directory";

pub(super) const TRAIN: &str = "\
Examples:
  gangway train --site site.toml --trajectories walks.jsonl --out trained  # the site's path models
  gangway train --site site.toml --survey survey.csv --out trained  # the localization cell classifier";

pub(super) const EVAL: &str = "\
Examples:
  gangway eval localization --site site.toml --survey survey.csv --json  # accuracy on a labelled survey
  gangway eval planning --json  # every planner mode on the config's site
  gangway eval guidance --trips 50 --json  # simulated walkers guided along routes";

pub(super) const WALKS: &str = "\
Examples:
  gangway walks site --name concourse --cell-m 0.5 --walks obsmat.txt --out concourse.toml  # a site from walks
  gangway walks import --site concourse.toml --from obsmat.txt --train train.jsonl --heldout heldout.jsonl  # walks onto it";

pub(super) const SITE: &str = "\
Examples:
  gangway site edit --site site.toml --image plan.png  # edit over the floor plan at http://127.0.0.1:8080
  gangway site import --geojson site1 --out mall/mall.toml  # one site per floor folder and the building file";

pub(super) const SURVEY: &str = "\
Examples:
  gangway survey import --floor-dir site1/F1 --out f1  # f1/site.toml, f1/survey.csv and the floor image
  gangway survey import --floor-dir site1/B1 --out b1 --cell-m 0.5 --max-gap-s 20 --json  # finer cells, stricter gaps";

/// Every command's examples with the command's name (`""` for `gangway`
/// itself).
#[cfg(test)]
const ALL: [(&str, &str); 13] = [
    ("", GANGWAY),
    ("record", RECORD),
    ("replay", REPLAY),
    ("simulate", SIMULATE),
    ("run", RUN),
    ("calibrate", CALIBRATE),
    ("check", CHECK),
    ("plan", PLAN),
    ("train", TRAIN),
    ("eval", EVAL),
    ("walks", WALKS),
    ("site", SITE),
    ("survey", SURVEY),
];

/// The command lines of `examples`: each line's words after any `VAR=value`
/// prefix and before its `#` comment, with double quotes grouping words.
#[cfg(test)]
fn command_lines(examples: &str) -> Vec<Vec<String>> {
    examples
        .lines()
        .skip(1)
        .map(|line| {
            let command = line.split("  #").next().unwrap_or(line).trim();
            let mut words = Vec::new();
            let mut word = String::new();
            let mut quoted = false;
            for c in command.chars() {
                match c {
                    '"' => quoted = !quoted,
                    ' ' if !quoted => {
                        if !word.is_empty() {
                            words.push(std::mem::take(&mut word));
                        }
                    }
                    _ => word.push(c),
                }
            }
            words.push(word);
            // `VAR=value gangway …`: the environment, not an argument.
            let command = words.iter().position(|w| w == "gangway").unwrap_or(0);
            words.split_off(command)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;
    use crate::cli::Cli;

    #[test]
    fn every_example_parses_with_the_cli_it_documents() {
        let mut lines = 0;
        for (command, examples) in ALL {
            assert!(examples.starts_with(HEADING), "{command}: {examples}");
            for words in command_lines(examples) {
                assert_eq!(words[0], "gangway", "{command}: {words:?}");
                if !command.is_empty() {
                    assert_eq!(words[1], command, "{command}'s examples run {words:?}");
                }
                if let Err(e) = Cli::try_parse_from(&words) {
                    panic!("{words:?} does not parse: {e}");
                }
                lines += 1;
            }
        }
        assert!(lines >= 2 * ALL.len(), "{lines} examples");
    }

    #[test]
    fn a_drifted_flag_is_caught() {
        let words = &command_lines("Examples:\n  gangway run --no-such-flag  # x")[0];
        assert_eq!(words, &["gangway", "run", "--no-such-flag"]);
        assert!(Cli::try_parse_from(words).is_err());
    }
}
