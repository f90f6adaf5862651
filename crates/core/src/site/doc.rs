//! A site file as data ([`SiteDoc`]), for the site editor, and the writer that
//! turns an edited document back into TOML ([`write_doc`]).
//!
//! The document is the file as written: obstacles and walls as drawn, not as
//! rasterised; beacons by `cell` or `pos` as given; keys that were absent stay
//! absent. It is validated only by writing it and loading the text with
//! [`Site::parse`](super::Site::parse), so the editor's errors are the very
//! ones `gangway check` prints.
//!
//! Writing preserves the file: given the text the document was opened from,
//! only what changed is rewritten (through `toml_edit`), so comments,
//! ordering and formatting of everything else survive, and a document saved
//! unchanged is the same bytes.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use toml_edit::{ArrayOfTables, DocumentMut, Item, Table, Value};
use uuid::Uuid;

use super::{Cell, LabelScheme, ReferencePoint, YAxis};
use crate::sighting::Mac;

/// Every key of a site file (`config/sites/README.md`), as plain data. Its
/// JSON form is the TOML's: `beacon` and `gateway` are the arrays of tables.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SiteDoc {
    pub name: String,
    pub cell_m: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub origin_m: Option<[f64; 2]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y_axis: Option<YAxis>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub map: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub width_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub height_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub floorplan: Option<FloorplanDoc>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub obstacles: Vec<ObstacleDoc>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub walls: Vec<WallDoc>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub labels: Option<LabelScheme>,
    #[serde(default, rename = "beacon", skip_serializing_if = "Vec::is_empty")]
    pub beacons: Vec<BeaconDoc>,
    #[serde(default, rename = "gateway", skip_serializing_if = "Vec::is_empty")]
    pub gateways: Vec<GatewayDoc>,
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub places: BTreeMap<String, Cell>,
}

/// `[floorplan]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FloorplanDoc {
    pub image: String,
    pub reference: Vec<ReferencePoint>,
}

/// One `[[obstacles]]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObstacleDoc {
    pub polygon: Vec<[f64; 2]>,
}

/// One `[[walls]]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WallDoc {
    pub line: Vec<[f64; 2]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub thickness_m: Option<f64>,
}

/// One `[[beacon]]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BeaconDoc {
    pub id: String,
    pub uuid: Uuid,
    pub major: u16,
    pub minor: u16,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cell: Option<Cell>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pos: Option<[f64; 2]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub height_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tx_power: Option<i8>,
    /// Where several transmitters share the UUID/major/minor, the one this is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mac: Option<Mac>,
    /// How loudly it is heard over the floor ([`crate::site::Beacon::heard_dbm`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub heard_dbm: Option<f64>,
}

/// One `[[gateway]]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GatewayDoc {
    pub id: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cell: Option<Cell>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pos: Option<[f64; 2]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub height_m: Option<f64>,
}

impl SiteDoc {
    /// The document of site TOML (not validated beyond its types: a
    /// document may be mid-edit).
    pub fn parse(text: &str) -> Result<SiteDoc, toml::de::Error> {
        toml::from_str(text)
    }
}

/// Writes `doc` as site TOML. With `original` (the text the document was
/// opened from), everything that did not change keeps its text, comments
/// included: keys are compared as data, arrays of tables entry by entry and
/// places name by name. Without it (or when it does not parse), a new file
/// in the order of `config/sites/README.md`.
pub fn write_doc(doc: &SiteDoc, original: Option<&str>) -> String {
    let opened = original.and_then(|text| {
        let old = SiteDoc::parse(text).ok()?;
        Some((text.parse::<DocumentMut>().ok()?, old))
    });
    let fresh = opened.is_none();
    let (mut out, old) = opened.unwrap_or_default();
    let old = (!fresh).then_some(&old);
    let mut w = Writer {
        out: &mut out,
        fresh,
    };
    w.value("name", old.map(|d| &d.name), Some(&doc.name));
    w.value("cell_m", old.map(|d| &d.cell_m), Some(&doc.cell_m));
    w.value(
        "origin_m",
        old.and_then(|d| d.origin_m.as_ref()),
        doc.origin_m.as_ref(),
    );
    w.value(
        "y_axis",
        old.and_then(|d| d.y_axis.as_ref()),
        doc.y_axis.as_ref(),
    );
    w.map(old.and_then(|d| d.map.as_deref()), doc.map.as_deref());
    w.value(
        "width_m",
        old.and_then(|d| d.width_m.as_ref()),
        doc.width_m.as_ref(),
    );
    w.value(
        "height_m",
        old.and_then(|d| d.height_m.as_ref()),
        doc.height_m.as_ref(),
    );
    w.table(
        "floorplan",
        old.and_then(|d| d.floorplan.as_ref()),
        doc.floorplan.as_ref(),
    );
    w.tables("obstacles", old.map(|d| &d.obstacles[..]), &doc.obstacles);
    w.tables("walls", old.map(|d| &d.walls[..]), &doc.walls);
    w.table(
        "labels",
        old.and_then(|d| d.labels.as_ref()),
        doc.labels.as_ref(),
    );
    w.tables("beacon", old.map(|d| &d.beacons[..]), &doc.beacons);
    w.tables("gateway", old.map(|d| &d.gateways[..]), &doc.gateways);
    w.places(old.map(|d| &d.places), &doc.places);
    out.to_string()
}

/// Applies the changes between two documents to the TOML document.
struct Writer<'a> {
    out: &'a mut DocumentMut,
    /// Writing a new file (no original text).
    fresh: bool,
}

impl Writer<'_> {
    /// A plain key: kept when unchanged, replaced in place, or removed.
    fn value<T: Serialize + PartialEq>(&mut self, key: &str, old: Option<&T>, new: Option<&T>) {
        if old == new && !self.fresh {
            return;
        }
        match new {
            None => {
                self.out.remove(key);
            }
            Some(v) => self.out[key] = Item::Value(value_of(v)),
        }
    }

    /// `map`, as a multi-line literal string like the hand-written files.
    fn map(&mut self, old: Option<&str>, new: Option<&str>) {
        if old == new && !self.fresh {
            return;
        }
        let Some(map) = new else {
            self.out.remove("map");
            return;
        };
        let mut text = map.trim_end_matches('\n').to_owned();
        text.push('\n');
        // A literal string cannot hold `'''`; such a map is invalid anyway,
        // and is then written escaped so the error names its glyph.
        let literal = format!("map = '''\n{text}'''\n");
        let item = match literal.parse::<DocumentMut>() {
            Ok(parsed) if !text.contains("'''") => parsed["map"].clone(),
            _ => Item::Value(Value::from(map)),
        };
        self.out["map"] = item;
    }

    /// A table such as `[labels]`: kept or rewritten whole.
    fn table<T: Serialize + PartialEq>(&mut self, key: &str, old: Option<&T>, new: Option<&T>) {
        if old == new && !self.fresh {
            return;
        }
        match new {
            None => {
                self.out.remove(key);
            }
            Some(v) => {
                let mut table = table_of(v);
                if !self.out.is_empty() {
                    table.decor_mut().set_prefix("\n");
                }
                self.out[key] = Item::Table(table);
            }
        }
    }

    /// An array of tables: entries equal to one of the original's (in
    /// order) keep its text; the others are written anew.
    fn tables<T: Serialize + PartialEq>(&mut self, key: &str, old: Option<&[T]>, new: &[T]) {
        let old = old.unwrap_or(&[]);
        if old == new && !self.fresh {
            return;
        }
        if new.is_empty() {
            self.out.remove(key);
            return;
        }
        let existing = self
            .out
            .get(key)
            .and_then(Item::as_array_of_tables)
            .filter(|a| a.len() == old.len())
            .cloned();
        let mut array = ArrayOfTables::new();
        let mut next = 0;
        for entry in new {
            let kept = existing.as_ref().and_then(|existing| {
                let j = next + old[next..].iter().position(|o| o == entry)?;
                next = j + 1;
                existing.get(j).cloned()
            });
            let table = kept.unwrap_or_else(|| {
                let mut table = table_of(entry);
                table.decor_mut().set_prefix("\n");
                table
            });
            array.push(table);
        }
        if self.out.is_empty()
            && let Some(first) = array.get_mut(0)
        {
            first.decor_mut().set_prefix("");
        }
        self.out[key] = Item::ArrayOfTables(array);
    }

    /// `[places]`: name by name, so each unchanged line (and its comment)
    /// stays where it was.
    fn places(&mut self, old: Option<&BTreeMap<String, Cell>>, new: &BTreeMap<String, Cell>) {
        let empty = BTreeMap::new();
        let old = old.unwrap_or(&empty);
        if old == new && !self.fresh {
            return;
        }
        if new.is_empty() {
            self.out.remove("places");
            return;
        }
        let prefixed = !self.out.is_empty();
        let table = self.out["places"].or_insert(Item::Table(Table::new()));
        let Some(table) = table.as_table_mut() else {
            // `places` written inline or dotted: rewrite it as a table.
            let mut fresh = Table::new();
            for (name, cell) in new {
                fresh.insert(name, Item::Value(value_of(cell)));
            }
            self.out["places"] = Item::Table(fresh);
            return;
        };
        if prefixed && table.is_empty() {
            table.decor_mut().set_prefix("\n");
        }
        table.retain(|name, _| new.contains_key(name));
        for (name, cell) in new {
            if old.get(name) != Some(cell) || !table.contains_key(name) {
                table.insert(name, Item::Value(value_of(cell)));
            }
        }
    }
}

/// A TOML value of plain data (numbers, strings, arrays, inline tables).
fn value_of<T: Serialize>(v: &T) -> Value {
    v.serialize(toml_edit::ser::ValueSerializer::new())
        .expect("site documents are plain data")
}

/// A table of a struct, one `key = value` line per field, in field order.
fn table_of<T: Serialize>(v: &T) -> Table {
    let mut table = Table::new();
    if let Value::InlineTable(inline) = value_of(v) {
        for (key, value) in inline.iter() {
            let mut value = value.clone();
            value.decor_mut().clear();
            table.insert(key, Item::Value(value));
        }
    }
    table.fmt();
    table
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::site::Site;
    use std::path::{Path, PathBuf};

    /// Every site file in the repository.
    fn site_files() -> Vec<PathBuf> {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let mut files = Vec::new();
        for dir in ["config/sites", "fixtures/sites"] {
            for entry in std::fs::read_dir(root.join(dir)).unwrap() {
                let path = entry.unwrap().path();
                let text = std::fs::read_to_string(&path).unwrap_or_default();
                if path.extension().is_some_and(|e| e == "toml") && SiteDoc::parse(&text).is_ok() {
                    files.push(path);
                }
            }
        }
        assert!(files.len() >= 3, "{files:?}");
        files
    }

    #[test]
    fn every_site_round_trips_unchanged() {
        for path in site_files() {
            let text = std::fs::read_to_string(&path).unwrap();
            let doc = SiteDoc::parse(&text).unwrap();
            assert_eq!(write_doc(&doc, Some(&text)), text, "{}", path.display());
        }
    }

    #[test]
    fn every_site_written_anew_loads_as_the_same_site() {
        for path in site_files() {
            let text = std::fs::read_to_string(&path).unwrap();
            let doc = SiteDoc::parse(&text).unwrap();
            let written = write_doc(&doc, None);
            assert_eq!(SiteDoc::parse(&written).unwrap(), doc, "{written}");
            let (a, b) = (
                Site::parse(&text, &path).unwrap(),
                Site::parse(&written, &path).unwrap(),
            );
            assert_eq!(a.map_hash(), b.map_hash(), "{}", path.display());
            assert_eq!(a.beacons, b.beacons);
            assert_eq!(a.places(), b.places());
            assert_eq!(a.floorplan(), b.floorplan());
        }
    }

    #[test]
    fn an_edit_rewrites_only_what_changed() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let text = std::fs::read_to_string(root.join("config/sites/waldo.toml")).unwrap();
        let mut doc = SiteDoc::parse(&text).unwrap();
        doc.beacons[2].cell = None;
        doc.beacons[2].pos = Some([14.5, 3.0]);
        doc.places.remove("printers");
        doc.places.insert("café <b>".into(), Cell::new(15, 14));
        doc.beacons.push(BeaconDoc {
            id: "b3014".into(),
            uuid: doc.beacons[0].uuid,
            major: 1,
            minor: 3014,
            cell: None,
            pos: Some([20.0, 0.5]),
            height_m: Some(2.5),
            tx_power: None,
            mac: Some("e0:78:a3:3d:b5:d6".parse().unwrap()),
            heard_dbm: Some(-81.25),
        });
        let written = write_doc(&doc, Some(&text));
        assert_eq!(SiteDoc::parse(&written).unwrap(), doc);
        let old: Vec<&str> = text.lines().collect();
        let new: Vec<&str> = written.lines().collect();
        // Everything before the third beacon is the same text, comments too.
        let third = old.iter().position(|l| l.contains("minor = 3003")).unwrap();
        assert_eq!(old[..third], new[..third]);
        assert!(written.contains("pos = [14.5, 3.0]"), "{written}");
        assert!(written.contains("cell = [9, 9]    # J10"), "{written}");
        assert!(!written.contains("printers"));
        assert!(written.contains("\"café <b>\" = [15, 14]"), "{written}");
        assert!(written.contains(
            "minor = 3014\npos = [20.0, 0.5]\nheight_m = 2.5\nmac = \"E0:78:A3:3D:B5:D6\""
        ));
        Site::parse(&written, Path::new("waldo.toml")).unwrap();
    }

    #[test]
    fn a_new_site_reads_like_a_hand_written_one() {
        let doc = SiteDoc {
            name: "new".into(),
            cell_m: 0.5,
            map: Some("##.\n###\n".into()),
            labels: Some(LabelScheme { first_row: 1 }),
            places: [("door".to_owned(), Cell::new(1, 1))].into(),
            walls: vec![WallDoc {
                line: vec![[0.0, 0.5], [1.0, 0.5]],
                thickness_m: None,
            }],
            ..SiteDoc::default()
        };
        let text = write_doc(&doc, None);
        assert_eq!(
            text,
            "name = \"new\"\ncell_m = 0.5\nmap = '''\n##.\n###\n'''\n\n[[walls]]\nline = \
             [[0.0, 0.5], [1.0, 0.5]]\n\n[labels]\nfirst_row = 1\n\n[places]\ndoor = [1, 1]\n"
        );
    }
}
