//! A headless chromium driven over WebDriver (chromedriver, fantoccini), for
//! tests/it/web.rs and examples/webload.rs: one session, reused.

use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use fantoccini::actions::{
    InputSource, KeyAction, KeyActions, MOUSE_BUTTON_LEFT, MouseActions, PointerAction,
};
use fantoccini::{Client, ClientBuilder, Locator};
use serde_json::{Value, json};

/// A child process killed when dropped; with its whole process group when
/// it leads one (chromedriver: the browsers it starts must not outlive a
/// failed test).
pub(crate) struct Proc(pub Child);

impl Proc {
    /// Spawns `command` leading a process group of its own.
    pub(crate) fn group(mut command: Command) -> Proc {
        use std::os::unix::process::CommandExt;
        Proc(command.process_group(0).spawn().expect("the program runs"))
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        // The group is the child's pid when it leads one; kill(-pid) is a
        // no-op (ESRCH) when it does not.
        // SAFETY: kill only sends a signal.
        unsafe {
            libc::kill(-(self.0.id() as i32), libc::SIGKILL);
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// chromedriver and a headless chromium session, or none (skip) when they
/// are not installed outside CI.
pub(crate) struct Browser {
    pub client: Client,
    _driver: Proc,
    _profile: tempfile::TempDir,
    screenshots: PathBuf,
}

impl Browser {
    /// Starts chromium with `extra` command-line switches; without chromium
    /// and chromedriver, says what is missing instead.
    pub(crate) async fn start_with(screenshots: &Path, extra: &[&str]) -> Result<Browser, String> {
        let (chromium, driver) = (
            Path::new("/usr/bin/chromium"),
            Path::new("/usr/bin/chromedriver"),
        );
        if !(chromium.exists() && driver.exists()) {
            return Err(
                "no /usr/bin/chromium or /usr/bin/chromedriver (Debian: apt install chromium chromium-driver)"
                    .into(),
            );
        }
        let port = free_port();
        let mut command = Command::new(driver);
        command
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        let driver = Proc::group(command);
        let deadline = Instant::now() + Duration::from_secs(20);
        while TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(Instant::now() < deadline, "chromedriver did not listen");
            std::thread::sleep(Duration::from_millis(50));
        }
        let profile = tempfile::tempdir().unwrap();
        let mut args: Vec<String> = [
            "--headless=new",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--disable-dev-shm-usage",
            "--window-size=1500,950",
        ]
        .into_iter()
        .chain(extra.iter().copied())
        .map(String::from)
        .collect();
        args.push(format!("--user-data-dir={}", profile.path().display()));
        let mut caps = serde_json::Map::new();
        caps.insert(
            "goog:chromeOptions".into(),
            json!({ "binary": chromium, "args": args }),
        );
        let client = ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
            .capabilities(caps)
            .connect(&format!("http://127.0.0.1:{port}"))
            .await
            .expect("a chromium session");
        std::fs::create_dir_all(screenshots).unwrap();
        Ok(Browser {
            client,
            _driver: driver,
            _profile: profile,
            screenshots: screenshots.to_owned(),
        })
    }

    pub(crate) async fn js(&self, script: &str) -> Value {
        self.client
            .execute(script, vec![])
            .await
            .unwrap_or_else(|e| panic!("{script}: {e}"))
    }

    /// Waits until `script` returns true (a timeout fails the test with
    /// what `describe` returns then).
    pub(crate) async fn until(&self, what: &str, script: &str, describe: &str) {
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            if self.js(script).await == Value::Bool(true) {
                return;
            }
            if Instant::now() > deadline {
                let now = self.js(describe).await;
                panic!("timed out waiting for {what}: {now}");
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    pub(crate) async fn text(&self, id: &str) -> String {
        self.js(&format!(
            "return document.getElementById('{id}').textContent"
        ))
        .await
        .as_str()
        .unwrap_or_default()
        .to_owned()
    }

    pub(crate) async fn click_id(&self, id: &str) {
        self.client
            .find(Locator::Id(id))
            .await
            .unwrap()
            .click()
            .await
            .unwrap();
    }

    /// Presses Enter on the element `locator` finds (the keyboard's click).
    pub(crate) async fn enter_on(&self, locator: Locator<'_>) {
        let element = self.client.find(locator).await.unwrap();
        element.send_keys("\u{e007}").await.unwrap();
    }

    pub(crate) async fn tool(&self, name: &str) {
        self.client
            .find(Locator::Css(&format!("input[name=tool][value={name}]")))
            .await
            .unwrap()
            .click()
            .await
            .unwrap();
    }

    pub(crate) async fn type_into(&self, id: &str, text: &str) {
        let input = self.client.find(Locator::Id(id)).await.unwrap();
        input.clear().await.unwrap();
        input.send_keys(text).await.unwrap();
    }

    /// Viewport coordinates of pixels of the floor-plan image.
    pub(crate) async fn image_points(&self, pixels: &[[f64; 2]]) -> Vec<[f64; 2]> {
        let script = format!(
            "const m = document.querySelector('.layer-floorplan image').getScreenCTM();
             return {}.map(p => {{ const q = new DOMPoint(p[0], p[1]).matrixTransform(m); return [q.x, q.y]; }});",
            serde_json::to_string(pixels).unwrap()
        );
        serde_json::from_value(self.js(&script).await).unwrap()
    }

    pub(crate) async fn click_at(&self, [x, y]: [f64; 2]) {
        let mouse = MouseActions::new("mouse".into())
            .then(PointerAction::MoveTo {
                duration: None,
                x: x.round(),
                y: y.round(),
            })
            .then(PointerAction::Down {
                button: MOUSE_BUTTON_LEFT,
            })
            .then(PointerAction::Up {
                button: MOUSE_BUTTON_LEFT,
            });
        self.client.perform_actions(mouse).await.unwrap();
        self.client.release_actions().await.unwrap();
    }

    /// A Shift-drag from `a` to `b`.
    pub(crate) async fn shift_drag(&self, a: [f64; 2], b: [f64; 2]) {
        let shift = '\u{e008}';
        let keys = KeyActions::new("keys".into())
            .then(KeyAction::Down { value: shift })
            .pause(Duration::from_millis(10))
            .pause(Duration::from_millis(10))
            .pause(Duration::from_millis(10))
            .then(KeyAction::Up { value: shift });
        let mouse = MouseActions::new("mouse".into())
            .pause(Duration::from_millis(10))
            .then(PointerAction::MoveTo {
                duration: None,
                x: a[0].round(),
                y: a[1].round(),
            })
            .then(PointerAction::Down {
                button: MOUSE_BUTTON_LEFT,
            })
            .then(PointerAction::MoveTo {
                duration: Some(Duration::from_millis(100)),
                x: b[0].round(),
                y: b[1].round(),
            })
            .then(PointerAction::Up {
                button: MOUSE_BUTTON_LEFT,
            });
        self.client
            .perform_actions(fantoccini::actions::Actions::from(keys).and(mouse))
            .await
            .unwrap();
        self.client.release_actions().await.unwrap();
    }

    pub(crate) async fn screenshot(&self, name: &str) {
        let png = self.client.screenshot().await.unwrap();
        std::fs::write(self.screenshots.join(name), png).unwrap();
    }
}

pub(crate) fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Spawns a gateway (`gangway run` or `replay --web`) whose web UI binds
/// port 0, and returns it with the UI's base URL, read from its log (the
/// rest of the log is drained so the gateway never blocks on it).
pub(crate) fn with_web_ui(mut command: Command) -> (Proc, String) {
    use std::io::{BufRead, BufReader};
    let mut child = command
        .env("RUST_LOG", "warn,gangway_io::web=info")
        .env("NO_COLOR", "1")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("gangway runs");
    let mut lines = BufReader::new(child.stderr.take().unwrap()).lines();
    let mut seen = Vec::new();
    let url = loop {
        let Some(Ok(line)) = lines.next() else {
            let _ = child.kill();
            panic!("the gateway ended before its web UI started: {seen:#?}");
        };
        if let Some(at) = line.find("web UI at http://") {
            let url = line[at + "web UI at ".len()..]
                .split_whitespace()
                .next()
                .unwrap()
                .trim_end_matches('/')
                .to_owned();
            break url;
        }
        seen.push(line);
    };
    std::thread::spawn(move || for _ in lines {});
    (Proc(child), url)
}

impl Browser {
    /// Viewport coordinates of grid points of the plan (`#plan`, in grid units).
    pub(crate) async fn grid_points(&self, points: &[[f64; 2]]) -> Vec<[f64; 2]> {
        let script = format!(
            "const m = document.getElementById('plan').getScreenCTM();
             return {}.map(p => {{ const q = new DOMPoint(p[0], p[1]).matrixTransform(m); return [q.x, q.y]; }});",
            serde_json::to_string(points).unwrap()
        );
        serde_json::from_value(self.js(&script).await).unwrap()
    }

    /// The plan's visible labels (place names, beacon ids) that overlap
    /// another or stand out of the plan, as text, and how many are visible.
    pub(crate) async fn label_problems(&self) -> Value {
        self.js(
            "const plan = document.getElementById('plan').getBoundingClientRect();
             const shown = [...document.querySelectorAll('#plan .label')]
               .filter(l => l.getAttribute('visibility') !== 'hidden')
               .map(l => [l.textContent, l.getBoundingClientRect()]);
             const problems = [];
             shown.forEach(([a, r], i) => {
               if (r.left < plan.left || r.top < plan.top || r.right > plan.right || r.bottom > plan.bottom)
                 problems.push(`${a} out of the plan`);
               for (const [b, q] of shown.slice(i + 1))
                 if (r.left < q.right && q.left < r.right && r.top < q.bottom && q.top < r.bottom)
                   problems.push(`${a} overlaps ${b}`);
             });
             return { shown: shown.length, problems };",
        )
        .await
    }
}

impl Browser {
    /// Clicks the editor's Save and waits for `what` (a save, applied or
    /// not); returns what the page says of it.
    pub(crate) async fn save(&self, what: &str) -> String {
        self.click_id("save").await;
        self.until(
            what,
            "return document.getElementById('save-status').textContent.startsWith('saved')",
            "return document.getElementById('save-status').textContent",
        )
        .await;
        self.text("save-status").await
    }

    /// Moves the pointer to `[x, y]` (viewport coordinates).
    pub(crate) async fn move_to(&self, [x, y]: [f64; 2]) {
        let mouse = MouseActions::new("mouse".into()).then(PointerAction::MoveTo {
            duration: None,
            x: x.round(),
            y: y.round(),
        });
        self.client.perform_actions(mouse).await.unwrap();
        self.client.release_actions().await.unwrap();
    }
}
