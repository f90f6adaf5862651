//! The crowd-sourced learning store: what the gateway saw people walk (each
//! device's smoothed trajectory, i.e. the tracker's fixes), the routes it gave,
//! the feedback on them and how guided walks followed them (adherence, the
//! implicit feedback of [`crate::guide`]; the walk is the device's fixes over
//! the session's time, the route the one of its request), in an embedded SQLite file (rusqlite, bundled, so
//! nothing is installed) in the state directory, with bounded retention.
//!
//! The daemon writes through [`Store::write`]; training reads through
//! [`Store::trajectories`] and [`Store::routes`] (`gangway train --from-store`),
//! recalibration of the radio model through [`Store::heard`] (what each device
//! heard per fingerprint window, [`crate::locate::recalibrate`]).
//!
//! What goes in comes from the air and the broker, so the store is bounded in
//! rows and bytes, in total and per device ([`Store::enforce_quotas`]), and a
//! file that cannot be opened (corrupt, truncated, of another version) never
//! stops the gateway: [`Store::open_or_move_aside`] keeps it for inspection
//! and starts a fresh one. Files are created readable by their owner only.

use std::path::{Path, PathBuf};

use rusqlite::{Connection, OpenFlags, params};
use serde::Deserialize;

use crate::guide::{Adherence, Ending};
use crate::locate::recalibrate::Heard;
use crate::site::Cell;

/// Bumped when the tables change; a file of another version is refused,
/// but for the versions before floors ([`FLOORLESS_VERSION`],
/// [`FLOORLESS_ROUTES_VERSION`], [`FLOORLESS_HEARD_VERSION`]).
const SCHEMA_VERSION: i64 = 4;

/// The version before fixes named their floor: opened for writing it is
/// upgraded in place (its fixes and routes keep no floor), and read as it is.
const FLOORLESS_VERSION: i64 = 1;

/// The version before routes named their floor (a route across floors is
/// recorded as a route per floor since): upgraded and read as version 1 is.
const FLOORLESS_ROUTES_VERSION: i64 = 2;

/// The version before heard windows named their floor (a building's floors
/// are recalibrated each from its own windows since): upgraded and read as
/// version 1 is.
const FLOORLESS_HEARD_VERSION: i64 = 3;

/// Every version this one reads.
const READABLE: [i64; 4] = [
    SCHEMA_VERSION,
    FLOORLESS_HEARD_VERSION,
    FLOORLESS_ROUTES_VERSION,
    FLOORLESS_VERSION,
];

/// `[store]` in the gateway config.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StoreConfig {
    /// Record trajectories, routes and feedback.
    pub enabled: bool,
    /// The SQLite file; by default `learning.sqlite` in systemd's
    /// `$STATE_DIRECTORY`, else in the working directory.
    pub path: Option<PathBuf>,
    /// Rows older than this are deleted.
    pub retention_days: f64,
    /// At most this many fixes are kept (the oldest go first).
    pub max_fixes: u64,
    /// At most this many rows in all tables together (the oldest go first).
    pub max_rows: u64,
    /// At most this many rows of one device in each table.
    pub max_rows_per_device: u64,
    /// At most this many bytes of pages in use (the oldest rows go first).
    pub max_bytes: u64,
}

impl Default for StoreConfig {
    fn default() -> Self {
        StoreConfig {
            enabled: false,
            path: None,
            retention_days: 30.0,
            max_fixes: 2_000_000,
            max_rows: 3_000_000,
            max_rows_per_device: 200_000,
            max_bytes: 512 << 20,
        }
    }
}

impl StoreConfig {
    pub(crate) fn validate(&self) -> Result<(), String> {
        if !(self.retention_days > 0.0 && self.retention_days.is_finite()) {
            return Err("[store] `retention_days` must be a positive number of days".into());
        }
        if self.max_fixes == 0
            || self.max_rows == 0
            || self.max_rows_per_device == 0
            || self.max_bytes == 0
        {
            return Err(
                "[store] `max_fixes`, `max_rows`, `max_rows_per_device` and `max_bytes` must be positive"
                    .into(),
            );
        }
        Ok(())
    }

    /// Where the store lives.
    pub fn resolved_path(&self) -> PathBuf {
        self.path.clone().unwrap_or_else(|| {
            std::env::var_os("STATE_DIRECTORY")
                .map(PathBuf::from)
                .unwrap_or_default()
                .join("learning.sqlite")
        })
    }
}

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{}: {source}", path.display())]
    Sqlite {
        path: PathBuf,
        source: rusqlite::Error,
    },
    #[error(
        "{}: store schema version {found}, this gangway reads version {SCHEMA_VERSION}; \
         move the file away to start a new store",
        path.display()
    )]
    Version { path: PathBuf, found: i64 },
    #[error("{}: the integrity check failed: {found}", path.display())]
    Corrupt { path: PathBuf, found: String },
    #[error("{}: cannot create the store: {source}", path.display())]
    Create {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// One thing worth learning from.
#[derive(Clone, Debug, PartialEq)]
pub enum Record {
    Fix {
        device: String,
        t: f64,
        /// The floor's name (a one-floor site's is the site's); the cell is
        /// on that floor's grid.
        floor: Option<String>,
        cell: Cell,
        confidence: f32,
    },
    /// A route given, or one floor's leg of a route across floors (its
    /// floor named; the cells are on that floor's grid).
    Route {
        device: String,
        request_id: Option<String>,
        t: f64,
        floor: Option<String>,
        planner: String,
        cells: Vec<Cell>,
    },
    Feedback {
        device: String,
        request_id: String,
        t: f64,
        score: u8,
    },
    Adherence(Adherence),
    /// One fingerprint window: the anchors a device heard (by id) and how
    /// loud, for recalibrating the radio model; on a building, of the floor
    /// named.
    Heard {
        device: String,
        t: f64,
        floor: Option<String>,
        readings: Vec<(String, f32)>,
    },
}

/// A device's walk: fixes in time order on one floor, without a gap longer
/// than asked for.
#[derive(Clone, Debug, PartialEq)]
pub struct Trajectory {
    pub device: String,
    /// `None` for fixes recorded before the store kept floors.
    pub floor: Option<String>,
    pub points: Vec<(f64, Cell)>,
}

/// A route the gateway gave, with the mean feedback score when there was any.
#[derive(Clone, Debug, PartialEq)]
pub struct RecordedRoute {
    pub device: String,
    pub request_id: Option<String>,
    pub t: f64,
    /// The floor of a leg of a route across floors; `None` for a one-floor
    /// site's routes, and those recorded before routes kept floors.
    pub floor: Option<String>,
    pub planner: String,
    pub cells: Vec<Cell>,
    pub score: Option<f64>,
    /// Mean adherence score ([`Adherence::score`]) of the sessions that
    /// followed it.
    pub adherence: Option<f64>,
}

pub struct Store {
    conn: Connection,
    path: PathBuf,
    /// The file's schema version: [`SCHEMA_VERSION`], or one before it
    /// ([`READABLE`]) for a file opened read-only.
    version: i64,
}

/// The tables, each with its time column `t` and `device`.
const TABLES: [&str; 5] = ["fixes", "routes", "feedback", "adherence", "heard"];

impl Store {
    /// Opens (creating if needed, readable by its owner only) a store for
    /// writing, after SQLite's quick integrity check.
    pub fn open(path: &Path) -> Result<Store, StoreError> {
        create_private(path)?;
        let conn = Connection::open(path).map_err(|e| sql(path, e))?;
        let mut store = Store {
            conn,
            path: path.to_owned(),
            version: SCHEMA_VERSION,
        };
        store.init()?;
        let check: String = store
            .conn
            .query_row("PRAGMA quick_check(1)", [], |r| r.get(0))
            .map_err(|e| sql(path, e))?;
        if check != "ok" {
            return Err(StoreError::Corrupt {
                path: path.to_owned(),
                found: check,
            });
        }
        Ok(store)
    }

    /// [`Store::open`], and when that fails (a corrupt or truncated file, one
    /// of another version), the file is moved aside to
    /// `<name>.broken-<unix time>` (with its WAL files) and a fresh store is
    /// started. Returns the store and, when it had to, what happened.
    pub(crate) fn open_or_move_aside(path: &Path) -> Result<(Store, Option<String>), StoreError> {
        let error = match Store::open(path) {
            Ok(store) => return Ok((store, None)),
            Err(e) => e,
        };
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        let mut aside = path.as_os_str().to_owned();
        aside.push(format!(".broken-{stamp}"));
        let aside = PathBuf::from(aside);
        std::fs::rename(path, &aside).map_err(|source| StoreError::Create {
            path: path.to_owned(),
            source,
        })?;
        for suffix in ["-wal", "-shm"] {
            let mut from = path.as_os_str().to_owned();
            from.push(suffix);
            let mut to = aside.as_os_str().to_owned();
            to.push(suffix);
            // Absent unless the last writer died: nothing to keep then.
            let _ = std::fs::rename(&from, &to);
        }
        let store = Store::open(path)?;
        Ok((
            store,
            Some(format!(
                "[store] {error}; moved it aside to {} and started a fresh store",
                aside.display()
            )),
        ))
    }

    /// Opens an existing store read-only (training while the daemon writes).
    pub fn open_read_only(path: &Path) -> Result<Store, StoreError> {
        let conn = Connection::open_with_flags(path, OpenFlags::SQLITE_OPEN_READ_ONLY)
            .map_err(|e| sql(path, e))?;
        let mut store = Store {
            conn,
            path: path.to_owned(),
            version: SCHEMA_VERSION,
        };
        store.version = store.check_version(&READABLE)?;
        Ok(store)
    }

    fn init(&mut self) -> Result<(), StoreError> {
        // WAL lets a trainer read while the daemon writes; NORMAL sync is
        // durable across process crashes, which is what a learning log needs.
        self.conn
            .execute_batch(
                "PRAGMA journal_mode = WAL;
                 PRAGMA synchronous = NORMAL;
                 CREATE TABLE IF NOT EXISTS fixes (
                     device TEXT NOT NULL, t REAL NOT NULL,
                     x INTEGER NOT NULL, y INTEGER NOT NULL, confidence REAL NOT NULL,
                     floor TEXT);
                 CREATE INDEX IF NOT EXISTS fixes_by_device ON fixes (device, t);
                 CREATE INDEX IF NOT EXISTS fixes_by_time ON fixes (t);
                 CREATE TABLE IF NOT EXISTS routes (
                     device TEXT NOT NULL, request_id TEXT, t REAL NOT NULL,
                     planner TEXT NOT NULL, cells TEXT NOT NULL, floor TEXT);
                 CREATE INDEX IF NOT EXISTS routes_by_request ON routes (device, request_id);
                 CREATE TABLE IF NOT EXISTS feedback (
                     device TEXT NOT NULL, request_id TEXT NOT NULL, t REAL NOT NULL,
                     score INTEGER NOT NULL);
                 CREATE TABLE IF NOT EXISTS adherence (
                     device TEXT NOT NULL, request_id TEXT, started_t REAL NOT NULL,
                     t REAL NOT NULL, ending TEXT NOT NULL, in_corridor_share REAL NOT NULL,
                     detours INTEGER NOT NULL, arrived INTEGER NOT NULL,
                     expected_s REAL NOT NULL, taken_s REAL NOT NULL);
                 CREATE INDEX IF NOT EXISTS adherence_by_device ON adherence (device, t);
                 CREATE TABLE IF NOT EXISTS heard (
                     device TEXT NOT NULL, t REAL NOT NULL, readings TEXT NOT NULL,
                     floor TEXT);
                 CREATE INDEX IF NOT EXISTS heard_by_time ON heard (t);",
            )
            .map_err(|e| sql(&self.path, e))?;
        let version: i64 = self
            .conn
            .query_row("PRAGMA user_version", [], |r| r.get(0))
            .map_err(|e| sql(&self.path, e))?;
        if ![
            0,
            FLOORLESS_VERSION,
            FLOORLESS_ROUTES_VERSION,
            FLOORLESS_HEARD_VERSION,
        ]
        .contains(&version)
        {
            return self.check_version(&[SCHEMA_VERSION]).map(drop);
        }
        // A file from before floors: what it recorded stays, its fixes,
        // routes and heard windows keep no floor. (A table the statements
        // above just made has the column already.)
        let mut upgrade = String::new();
        for table in ["fixes", "routes", "heard"] {
            let has_floor: bool = self
                .conn
                .query_row(
                    "SELECT COUNT(*) > 0 FROM pragma_table_info(?1) WHERE name = 'floor'",
                    [table],
                    |r| r.get(0),
                )
                .map_err(|e| sql(&self.path, e))?;
            if !has_floor {
                upgrade += &format!("ALTER TABLE {table} ADD COLUMN floor TEXT; ");
            }
        }
        self.conn
            .execute_batch(&format!(
                "BEGIN; {upgrade}PRAGMA user_version = {SCHEMA_VERSION}; COMMIT;"
            ))
            .map_err(|e| sql(&self.path, e))?;
        self.check_version(&[SCHEMA_VERSION]).map(drop)
    }

    /// The name of a table's `floor` column in this file, or `NULL` for a
    /// file (opened read-only) of `floorless`, the version before the table
    /// had one, or older.
    fn floor_column(&self, floorless: i64) -> &'static str {
        if self.version > floorless {
            "floor"
        } else {
            "NULL"
        }
    }

    /// The file's schema version, if it is one of `readable`.
    fn check_version(&self, readable: &[i64]) -> Result<i64, StoreError> {
        let found: i64 = self
            .conn
            .query_row("PRAGMA user_version", [], |r| r.get(0))
            .map_err(|e| sql(&self.path, e))?;
        if !readable.contains(&found) {
            return Err(StoreError::Version {
                path: self.path.clone(),
                found,
            });
        }
        Ok(found)
    }

    /// Writes records in one transaction.
    pub fn write(&mut self, records: &[Record]) -> Result<(), StoreError> {
        let path = self.path.clone();
        let tx = self.conn.transaction().map_err(|e| sql(&path, e))?;
        for record in records {
            let done = match record {
                Record::Fix {
                    device,
                    t,
                    floor,
                    cell,
                    confidence,
                } => tx.execute(
                    "INSERT INTO fixes (device, t, x, y, confidence, floor) \
                     VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
                    params![device, t, cell.x, cell.y, confidence, floor],
                ),
                Record::Route {
                    device,
                    request_id,
                    t,
                    floor,
                    planner,
                    cells,
                } => tx.execute(
                    "INSERT INTO routes (device, request_id, t, planner, cells, floor) \
                     VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
                    params![
                        device,
                        request_id,
                        t,
                        planner,
                        serde_json::to_string(cells).expect("cells serialize"),
                        floor
                    ],
                ),
                Record::Feedback {
                    device,
                    request_id,
                    t,
                    score,
                } => tx.execute(
                    "INSERT INTO feedback (device, request_id, t, score) VALUES (?1, ?2, ?3, ?4)",
                    params![device, request_id, t, score],
                ),
                Record::Adherence(a) => tx.execute(
                    "INSERT INTO adherence (device, request_id, started_t, t, ending, \
                     in_corridor_share, detours, arrived, expected_s, taken_s) \
                     VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10)",
                    params![
                        a.device,
                        a.request_id,
                        a.started_t,
                        a.t,
                        a.ending.name(),
                        a.in_corridor_share,
                        a.detours,
                        a.arrived,
                        a.expected_s,
                        a.taken_s
                    ],
                ),
                Record::Heard {
                    device,
                    t,
                    floor,
                    readings,
                } => tx.execute(
                    "INSERT INTO heard (device, t, readings, floor) VALUES (?1, ?2, ?3, ?4)",
                    params![
                        device,
                        t,
                        serde_json::to_string(readings).expect("readings serialize"),
                        floor
                    ],
                ),
            };
            done.map_err(|e| sql(&path, e))?;
        }
        tx.commit().map_err(|e| sql(&path, e))
    }

    /// Deletes rows older than `now - retention_s`, and the oldest fixes past
    /// `max_fixes`. Returns the number of rows deleted.
    pub(crate) fn prune(
        &mut self,
        now: f64,
        retention_s: f64,
        max_fixes: u64,
    ) -> Result<usize, StoreError> {
        let cutoff = now - retention_s;
        let mut deleted = 0;
        for table in TABLES {
            deleted += self
                .conn
                .execute(&format!("DELETE FROM {table} WHERE t < ?1"), [cutoff])
                .map_err(|e| sql(&self.path, e))?;
        }
        deleted += self
            .conn
            .execute(
                "DELETE FROM fixes WHERE rowid IN (SELECT rowid FROM fixes ORDER BY t DESC LIMIT -1 OFFSET ?1)",
                [i64::try_from(max_fixes).unwrap_or(i64::MAX)],
            )
            .map_err(|e| sql(&self.path, e))?;
        Ok(deleted)
    }

    /// Keeps the store within `config`'s quotas: each device's rows per
    /// table, all rows, and the bytes of pages in use; the oldest rows go
    /// first. Returns the number of rows deleted.
    pub(crate) fn enforce_quotas(&mut self, config: &StoreConfig) -> Result<usize, StoreError> {
        let path = self.path.clone();
        let err = |e| sql(&path, e);
        let per_device = i64::try_from(config.max_rows_per_device).unwrap_or(i64::MAX);
        let mut deleted = 0;
        for table in TABLES {
            let over: Vec<String> = self
                .conn
                .prepare(&format!(
                    "SELECT device FROM {table} GROUP BY device HAVING COUNT(*) > ?1"
                ))
                .and_then(|mut stmt| {
                    stmt.query_map([per_device], |r| r.get(0))?
                        .collect::<Result<_, _>>()
                })
                .map_err(err)?;
            for device in over {
                deleted += self
                    .conn
                    .execute(
                        &format!(
                            "DELETE FROM {table} WHERE rowid IN (SELECT rowid FROM {table} \
                             WHERE device = ?1 ORDER BY t DESC LIMIT -1 OFFSET ?2)"
                        ),
                        params![device, per_device],
                    )
                    .map_err(err)?;
            }
        }
        // Past the total, or the bytes: the oldest tenth of the largest
        // table goes, until both hold (bounded, so a quota far too small
        // for the rows cannot spin).
        for _ in 0..20 {
            let mut counts = Vec::with_capacity(TABLES.len());
            for table in TABLES {
                let n: i64 = self
                    .conn
                    .query_row(&format!("SELECT COUNT(*) FROM {table}"), [], |r| r.get(0))
                    .map_err(err)?;
                counts.push((n, table));
            }
            let rows: i64 = counts.iter().map(|c| c.0).sum();
            let used: i64 = self
                .conn
                .query_row(
                    "SELECT (SELECT page_count FROM pragma_page_count()) - \
                     (SELECT freelist_count FROM pragma_freelist_count())",
                    [],
                    |r| r.get(0),
                )
                .map_err(err)?;
            let page: i64 = self
                .conn
                .query_row("PRAGMA page_size", [], |r| r.get(0))
                .map_err(err)?;
            let over_rows = u64::try_from(rows).unwrap_or(0) > config.max_rows;
            let over_bytes = u64::try_from(used * page).unwrap_or(0) > config.max_bytes;
            let (largest, table) = counts.into_iter().max().expect("five tables");
            if !(over_rows || over_bytes) || largest == 0 {
                break;
            }
            let excess = (rows - i64::try_from(config.max_rows).unwrap_or(i64::MAX)).max(0);
            let cut = excess.max(largest / 10).max(1);
            deleted += self
                .conn
                .execute(
                    &format!(
                        "DELETE FROM {table} WHERE rowid IN \
                         (SELECT rowid FROM {table} ORDER BY t LIMIT ?1)"
                    ),
                    [cut],
                )
                .map_err(err)?;
        }
        Ok(deleted)
    }

    /// Every device's walk, split wherever two fixes are more than `max_gap_s`
    /// apart (a device that left and came back walks twice) and wherever
    /// the floor changes (each floor's cells are on its own grid).
    pub fn trajectories(&self, max_gap_s: f64) -> Result<Vec<Trajectory>, StoreError> {
        let floor = self.floor_column(FLOORLESS_VERSION);
        let mut stmt = self
            .conn
            .prepare(&format!(
                "SELECT device, t, x, y, {floor} FROM fixes ORDER BY device, t"
            ))
            .map_err(|e| sql(&self.path, e))?;
        let rows = stmt
            .query_map([], |r| {
                Ok((
                    r.get::<_, String>(0)?,
                    r.get::<_, f64>(1)?,
                    Cell::new(r.get(2)?, r.get(3)?),
                    r.get::<_, Option<String>>(4)?,
                ))
            })
            .map_err(|e| sql(&self.path, e))?;
        let mut out: Vec<Trajectory> = Vec::new();
        for row in rows {
            let (device, t, cell, floor) = row.map_err(|e| sql(&self.path, e))?;
            match out.last_mut() {
                Some(last)
                    if last.device == device
                        && last.floor == floor
                        && last
                            .points
                            .last()
                            .is_some_and(|&(lt, _)| t - lt <= max_gap_s) =>
                {
                    last.points.push((t, cell));
                }
                _ => out.push(Trajectory {
                    device,
                    floor,
                    points: vec![(t, cell)],
                }),
            }
        }
        Ok(out)
    }

    /// Every route given (a route across floors as its legs), oldest
    /// first, with its mean feedback score.
    pub fn routes(&self) -> Result<Vec<RecordedRoute>, StoreError> {
        let floor = self.floor_column(FLOORLESS_ROUTES_VERSION);
        let mut stmt = self
            .conn
            .prepare(&format!(
                "SELECT r.device, r.request_id, r.t, r.planner, r.cells,
                        (SELECT AVG(f.score) FROM feedback f
                          WHERE f.device = r.device AND f.request_id = r.request_id),
                        {floor}
                   FROM routes r ORDER BY r.t"
            ))
            .map_err(|e| sql(&self.path, e))?;
        let rows = stmt
            .query_map([], |r| {
                Ok((
                    r.get::<_, String>(0)?,
                    r.get::<_, Option<String>>(1)?,
                    r.get::<_, f64>(2)?,
                    r.get::<_, String>(3)?,
                    r.get::<_, String>(4)?,
                    r.get::<_, Option<f64>>(5)?,
                    r.get::<_, Option<String>>(6)?,
                ))
            })
            .map_err(|e| sql(&self.path, e))?;
        let mut followed: std::collections::HashMap<(String, String), (f64, f64)> =
            std::collections::HashMap::new();
        for a in self.adherence()? {
            if let Some(id) = a.request_id.clone() {
                let entry = followed.entry((a.device.clone(), id)).or_default();
                *entry = (entry.0 + a.score(), entry.1 + 1.0);
            }
        }
        let mut out = Vec::new();
        for row in rows {
            let (device, request_id, t, planner, cells, score, floor) =
                row.map_err(|e| sql(&self.path, e))?;
            let adherence = request_id
                .as_ref()
                .and_then(|id| followed.get(&(device.clone(), id.clone())))
                .map(|&(sum, n)| sum / n);
            // Written by `write` from `Vec<Cell>`; a row that does not parse
            // was edited by hand and is skipped rather than failing training.
            let Ok(cells) = serde_json::from_str::<Vec<Cell>>(&cells) else {
                tracing::warn!(%device, "{}: a route row with unreadable cells, skipped", self.path.display());
                continue;
            };
            out.push(RecordedRoute {
                device,
                request_id,
                t,
                floor,
                planner,
                cells,
                score,
                adherence,
            });
        }
        Ok(out)
    }

    /// The newest `max_rows` fingerprint windows heard on `floor` (`None`:
    /// on a one-floor site), by device then time.
    pub fn heard(&self, max_rows: usize, floor: Option<&str>) -> Result<Vec<Heard>, StoreError> {
        let column = self.floor_column(FLOORLESS_HEARD_VERSION);
        let mut stmt = self
            .conn
            .prepare(&format!(
                "SELECT device, t, readings FROM \
                 (SELECT device, t, readings FROM heard WHERE {column} IS ?2 \
                  ORDER BY t DESC LIMIT ?1) \
                 ORDER BY device, t"
            ))
            .map_err(|e| sql(&self.path, e))?;
        let limit = i64::try_from(max_rows).unwrap_or(i64::MAX);
        let rows = stmt
            .query_map(params![limit, floor], |r| {
                Ok((
                    r.get::<_, String>(0)?,
                    r.get::<_, f64>(1)?,
                    r.get::<_, String>(2)?,
                ))
            })
            .map_err(|e| sql(&self.path, e))?;
        let mut out = Vec::new();
        for row in rows {
            let (device, t, readings) = row.map_err(|e| sql(&self.path, e))?;
            // Written by `write`; a row edited by hand is skipped.
            let Ok(readings) = serde_json::from_str(&readings) else {
                tracing::warn!(%device, "{}: a heard row with unreadable readings, skipped", self.path.display());
                continue;
            };
            out.push(Heard {
                device,
                t,
                readings,
                floor: floor.map(str::to_owned),
            });
        }
        Ok(out)
    }

    /// Deletes all but the newest `max_rows` fingerprint windows. Returns
    /// the number deleted.
    pub(crate) fn keep_newest_heard(&mut self, max_rows: usize) -> Result<usize, StoreError> {
        self.conn
            .execute(
                "DELETE FROM heard WHERE rowid IN \
                 (SELECT rowid FROM heard ORDER BY t DESC LIMIT -1 OFFSET ?1)",
                [i64::try_from(max_rows).unwrap_or(i64::MAX)],
            )
            .map_err(|e| sql(&self.path, e))
    }

    /// Every guided walk's adherence, oldest first.
    pub fn adherence(&self) -> Result<Vec<Adherence>, StoreError> {
        let mut stmt = self
            .conn
            .prepare(
                "SELECT device, request_id, started_t, t, ending, in_corridor_share, detours,
                        arrived, expected_s, taken_s
                   FROM adherence ORDER BY t",
            )
            .map_err(|e| sql(&self.path, e))?;
        let rows = stmt
            .query_map([], |r| {
                Ok((
                    Adherence {
                        device: r.get(0)?,
                        request_id: r.get(1)?,
                        started_t: r.get(2)?,
                        t: r.get(3)?,
                        ending: Ending::Cancelled,
                        in_corridor_share: r.get(5)?,
                        detours: r.get(6)?,
                        arrived: r.get(7)?,
                        expected_s: r.get(8)?,
                        taken_s: r.get(9)?,
                    },
                    r.get::<_, String>(4)?,
                ))
            })
            .map_err(|e| sql(&self.path, e))?;
        let mut out = Vec::new();
        for row in rows {
            let (mut adherence, ending) = row.map_err(|e| sql(&self.path, e))?;
            // Written by `write`; a row edited by hand into something else
            // is skipped rather than failing training.
            let Some(ending) = Ending::parse(&ending) else {
                tracing::warn!(device = %adherence.device, "{}: an adherence row ending {ending:?}, skipped", self.path.display());
                continue;
            };
            adherence.ending = ending;
            out.push(adherence);
        }
        Ok(out)
    }
}

/// Creates the file readable and writable by its owner only, so SQLite (which
/// gives its WAL and shared-memory files the database's mode) keeps all three
/// private whatever the umask; an existing file is left as it is.
fn create_private(path: &Path) -> Result<(), StoreError> {
    use std::os::unix::fs::OpenOptionsExt;
    match std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(path)
    {
        Ok(_) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(()),
        Err(source) => Err(StoreError::Create {
            path: path.to_owned(),
            source,
        }),
    }
}

fn sql(path: &Path, source: rusqlite::Error) -> StoreError {
    StoreError::Sqlite {
        path: path.to_owned(),
        source,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fix(device: &str, t: f64, x: u16) -> Record {
        Record::Fix {
            device: device.into(),
            t,
            floor: Some("G".into()),
            cell: Cell::new(x, 1),
            confidence: 0.5,
        }
    }

    #[test]
    fn trajectories_routes_and_feedback_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.sqlite");
        let mut store = Store::open(&path).unwrap();
        store
            .write(&[
                fix("a", 1.0, 1),
                fix("a", 3.0, 2),
                fix("b", 2.0, 5),
                fix("a", 100.0, 9), // after a long gap: a second walk
                Record::Route {
                    device: "a".into(),
                    request_id: Some("r1".into()),
                    t: 3.5,
                    floor: None,
                    planner: "astar".into(),
                    cells: vec![Cell::new(2, 1), Cell::new(3, 1)],
                },
                Record::Feedback {
                    device: "a".into(),
                    request_id: "r1".into(),
                    t: 9.0,
                    score: 4,
                },
                Record::Feedback {
                    device: "a".into(),
                    request_id: "r1".into(),
                    t: 9.5,
                    score: 2,
                },
                Record::Adherence(Adherence {
                    device: "a".into(),
                    request_id: Some("r1".into()),
                    started_t: 3.5,
                    t: 20.0,
                    ending: Ending::Expired,
                    in_corridor_share: 1.0,
                    detours: 0,
                    arrived: false,
                    expected_s: 20.0,
                    taken_s: 16.5,
                }),
            ])
            .unwrap();
        let reader = Store::open_read_only(&path).unwrap();
        let walks = reader.trajectories(30.0).unwrap();
        let shape: Vec<(&str, usize)> = walks
            .iter()
            .map(|w| (w.device.as_str(), w.points.len()))
            .collect();
        assert_eq!(shape, [("a", 2), ("a", 1), ("b", 1)]);
        let routes = reader.routes().unwrap();
        assert_eq!(routes.len(), 1);
        assert_eq!(routes[0].score, Some(3.0));
        assert_eq!(routes[0].adherence, Some(0.5));
        let followed = reader.adherence().unwrap();
        assert_eq!(followed.len(), 1);
        assert_eq!(followed[0].ending, Ending::Expired);
        assert_eq!(routes[0].cells.len(), 2);
    }

    #[test]
    fn retention_bounds_age_and_count() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = Store::open(&dir.path().join("s.sqlite")).unwrap();
        let records: Vec<Record> = (0..10).map(|i| fix("a", f64::from(i), 1)).collect();
        store.write(&records).unwrap();
        // Older than 10 - 6 = 4 goes (t = 0..3), then only the newest 3 stay.
        assert_eq!(store.prune(10.0, 6.0, 3).unwrap(), 4 + 3);
        let times: Vec<f64> = store.trajectories(100.0).unwrap()[0]
            .points
            .iter()
            .map(|p| p.0)
            .collect();
        assert_eq!(times, [7.0, 8.0, 9.0]);
    }

    #[test]
    fn a_truncated_store_is_moved_aside_and_a_fresh_one_started() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.sqlite");
        let mut store = Store::open(&path).unwrap();
        let records: Vec<Record> = (0..5000).map(|i| fix("a", f64::from(i), 1)).collect();
        store.write(&records).unwrap();
        drop(store);
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        let _ = std::fs::remove_file(dir.path().join("s.sqlite-wal"));

        assert!(Store::open(&path).is_err());
        let (mut store, note) = Store::open_or_move_aside(&path).unwrap();
        let note = note.expect("a fallback is reported");
        assert!(note.contains("moved it aside"), "{note}");
        store.write(&[fix("b", 1.0, 1)]).unwrap();
        let kept: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .filter(|n| n.starts_with("s.sqlite.broken-"))
            .collect();
        assert!(!kept.is_empty(), "the broken file is kept");
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&path).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o600);
    }

    #[test]
    fn quotas_bound_rows_per_device_and_in_total() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = Store::open(&dir.path().join("s.sqlite")).unwrap();
        let mut records: Vec<Record> = (0..300).map(|i| fix("greedy", f64::from(i), 1)).collect();
        records.extend((0..50).map(|i| fix(&format!("d{i}"), 1000.0 + f64::from(i), 1)));
        store.write(&records).unwrap();
        let config = StoreConfig {
            max_rows_per_device: 100,
            max_rows: 120,
            ..StoreConfig::default()
        };
        let deleted = store.enforce_quotas(&config).unwrap();
        let walks = store.trajectories(1e9).unwrap();
        let rows: usize = walks.iter().map(|w| w.points.len()).sum();
        assert!(rows <= 120, "{rows}");
        assert_eq!(deleted, 350 - rows);
        let greedy = walks.iter().find(|w| w.device == "greedy");
        // The greedy device's oldest went first; the newest devices stay.
        assert!(greedy.is_none_or(|w| w.points.len() <= 100));
        assert!(walks.iter().any(|w| w.device == "d49"));
    }

    #[test]
    fn a_walk_is_split_where_its_floor_changes() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = Store::open(&dir.path().join("s.sqlite")).unwrap();
        let on = |floor: &str, t: f64| Record::Fix {
            device: "a".into(),
            t,
            floor: Some(floor.into()),
            cell: Cell::new(1, 1),
            confidence: 0.5,
        };
        store
            .write(&[on("B1", 1.0), on("B1", 2.0), on("L1", 3.0), on("L1", 4.0)])
            .unwrap();
        let walks = store.trajectories(30.0).unwrap();
        let shape: Vec<(Option<&str>, usize)> = walks
            .iter()
            .map(|w| (w.floor.as_deref(), w.points.len()))
            .collect();
        assert_eq!(shape, [(Some("B1"), 2), (Some("L1"), 2)]);
    }

    /// A version-2 file (fixes with floors, routes without) reads its routes
    /// as floorless, and is upgraded in place when opened for writing.
    #[test]
    fn a_store_from_before_routes_kept_floors_is_read_and_upgraded() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.sqlite");
        Connection::open(&path)
            .unwrap()
            .execute_batch(
                "CREATE TABLE routes (device TEXT NOT NULL, request_id TEXT, t REAL NOT NULL,
                     planner TEXT NOT NULL, cells TEXT NOT NULL);
                 INSERT INTO routes VALUES ('a', 'r1', 1.0, 'astar', '[[1,2],[2,2]]');
                 CREATE TABLE feedback (device TEXT NOT NULL, request_id TEXT NOT NULL,
                     t REAL NOT NULL, score INTEGER NOT NULL);
                 CREATE TABLE adherence (device TEXT NOT NULL, request_id TEXT,
                     started_t REAL NOT NULL, t REAL NOT NULL, ending TEXT NOT NULL,
                     in_corridor_share REAL NOT NULL, detours INTEGER NOT NULL,
                     arrived INTEGER NOT NULL, expected_s REAL NOT NULL, taken_s REAL NOT NULL);
                 PRAGMA user_version = 2;",
            )
            .unwrap();
        let floors = |path: &Path| -> Vec<Option<String>> {
            let store = Store::open_read_only(path).unwrap();
            store
                .routes()
                .unwrap()
                .into_iter()
                .map(|r| r.floor)
                .collect()
        };
        assert_eq!(floors(&path), [None]);
        Store::open(&path)
            .unwrap()
            .write(&[Record::Route {
                device: "a".into(),
                request_id: Some("r2".into()),
                t: 2.0,
                floor: Some("L1".into()),
                planner: "astar".into(),
                cells: vec![Cell::new(0, 0), Cell::new(1, 0)],
            }])
            .unwrap();
        assert_eq!(floors(&path), [None, Some("L1".to_owned())]);
    }

    /// A version-3 file (heard windows without floors) reads them as a
    /// one-floor site's, and is upgraded in place when opened for writing:
    /// each floor's windows then read back apart.
    #[test]
    fn a_store_from_before_heard_windows_kept_floors_is_read_and_upgraded() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.sqlite");
        Connection::open(&path)
            .unwrap()
            .execute_batch(
                "CREATE TABLE heard (device TEXT NOT NULL, t REAL NOT NULL,
                     readings TEXT NOT NULL);
                 INSERT INTO heard VALUES ('a', 1.0, '[[\"b1\",-70.0]]');
                 PRAGMA user_version = 3;",
            )
            .unwrap();
        let heard = |floor: Option<&str>| -> Vec<(String, f64)> {
            let store = Store::open_read_only(&path).unwrap();
            let rows = store.heard(10, floor).unwrap();
            assert!(rows.iter().all(|r| r.floor.as_deref() == floor));
            rows.into_iter().map(|r| (r.device, r.t)).collect()
        };
        assert_eq!(heard(None), [("a".to_owned(), 1.0)]);
        assert!(heard(Some("L1")).is_empty());
        let on = |floor: &str, t: f64| Record::Heard {
            device: "a".into(),
            t,
            floor: Some(floor.into()),
            readings: vec![("b9".into(), -60.0)],
        };
        Store::open(&path)
            .unwrap()
            .write(&[on("L1", 2.0), on("B1", 3.0), on("L1", 4.0)])
            .unwrap();
        assert_eq!(heard(None), [("a".to_owned(), 1.0)]);
        assert_eq!(
            heard(Some("L1")),
            [("a".to_owned(), 2.0), ("a".to_owned(), 4.0)]
        );
        assert_eq!(heard(Some("B1")), [("a".to_owned(), 3.0)]);
    }

    #[test]
    fn a_store_from_before_floors_is_read_and_upgraded_with_nothing_lost() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.sqlite");
        Connection::open(&path)
            .unwrap()
            .execute_batch(
                "CREATE TABLE fixes (device TEXT NOT NULL, t REAL NOT NULL,
                     x INTEGER NOT NULL, y INTEGER NOT NULL, confidence REAL NOT NULL);
                 INSERT INTO fixes VALUES ('a', 1.0, 2, 3, 0.5);
                 PRAGMA user_version = 1;",
            )
            .unwrap();
        let old = Store::open_read_only(&path)
            .unwrap()
            .trajectories(30.0)
            .unwrap();
        assert_eq!(old.len(), 1);
        assert_eq!(
            (old[0].floor.as_deref(), old[0].points[0].1),
            (None, Cell::new(2, 3))
        );
        let mut store = Store::open(&path).unwrap();
        store
            .write(&[Record::Fix {
                device: "a".into(),
                t: 2.0,
                floor: Some("G".into()),
                cell: Cell::new(2, 4),
                confidence: 0.5,
            }])
            .unwrap();
        let walks = Store::open_read_only(&path)
            .unwrap()
            .trajectories(30.0)
            .unwrap();
        let floors: Vec<Option<&str>> = walks.iter().map(|w| w.floor.as_deref()).collect();
        assert_eq!(floors, [None, Some("G")]);
    }

    #[test]
    fn a_store_of_another_version_is_refused_with_its_path() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.sqlite");
        Store::open(&path).unwrap();
        Connection::open(&path)
            .unwrap()
            .execute_batch("PRAGMA user_version = 99")
            .unwrap();
        let err = Store::open_read_only(&path).err().unwrap().to_string();
        assert!(err.contains("s.sqlite") && err.contains("99"), "{err}");
    }

    #[test]
    fn heard_windows_read_back_newest_and_are_kept_bounded() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.sqlite");
        let mut store = Store::open(&path).unwrap();
        let heard = |device: &str, t: f64| Record::Heard {
            device: device.into(),
            t,
            floor: None,
            readings: vec![("b1".into(), -70.5), ("b2".into(), -81.0)],
        };
        store
            .write(&[
                heard("b", 3.0),
                heard("a", 1.0),
                heard("a", 2.0),
                heard("b", 0.5),
            ])
            .unwrap();
        // The newest three, by device then time.
        let read = Store::open_read_only(&path)
            .unwrap()
            .heard(3, None)
            .unwrap();
        let keys: Vec<(&str, f64)> = read.iter().map(|r| (r.device.as_str(), r.t)).collect();
        assert_eq!(keys, [("a", 1.0), ("a", 2.0), ("b", 3.0)]);
        assert_eq!(
            read[0].readings,
            [("b1".to_owned(), -70.5), ("b2".to_owned(), -81.0)]
        );
        assert_eq!(store.keep_newest_heard(2).unwrap(), 2);
        assert_eq!(store.heard(10, None).unwrap().len(), 2);
        // Retention covers the table like the others.
        assert_eq!(store.prune(10.0, 6.5, u64::MAX).unwrap(), 2);
        assert!(store.heard(10, None).unwrap().is_empty());
    }
}
