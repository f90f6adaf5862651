//! The browser UI in a real browser: Debian's chromium driven over WebDriver
//! (chromedriver) by fantoccini, one browser session for every check.
//!
//! Without chromium and chromedriver (packages `chromium`, `chromium-driver`;
//! `.ci/run` installs them) the browser test prints a note and skips, except
//! in CI. The HTTP checks (headers, the token, cross-site writes) need no
//! browser. Screenshots of every page go to `target/web-screenshots/`.

mod common;
mod web_support;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use fantoccini::Locator;
use serde_json::{Value, json};
use web_support::{Browser, Proc, free_port};

const HOSTILE: &str = "<img src=x onerror=\"window.__pwned=1\">";

/// `gangway site edit` on a free port; returns it and its base URL.
fn editor(site: &Path, extra: &[&str]) -> (Proc, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_gangway"))
        .args(["site", "edit", "--site"])
        .arg(site)
        .args(extra)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .spawn()
        .expect("gangway runs");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let url = line
        .split_whitespace()
        .find(|w| w.starts_with("http://"))
        .unwrap_or_else(|| panic!("no URL in {line:?}"))
        .trim_end_matches("/edit")
        .to_owned();
    (Proc(child), url)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_web_ui_in_a_real_browser() {
    let Some(plan) = common::shared_data("uci-ble-rssi/iBeacon_Layout.jpg") else {
        return;
    };
    let Some(browser) = Browser::start(&common::root().join("target/web-screenshots")).await else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let site = dir.path().join("library.toml");
    let image = dir.path().join("iBeacon_Layout.jpg");
    the_editor_goes_from_a_plan_image_to_a_valid_site(&browser, &site, &plan, &image).await;
    the_live_map_follows_a_replay_and_routes_a_click(&browser, dir.path()).await;
    browser.client.close().await.unwrap();
}

/// `gangway run --replay` with the web UI: the map loads, devices move as
/// the walk plays, a click on a device and a place asks for a route through
/// the same admission as MQTT and shows it with its instructions, a device
/// whose id is markup shows it as text, and /metrics counts it all.
async fn the_live_map_follows_a_replay_and_routes_a_click(browser: &Browser, dir: &Path) {
    // The sample walk, plus a phone whose id is an HTML attack walking
    // beside walker-02.
    let walk = std::fs::read_to_string(common::root().join("fixtures/walk-waldo.jsonl")).unwrap();
    let mut log = String::new();
    for line in walk.lines() {
        log.push_str(line);
        log.push('\n');
        if line.contains("\"observer\":\"walker-02\"") {
            let hostile = serde_json::to_string(HOSTILE).unwrap();
            log.push_str(&line.replace("\"walker-02\"", &hostile));
            log.push('\n');
        }
    }
    let log_path = common::write(dir, "walk.jsonl", &log);
    let web_port = free_port();
    let config = common::write(
        dir,
        "live.toml",
        &format!(
            "gateway_id = \"gw-web\"\nsite = \"{}\"\n[planner]\nmode = \"astar\"\n\
             [mqtt]\nembedded_port = {}\nstats_interval_s = 1\n[web]\nbind = \"127.0.0.1:{web_port}\"\n",
            common::root().join("config/sites/waldo.toml").display(),
            free_port()
        ),
    );
    let _gateway = Proc(
        Command::new(env!("CARGO_BIN_EXE_gangway"))
            .args(["run", "--config"])
            .arg(&config)
            .arg("--replay")
            .arg(&log_path)
            .args(["--speed", "3"])
            .env("RUST_LOG", "warn")
            .stdout(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let url = format!("http://127.0.0.1:{web_port}");
    let deadline = Instant::now() + Duration::from_secs(20);
    while ureq::get(&format!("{url}/healthz")).call().is_err() {
        assert!(
            Instant::now() < deadline,
            "the gateway's web UI did not start"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    browser.client.goto(&format!("{url}/")).await.unwrap();
    browser
        .until(
            "devices on the map",
            "return document.querySelectorAll('.layer-devices .device').length >= 3",
            "return document.getElementById('connection').textContent + ' ' + document.querySelectorAll('.device').length",
        )
        .await;
    let positions =
        "return Object.fromEntries([...document.querySelectorAll('.layer-devices .device')]
        .map(d => [d.dataset.device, d.getAttribute('transform')]))";
    let before = browser.js(positions).await;
    tokio::time::sleep(Duration::from_secs(4)).await;
    let after = browser.js(positions).await;
    let moved = before
        .as_object()
        .unwrap()
        .iter()
        .filter(|(id, at)| after.get(id.as_str()).is_some_and(|now| now != *at))
        .count();
    assert!(moved >= 1, "no device moved in 4 s: {before} then {after}");

    // The hostile id is a device like any other, shown as text.
    browser
        .until(
            "the hostile device",
            &format!("return !!document.querySelector('.device[data-device=\"' + CSS.escape({}) + '\"]')", serde_json::to_string(HOSTILE).unwrap()),
            "return [...document.querySelectorAll('.device')].map(d => d.dataset.device)",
        )
        .await;
    let hostile = browser
        .js("for (const d of document.querySelectorAll('.device')) d.dispatchEvent(new PointerEvent('pointerenter'));
             return { imgs: document.querySelectorAll('img').length, pwned: window.__pwned === 1,
                      titles: [...document.querySelectorAll('.device title')].map(t => t.textContent),
                      listed: document.getElementById('devices').textContent }")
        .await;
    assert_eq!(hostile["imgs"], 0, "{hostile}");
    assert_eq!(hostile["pwned"], false, "{hostile}");
    assert!(
        hostile["titles"].to_string().contains("onerror"),
        "{hostile}"
    );

    // Click walker-01's dot, then the help desk: a route and its instructions.
    let dot = browser
        .js("const r = document.querySelector('.device[data-device=\"walker-01\"] .dot').getBoundingClientRect();
             return [r.x + r.width / 2, r.y + r.height / 2]")
        .await;
    browser.click_at(serde_json::from_value(dot).unwrap()).await;
    let desk = browser
        .js("const r = document.querySelector('.place[data-place=\"help desk\"] rect').getBoundingClientRect();
             return [r.x + r.width / 2, r.y + r.height / 2]")
        .await;
    browser
        .click_at(serde_json::from_value(desk.clone()).unwrap())
        .await;
    browser
        .until(
            "the route",
            "return document.querySelectorAll('#route .instructions li').length > 0 && !!document.querySelector('.layer-route polyline')",
            "return document.getElementById('route-pick').textContent + ' | ' + document.getElementById('route').textContent",
        )
        .await;
    let pick = browser.text("route-pick").await;
    assert!(
        pick.contains("walker-01") && pick.contains("help desk"),
        "{pick}"
    );
    let route = browser.text("route").await;
    assert!(route.contains(" m by astar"), "{route}");
    browser
        .until(
            "the page's own figures",
            "return Number(document.getElementById('page-stats').dataset.latencyP99) >= 0",
            "return document.getElementById('page-stats').textContent",
        )
        .await;
    browser.screenshot("map.png").await;

    // Survey mode: walker-01 (still selected) stands at the help desk for
    // two windows; the survey file gets them in the generic layout, which
    // the gateway's own survey reader takes.
    browser
        .client
        .find(Locator::Id("survey-on"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    browser.type_into("survey-samples", "2").await;
    browser
        .click_at(serde_json::from_value(desk).unwrap())
        .await;
    browser
        .until(
            "two surveyed windows",
            "return document.getElementById('survey-status').textContent.includes('2 of 2 windows (done)')",
            "return document.getElementById('survey-status').textContent",
        )
        .await;
    let survey = dir.join("survey.csv");
    let text = std::fs::read_to_string(&survey).unwrap();
    assert!(text.starts_with("x_m,y_m,t,b3001,"), "{text}");
    assert_eq!(text.lines().count(), 3, "{text}");
    let site = gangway::site::Site::load(&common::root().join("config/sites/waldo.toml")).unwrap();
    let anchors: Vec<String> = site.beacons.iter().map(|b| b.id.clone()).collect();
    let read = gangway::locate::survey::Survey::load(&survey, &site, &anchors, -200).unwrap();
    assert_eq!(read.samples.len(), 2);
    assert!(
        read.samples
            .iter()
            .all(|s| s.cell == gangway::site::Cell::new(9, 9))
    );
    let heat = browser.client.find(Locator::Id("heat")).await.unwrap();
    heat.select_by_value("samples").await.unwrap();
    browser
        .until(
            "the coverage map",
            "return document.querySelectorAll('.layer-heat rect').length >= 1",
            "return document.getElementById('heat-legend').textContent",
        )
        .await;
    browser.screenshot("survey.png").await;

    let metrics = ureq::get(&format!("{url}/metrics"))
        .call()
        .unwrap()
        .body_mut()
        .read_to_string()
        .unwrap();
    for series in [
        "# TYPE gangway_fixes_total counter",
        "# TYPE gangway_tracked gauge",
        "# TYPE gangway_route_latency_seconds histogram",
    ] {
        assert!(metrics.contains(series), "{series} missing:\n{metrics}");
    }
    let routes = metrics
        .lines()
        .find_map(|l| l.strip_prefix("gangway_route_latency_seconds_count "))
        .and_then(|v| v.parse::<u64>().ok())
        .unwrap_or(0);
    assert!(routes >= 1, "{metrics}");
}

/// A new user, no TOML: open the plan, set the scale, paint the floor,
/// place beacons and places (one with a hostile name), save; `gangway check`
/// accepts the file, and opening and saving it again changes nothing.
async fn the_editor_goes_from_a_plan_image_to_a_valid_site(
    browser: &Browser,
    site: &Path,
    plan: &Path,
    image: &Path,
) {
    let (_server, url) = editor(site, &[]);
    browser.client.goto(&format!("{url}/edit")).await.unwrap();
    browser
        .until(
            "the first check",
            "return document.getElementById('problems').children.length > 0",
            "return document.getElementById('check-summary').textContent",
        )
        .await;
    assert!(
        browser
            .text("problems")
            .await
            .contains("the site needs a `map`"),
        "{}",
        browser.text("problems").await
    );

    // 1. The plan image, uploaded through the file picker. The dataset's
    // file is only copied into a temporary directory, never into the repo.
    let input = browser
        .client
        .find(Locator::Id("image-file"))
        .await
        .unwrap();
    let plan = std::fs::canonicalize(plan).unwrap();
    input.send_keys(plan.to_str().unwrap()).await.unwrap();
    browser
        .until(
            "the plan image",
            "return !!document.querySelector('.layer-floorplan image')",
            "return document.getElementById('save-status').textContent",
        )
        .await;
    assert_eq!(std::fs::read(image).unwrap(), std::fs::read(&plan).unwrap());

    // 2. The scale: the centres of survey cells A01 and W01 are 22 m apart
    // (one survey cell = 1 m, as in config/sites/waldo.toml).
    browser.tool("measure").await;
    let points = browser
        .image_points(&[
            [120.0, 118.0],
            [692.0, 118.0],
            [107.0, 105.0],
            [718.0, 495.0],
        ])
        .await;
    browser.click_at(points[0]).await;
    browser.click_at(points[1]).await;
    browser.type_into("scale-m", "22").await;
    browser.click_id("scale-apply").await;
    let info = browser.text("scale-info").await;
    assert!(info.contains("px per metre"), "{info}");
    browser
        .until(
            "the blocked grid's check",
            "return document.getElementById('problems').textContent.includes('no cell is walkable')",
            "return document.getElementById('problems').textContent",
        )
        .await;

    // 3. The surveyed floor, A01 to W15, painted walkable with a Shift-drag.
    let points = browser
        .image_points(&[[107.0, 105.0], [718.0, 495.0]])
        .await;
    browser.tool("paint").await;
    browser.shift_drag(points[0], points[1]).await;

    // 4. Beacons where the plan shows 2, 3 and 4; places, one named to attack.
    browser.tool("beacon").await;
    for p in browser
        .image_points(&[[361.0, 194.0], [469.0, 194.0], [587.0, 194.0]])
        .await
    {
        browser.click_at(p).await;
    }
    browser.tool("place").await;
    let places = browser
        .image_points(&[[360.0, 358.0], [700.0, 480.0]])
        .await;
    browser.type_into("place-name", HOSTILE).await;
    browser.click_at(places[0]).await;
    browser.type_into("place-name", "east entrance").await;
    browser.click_at(places[1]).await;
    browser
        .until(
            "a valid site",
            "return document.getElementById('check-summary').textContent.startsWith('ok:')",
            "return document.getElementById('check-summary').textContent + ' | ' + document.getElementById('problems').textContent",
        )
        .await;
    let summary = browser.text("check-summary").await;
    assert!(summary.contains("3 beacons, 2 places"), "{summary}");

    // The hostile name is text: no element made of it, no handler run.
    let hostile = browser
        .js(
            "return { imgs: document.querySelectorAll('img').length, pwned: window.__pwned === 1,
                      names: [...document.querySelectorAll('.place-name')].map(t => t.textContent),
                      listed: document.getElementById('places').textContent }",
        )
        .await;
    assert_eq!(hostile["imgs"], 0, "{hostile}");
    assert_eq!(hostile["pwned"], false, "{hostile}");
    assert!(
        hostile["names"]
            .as_array()
            .unwrap()
            .contains(&json!(HOSTILE)),
        "{hostile}"
    );
    assert!(
        hostile["listed"].as_str().unwrap().contains(HOSTILE),
        "{hostile}"
    );
    browser.screenshot("editor.png").await;

    // 5. Save; `gangway check` accepts the file.
    browser.click_id("save").await;
    browser
        .until(
            "the save",
            "return document.getElementById('save-status').textContent.startsWith('saved')",
            "return document.getElementById('save-status').textContent",
        )
        .await;
    let saved = std::fs::read_to_string(site).unwrap();
    assert!(
        saved.contains("[floorplan]") && saved.contains("image = \"iBeacon_Layout.jpg\""),
        "{saved}"
    );
    let config = site.with_file_name("gangway.toml");
    std::fs::write(
        &config,
        "gateway_id = \"gw-test\"\nsite = \"library.toml\"\n[localizer]\nmethod = \"pathloss\"\n",
    )
    .unwrap();
    let out = common::gangway_ok(&["check", "--config", config.to_str().unwrap()]);
    assert!(out.starts_with("ok: "), "{out}");
    assert!(out.contains("3 beacons, 0 gateways, 2 places"), "{out}");

    // 6. Opened again and saved unchanged: the same bytes.
    browser.client.refresh().await.unwrap();
    browser
        .until(
            "the reopened site's check",
            "return document.getElementById('check-summary').textContent.startsWith('ok:')",
            "return document.getElementById('check-summary').textContent",
        )
        .await;
    browser.click_id("save").await;
    browser
        .until(
            "the second save",
            "return document.getElementById('save-status').textContent.startsWith('saved')",
            "return document.getElementById('save-status').textContent",
        )
        .await;
    assert_eq!(std::fs::read_to_string(site).unwrap(), saved);
}

/// Every page and API reply carries the strict policy; the health check answers.
#[test]
fn every_reply_carries_the_content_security_policy() {
    let dir = tempfile::tempdir().unwrap();
    let (_server, url) = editor(&dir.path().join("s.toml"), &["--bind", "127.0.0.1:0"]);
    for path in [
        "/edit",
        "/assets/edit.js",
        "/api/editor",
        "/healthz",
        "/nope",
    ] {
        let reply = ureq::get(&format!("{url}{path}"))
            .config()
            .http_status_as_error(false)
            .build()
            .call()
            .unwrap();
        let csp = reply
            .headers()
            .get("content-security-policy")
            .and_then(|v| v.to_str().ok())
            .unwrap_or_default()
            .to_owned();
        assert_eq!(csp, gangway::web::CONTENT_SECURITY_POLICY, "{path}");
        assert!(
            csp.contains("script-src 'self'") && !csp.contains("unsafe"),
            "{csp}"
        );
        assert_eq!(reply.headers()["x-content-type-options"], "nosniff");
    }
    let health: Value = ureq::get(&format!("{url}/healthz"))
        .call()
        .unwrap()
        .body_mut()
        .read_json()
        .unwrap();
    assert_eq!(health["status"], "ok");
}

/// Bound off loopback, a write without the token is refused; with it, it
/// is taken. On loopback, another site's page cannot write (cross-origin)
/// and a rebound host name is not answered.
#[test]
fn writes_off_loopback_need_the_token() {
    let dir = tempfile::tempdir().unwrap();
    let token = "s3cret-token-for-the-test";
    let token_file = common::write(dir.path(), "token", &format!("{token}\n"));
    let site = dir.path().join("s.toml");
    let (_server, url) = editor(
        &site,
        &[
            "--bind",
            "0.0.0.0:0",
            "--token-file",
            token_file.to_str().unwrap(),
        ],
    );
    let doc = json!({ "doc": { "name": "s", "cell_m": 1.0, "map": "##\n" } });
    let put = |auth: Option<&str>| {
        let mut req = ureq::put(&format!("{url}/api/editor/site"))
            .config()
            .http_status_as_error(false)
            .build();
        if let Some(a) = auth {
            req = req.header("Authorization", a);
        }
        let mut reply = req.send_json(&doc).unwrap();
        let status = reply.status().as_u16();
        let body: Value = reply.body_mut().read_json().unwrap_or(Value::Null);
        (status, body)
    };
    let (status, body) = put(None);
    assert_eq!(status, 401, "{body}");
    assert_eq!(body["error"]["code"], "unauthorized");
    assert_eq!(put(Some("Bearer wrong-token-0123456789")).0, 401);
    assert!(!site.exists(), "nothing was written without the token");
    let (status, body) = put(Some(&format!("Bearer {token}")));
    assert_eq!(status, 200, "{body}");
    assert!(site.exists());
    // The token is never served.
    for path in ["/api/access", "/api/editor", "/edit", "/assets/edit.js"] {
        let text = ureq::get(&format!("{url}{path}"))
            .call()
            .unwrap()
            .body_mut()
            .read_to_string()
            .unwrap();
        assert!(!text.contains(token), "{path}");
    }

    let (_local, url) = editor(&dir.path().join("t.toml"), &["--bind", "127.0.0.1:0"]);
    let cross = ureq::put(&format!("{url}/api/editor/site"))
        .header("Origin", "http://evil.example")
        .config()
        .http_status_as_error(false)
        .build()
        .send_json(&doc)
        .unwrap();
    assert_eq!(cross.status().as_u16(), 403);
    let rebound = ureq::get(&format!("{url}/api/editor"))
        .header("Host", "evil.example")
        .config()
        .http_status_as_error(false)
        .build()
        .call()
        .unwrap();
    assert_eq!(rebound.status().as_u16(), 421);
}
