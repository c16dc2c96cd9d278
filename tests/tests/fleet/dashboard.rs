//! The web dashboard (issue 15) in a real browser: Debian's headless Chromium, driven over the
//! DevTools protocol, against a real operator (controller + gateway), real agents
//! (`lekiwi-fleet`) and a release pushed with the real CLI. Users are ServiceAccounts bound to
//! the chart's `lekiwi-operator-user` and `lekiwi-viewer` roles, logging in with tokens from
//! `kubectl create token`.
//!
//! What it shows, each without reloading the page: the fleet view counts and lists the robots
//! as they come Online; a robot's view has its conditions, CPU/memory charts from the event store
//! and its events; the rollouts view shows a rollout's batches filling up until it completes;
//! Pause and Resume work for the operator user; the viewer sees them disabled and a direct call
//! with its token is refused (403); robots going Offline appear in the fleet view. A second test
//! (issue 40), with robots of both simulators, checks what the page shows of each robot (its
//! live heartbeat, display name, hardware, dated events, charts of simulated telemetry, a "not
//! found" page), a malformed selector, the login page without navigation, a paused Completed
//! rollout and the dialog Undo asks first. Screenshots of each view go to
//! `target/test-logs/dashboard-*.png` (the README's come from there).

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context as _, Result, ensure};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use kube::api::{Patch, PatchParams, PostParams};
use kube::{Api, Client, ResourceExt};
use lekiwi_crds::deployment::UNDO_ANNOTATION;
use lekiwi_crds::{ReleaseRef, Robot, RobotDeployment, RobotDeploymentSpec};
use lekiwi_tests::browser::Browser;
use lekiwi_tests::{
    AgentProcess, ControlPlane, FleetProcess, FleetSpec, OperatorProcess, SimProcess, SimSpec,
    account, chart_roles, enrollment_token_file, gateway_url, http_request, log_dir, namespace,
    push_release, test_strategy, wait_for, wait_online,
};
use serde_json::json;

/// Robots of the `lekiwi-fleet` process plus one `lekiwi-agent` with telemetry of its machine.
const ROBOTS: usize = 5;
/// The robot whose own view the test opens.
const SOLO: &str = "kiwi-solo";
/// An event message that would run script if the page parsed it as HTML.
const HOSTILE: &str = "<img src=x onerror=\"window.__xss=1\">restart done";
const LIVE: Duration = Duration::from_secs(60);
/// How soon the fleet view re-reads after a change announced during a refresh: under the
/// dashboard's `SUBSCRIBED_REFRESH_MS` (15 s) safety net, which must not be what catches up.
const CHANGE_REREAD: Duration = Duration::from_secs(10);

/// A release directory of a few files, differing by `tag`.
fn release_dir(root: &Path, tag: &str) -> Result<PathBuf> {
    let dir = root.join(format!("release-{tag}"));
    std::fs::create_dir_all(dir.join("lekiwi"))?;
    for i in 0..3 {
        std::fs::write(
            dir.join("lekiwi").join(format!("f{i}.py")),
            format!("# file {i} of release {tag}\n").repeat(50),
        )?;
    }
    Ok(dir)
}

async fn deploy(
    client: &Client,
    ns: &str,
    release: &ReleaseRef,
    selector: LabelSelector,
) -> Result<()> {
    let d = RobotDeployment::new(
        "demo",
        RobotDeploymentSpec {
            selector,
            release: Some(release.clone()),
            agent: None,
            strategy: test_strategy(2, 1),
            paused: false,
            analysis: None,
            priority: 0,
        },
    );
    Api::<RobotDeployment>::namespaced(client.clone(), ns)
        .create(&PostParams::default(), &d)
        .await?;
    Ok(())
}

/// Logs in through the page's form (the token typed as a user pastes it) and marks the page,
/// so a later check can tell it was never reloaded.
async fn log_in(browser: &mut Browser, base: &str, ns: &str, token: &str) -> Result<()> {
    browser.goto(&format!("{base}/dashboard/")).await?;
    browser
        .wait_for(
            "the login form",
            "!document.getElementById('login').hidden",
            LIVE,
        )
        .await?;
    // Before anyone logs in, the navigation (namespace, log out) is not shown at all.
    let nav_shown = browser
        .eval("(n => getComputedStyle(n).display !== 'none' || n.getClientRects().length > 0)(document.getElementById('nav'))")
        .await?;
    ensure!(
        nav_shown == json!(false),
        "the navigation shows on the login page"
    );
    let fill = format!(
        "document.getElementById('login-namespace').value = {ns};\
         document.getElementById('login-token').value = {token};\
         document.getElementById('login-form').requestSubmit(); true",
        ns = json!(ns),
        token = json!(token),
    );
    browser.eval(&fill).await?;
    browser
        .wait_for(
            "the navigation after login",
            "!document.getElementById('nav').hidden",
            LIVE,
        )
        .await?;
    browser.eval("window.__notReloaded = true").await?;
    Ok(())
}

async fn screenshot(browser: &mut Browser, view: &str) -> Result<()> {
    let path = log_dir().join(format!("dashboard-{view}.png"));
    let bytes = browser.screenshot(&path).await?;
    ensure!(bytes > 10_000, "{view} screenshot is only {bytes} bytes");
    Ok(())
}

/// `document.querySelectorAll(selector).length` as a JavaScript expression.
fn count(selector: &str) -> String {
    format!("document.querySelectorAll({}).length", json!(selector))
}

#[tokio::test]
async fn dashboard_shows_the_fleet_live_and_obeys_rbac() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "dash").await?;
    let dir = tempfile::tempdir()?;
    let blobs = dir.path().join("blobs");
    std::fs::create_dir_all(&blobs)?;
    let mut op = OperatorProcess::start(cp, &ns, "dash", &["--blob-dir", blobs.to_str().unwrap()])?;
    op.wait_ready().await?;
    let [viewer_role, user_role] = chart_roles(cp, &client, &ns).await?;
    let user = account(cp, &client, &ns, "ops", Some(&user_role)).await?;
    let viewer = account(cp, &client, &ns, "watcher", Some(&viewer_role)).await?;
    let token_file = dir.path().join("enroll");
    enrollment_token_file(&client, &ns, &token_file).await?;
    let server = format!("http://127.0.0.1:{}", op.gateway_port);
    let v1 = push_release(
        &cp.kubeconfig(),
        &ns,
        &server,
        None,
        &release_dir(dir.path(), "1")?,
        "1.0.0",
    )?;
    let v2 = push_release(
        &cp.kubeconfig(),
        &ns,
        &server,
        None,
        &release_dir(dir.path(), "2")?,
        "2.0.0",
    )?;

    let mut browser = Browser::start("dashboard", 1280, 900).await?;
    log_in(&mut browser, &server, &ns, &user).await?;

    // The fleet view fills in as real agents enroll and come Online.
    let mut fleet = FleetProcess::start(FleetSpec {
        gateway: &gateway_url(&op),
        token_file: &token_file,
        namespace: &ns,
        robots: ROBOTS - 1,
        state_root: &dir.path().join("robots"),
        health_command: "true",
        report_every: "5",
        rust_log: "warn",
        extra: &["--restart-command", "sleep 1"],
    })?;
    let quick = [
        "--telemetry-cpu-interval-s",
        "1",
        "--telemetry-memory-interval-s",
        "1",
    ];
    let solo_state = dir.path().join("solo");
    let mut solo = AgentProcess::start(
        &gateway_url(&op),
        &format!("{ns}/{SOLO}"),
        &token_file,
        &solo_state,
        &[&quick[..], &["--telemetry-batch-interval-s", "1"]].concat(),
    )?;
    wait_online(&client, &ns, ROBOTS, Duration::from_secs(120)).await?;
    // Text a robot reports is shown as text: this event's message must not become markup.
    solo.emit("note", HOSTILE, &json!({"why": "markup in a message"}))?;
    browser
        .wait_for(
            "every robot Online in the table",
            &format!("{} === {ROBOTS}", count("#robots tr[data-phase=Online]")),
            LIVE,
        )
        .await?;
    browser
        .wait_for(
            "the fleet view on its subscription",
            "document.getElementById('status').textContent.startsWith('Live (subscription)')",
            LIVE,
        )
        .await?;
    // The counts and the rows are two reads: a robot that came Online between them is counted
    // by the re-read its announced change scheduled, well within the 15 s safety-net refresh
    // (so a view that dropped changes announced during a refresh would fail here).
    browser
        .wait_for(
            "every robot in the Online count",
            &format!("document.querySelector('#count-Online .n')?.textContent === '{ROBOTS}'"),
            CHANGE_REREAD,
        )
        .await?;

    // A rollout of v1 then v2: the rollouts view follows it to Completed without a reload.
    deploy(&client, &ns, &v1, LabelSelector::default()).await?;
    browser.eval("location.hash = '#/rollouts'").await?;
    browser
        .wait_for(
            "rollout demo Completed on v1",
            "document.querySelector('[data-rollout=demo]')?.dataset.phase === 'Completed'",
            Duration::from_secs(120),
        )
        .await?;
    let rollouts = Api::<RobotDeployment>::namespaced(client.clone(), &ns);
    rollouts
        .patch(
            "demo",
            &PatchParams::default(),
            &Patch::Merge(&json!({"spec": {"release": v2}})),
        )
        .await?;
    browser
        .wait_for(
            "rollout demo Progressing on v2",
            "document.querySelector('[data-rollout=demo]')?.dataset.phase === 'Progressing'",
            LIVE,
        )
        .await?;
    screenshot(&mut browser, "rollouts-progressing").await?;
    let batches = browser
        .wait_for(
            "every batch of demo complete",
            "document.querySelector('[data-rollout=demo]')?.dataset.phase === 'Completed' && \
             [...document.querySelectorAll('[data-rollout=demo] [data-batch]')]\
               .map(b => b.dataset.updated + '/' + b.dataset.total)",
            Duration::from_secs(120),
        )
        .await?;
    ensure!(batches == json!(["1/1", "2/2", "2/2"]), "batches {batches}");
    screenshot(&mut browser, "rollouts").await?;

    // Pause and Resume through the buttons, as the operator user.
    browser
        .eval("document.querySelector('[data-rollout=demo] [data-action=pause]').click(); true")
        .await?;
    wait_for("spec.paused true", LIVE, || async {
        let d = rollouts.get("demo").await.ok()?;
        d.spec.paused.then_some(())
    })
    .await?;
    browser
        .wait_for(
            "the Resume button",
            "!!document.querySelector('[data-rollout=demo] [data-action=resume]:not([disabled])')",
            LIVE,
        )
        .await?;
    browser
        .eval("document.querySelector('[data-rollout=demo] [data-action=resume]').click(); true")
        .await?;
    wait_for("spec.paused false", LIVE, || async {
        let d = rollouts.get("demo").await.ok()?;
        (!d.spec.paused).then_some(())
    })
    .await?;

    // One robot: conditions, charts from the event store, events.
    browser
        .eval(&format!("location.hash = '#/robots/{ns}/{SOLO}'"))
        .await?;
    for (what, expr) in [
        (
            "the robot's conditions",
            count("#conditions tr[data-condition]"),
        ),
        (
            "its CPU chart",
            "Number(document.querySelector('svg[data-metric=cpu_percent]')?.dataset.samples)"
                .into(),
        ),
        ("its events", count("#events tr[data-seq]")),
    ] {
        browser.wait_for(what, &expr, LIVE).await?;
    }
    let shown = browser
        .wait_for(
            "the hostile event, as text",
            &format!(
                "[...document.querySelectorAll('#events td')].some(td => td.textContent === {})",
                json!(HOSTILE)
            ),
            LIVE,
        )
        .await?;
    ensure!(shown == json!(true));
    ensure!(
        browser
            .eval("window.__xss === undefined && !document.querySelector('#events img')")
            .await?
            == json!(true),
        "an event's message became markup"
    );
    screenshot(&mut browser, "robot").await?;
    ensure!(
        browser.eval("window.__notReloaded === true").await? == json!(true),
        "the page reloaded"
    );

    // The viewer: buttons disabled, and the API refuses the call the button would make.
    browser
        .eval("document.getElementById('logout').click(); true")
        .await?;
    log_in(&mut browser, &server, &ns, &viewer).await?;
    browser.eval("location.hash = '#/rollouts'").await?;
    let disabled = browser
        .wait_for(
            "demo's buttons for the viewer",
            "(b => b.length ? b : null)([...document.querySelectorAll('[data-rollout=demo] button')].map(b => b.disabled))",
            LIVE,
        )
        .await?;
    ensure!(
        disabled == json!([true, true]),
        "viewer's buttons {disabled}"
    );
    let auth = format!("Bearer {viewer}");
    let (code, _, body) = http_request(
        op.gateway_port,
        "POST",
        &format!("/api/v1/namespaces/{ns}/rollouts/demo/pause"),
        &[("authorization", auth.as_str())],
        Some(b""),
    )
    .await?;
    ensure!(
        code == 403,
        "the viewer's pause answered {code}: {}",
        String::from_utf8_lossy(&body)
    );

    // Robots going Offline appear in the viewer's fleet view without a reload.
    browser.eval("location.hash = '#/fleet'").await?;
    browser
        .wait_for(
            "the fleet table",
            &format!("{} === {ROBOTS}", count("#robots tr[data-robot]")),
            LIVE,
        )
        .await?;
    screenshot(&mut browser, "fleet").await?;
    browser
        .wait_for(
            "the viewer's fleet view on its subscription",
            "document.getElementById('status').textContent.startsWith('Live (subscription)')",
            LIVE,
        )
        .await?;
    fleet.kill();
    solo.kill();
    browser
        .wait_for(
            "every robot Offline in the table",
            &format!("{} === {ROBOTS}", count("#robots tr[data-phase=Offline]")),
            Duration::from_secs(90),
        )
        .await
        .context("robots did not show Offline")?;
    ensure!(
        browser.eval("window.__notReloaded === true").await? == json!(true),
        "the page reloaded"
    );
    screenshot(&mut browser, "fleet-offline").await?;
    Ok(())
}

/// The label of the `lekiwi-fleet` robots of the second test, which rollouts select (simulated
/// robots of `lekiwi-sim` install no releases).
const REAL: &str = "lekiwi.test/real";
/// How long a check of the second test waits for what the page shows.
const SHOWN: Duration = Duration::from_secs(30);

/// What the page shows of each robot and what it asks first, with robots of both simulators
/// (`lekiwi-fleet`'s real agents and `lekiwi-sim`'s simulated ones, both sending synthetic
/// telemetry as agents do): the navigation stays hidden on the login page; an unknown robot
/// gets a "not found" page; a malformed label selector clears the rows and says so
/// prominently; a robot's last heartbeat is the gateway's live one, not the status written
/// minutes ago; its display name and hardware are shown, its events with their date, and its
/// charts have samples; a paused Completed rollout shows both; Undo asks first, naming the
/// rollout, and does nothing unless confirmed.
#[tokio::test]
async fn dashboard_shows_each_robot_fully_and_asks_before_undo() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "dashd").await?;
    let dir = tempfile::tempdir()?;
    let blobs = dir.path().join("blobs");
    std::fs::create_dir_all(&blobs)?;
    let flags = [
        "--blob-dir",
        blobs.to_str().unwrap(),
        "--heartbeat-interval-seconds",
        "5",
    ];
    let mut op = OperatorProcess::start(cp, &ns, "dashd", &flags)?;
    op.wait_ready().await?;
    let [_, user_role] = chart_roles(cp, &client, &ns).await?;
    let user = account(cp, &client, &ns, "ops", Some(&user_role)).await?;
    let token_file = dir.path().join("enroll");
    enrollment_token_file(&client, &ns, &token_file).await?;
    let server = format!("http://127.0.0.1:{}", op.gateway_port);

    let mut browser = Browser::start("dashboard-details", 1280, 900).await?;
    log_in(&mut browser, &server, &ns, &user).await?;
    let quick = [
        "--telemetry-interval-s",
        "1",
        "--telemetry-batch-interval-s",
        "2",
    ];
    let _fleet = FleetProcess::start(FleetSpec {
        gateway: &gateway_url(&op),
        token_file: &token_file,
        namespace: &ns,
        robots: 2,
        state_root: &dir.path().join("robots"),
        health_command: "true",
        report_every: "5",
        rust_log: "warn",
        extra: &quick,
    })?;
    let _sim = SimProcess::start(
        SimSpec {
            gateway: &gateway_url(&op),
            token_file: &token_file,
            namespace: &ns,
            robots: 1,
            prefix: "sim",
            extra: &quick,
        },
        dir.path(),
    )?;
    wait_online(&client, &ns, 3, Duration::from_secs(120)).await?;

    unknown_robot(&mut browser, &ns).await?;
    malformed_selector(&mut browser).await?;
    live_heartbeats(&mut browser, &op, &ns, &user).await?;
    robot_details(&mut browser, &client, &ns).await?;
    simulated_telemetry(&mut browser, &op, &ns, &user).await?;
    paused_and_undo(&mut browser, cp, &ns, &server, dir.path()).await?;
    Ok(())
}

/// `#/robots/NS/no-such-robot` says the robot was not found, instead of an empty page.
async fn unknown_robot(browser: &mut Browser, ns: &str) -> Result<()> {
    browser
        .eval(&format!("location.hash = '#/robots/{ns}/no-such-robot'"))
        .await?;
    let shown = browser
        .wait_for(
            "the robot-not-found page",
            "(e => e && e.getClientRects().length > 0 ? e.textContent : null)\
             (document.getElementById('robot-not-found'))",
            SHOWN,
        )
        .await?;
    let text = shown.as_str().unwrap_or_default();
    ensure!(
        text.contains("Robot not found: no-such-robot") && text.contains(ns),
        "not-found page: {text}"
    );
    let rest = browser
        .eval("document.getElementById('robot-facts')?.getClientRects().length ?? 0")
        .await?;
    ensure!(rest == json!(0), "the robot's empty facts show too");
    Ok(())
}

/// A selector the API refuses clears the previous filter's rows and shows the API's reason in
/// an alert at body size (not the 12 px status line); a valid one brings the rows back.
async fn malformed_selector(browser: &mut Browser) -> Result<()> {
    browser.eval("location.hash = '#/fleet'").await?;
    browser
        .wait_for(
            "the three robots in the table",
            &format!("{} === 3", count("#robots tr[data-robot]")),
            LIVE,
        )
        .await?;
    let type_selector = |text: &str| {
        format!(
            "(i => {{ i.value = {}; i.dispatchEvent(new Event('input')); return true }})\
             (document.getElementById('filter-selector'))",
            json!(text)
        )
    };
    browser.eval(&type_selector("lab in (b1")).await?;
    let shown = browser
        .wait_for(
            "the selector's error instead of the rows",
            &format!(
                "(e => e && e.getClientRects().length > 0 && {} === 0 && \
                   parseFloat(getComputedStyle(e).fontSize) >= 14 ? e.textContent : null)\
                 (document.getElementById('filter-error'))",
                count("#robots tr[data-robot]")
            ),
            SHOWN,
        )
        .await?;
    ensure!(
        shown.as_str().unwrap_or_default().contains("lab in (b1"),
        "the error names the selector's problem: {shown}"
    );
    browser.eval(&type_selector("")).await?;
    browser
        .wait_for(
            "the rows back, the error gone",
            &format!(
                "{} === 3 && document.getElementById('filter-error').hidden",
                count("#robots tr[data-robot]")
            ),
            SHOWN,
        )
        .await?;
    Ok(())
}

/// Each robot's heartbeat as the fleet view shows it: the live one the gateway holds (newer than
/// what its status recorded, which is refreshed only every `--status-refresh-seconds`), within
/// a few heartbeat intervals of now. The API's lists and robot view carry it as `lastSeen`.
async fn live_heartbeats(
    browser: &mut Browser,
    op: &OperatorProcess,
    ns: &str,
    user: &str,
) -> Result<()> {
    browser
        .wait_for(
            "every robot's live heartbeat, newer than its status",
            "(rows => rows.length === 3 && rows.every(r => {\
               const h = r.querySelector('[data-last-seen]');\
               const seen = h && Date.parse(h.dataset.lastSeen);\
               return seen > Date.parse(h.dataset.statusTime) && Date.now() - seen < 20000;\
             }))([...document.querySelectorAll('#robots tr[data-robot]')])",
            SHOWN,
        )
        .await?;
    let auth = format!("Bearer {user}");
    for path in [
        format!("/api/v1/namespaces/{ns}/robots"),
        format!("/api/v1/namespaces/{ns}/robots/kiwi-000"),
    ] {
        let (code, _, body) = http_request(
            op.gateway_port,
            "GET",
            &path,
            &[("authorization", &auth)],
            None,
        )
        .await?;
        ensure!(code == 200, "{path}: {code}");
        let body: serde_json::Value = serde_json::from_slice(&body)?;
        let seen: Vec<&str> = match body["items"].as_array() {
            Some(items) => items
                .iter()
                .filter_map(|r| r["lastSeen"].as_str())
                .collect(),
            None => body["lastSeen"].as_str().into_iter().collect(),
        };
        ensure!(
            !seen.is_empty() && seen.len() == body["items"].as_array().map_or(1, Vec::len),
            "{path}: lastSeen missing in {body}"
        );
        for t in seen {
            let t: jiff::Timestamp = t.parse()?;
            let age = jiff::Timestamp::now().duration_since(t);
            ensure!(age.as_secs() < 20, "{path}: lastSeen {t} is {age:?} old");
        }
    }
    Ok(())
}

/// A robot's display name (fleet table and robot view) and hardware (robot view), its events
/// with date and time, and charts of the telemetry `lekiwi-fleet` now sends.
async fn robot_details(browser: &mut Browser, client: &Client, ns: &str) -> Result<()> {
    let spec = json!({"spec": {
        "displayName": "Kiwi zero (bench 2)",
        "hardware": {"model": "LeKiwi v1", "computer": "Raspberry Pi 5 8GB",
                     "serial": "LK-0042", "cameras": ["front", "wrist"]}}});
    Api::<Robot>::namespaced(client.clone(), ns)
        .patch("kiwi-000", &PatchParams::default(), &Patch::Merge(&spec))
        .await?;
    browser
        .wait_for(
            "the display name in the fleet table",
            "document.querySelector('#robots tr[data-robot=\"kiwi-000\"]')?.textContent\
               .includes('Kiwi zero (bench 2)')",
            SHOWN,
        )
        .await?;
    browser
        .eval(&format!("location.hash = '#/robots/{ns}/kiwi-000'"))
        .await?;
    let facts = browser
        .wait_for(
            "the display name and hardware among the robot's facts",
            "(f => f && f.includes('Kiwi zero (bench 2)') && f.includes('LeKiwi v1') ? f : null)\
             (document.getElementById('robot-facts')?.textContent)",
            SHOWN,
        )
        .await?;
    let facts = facts.as_str().unwrap_or_default();
    for part in ["Raspberry Pi 5 8GB", "LK-0042", "front, wrist"] {
        ensure!(
            facts.contains(part),
            "{part} is not among the facts: {facts}"
        );
    }
    let heading = browser
        .eval("document.querySelector('#view h2').textContent")
        .await?;
    ensure!(
        heading
            .as_str()
            .unwrap_or_default()
            .contains("Kiwi zero (bench 2)"),
        "heading {heading}"
    );
    // Events carry their date (the browser's local date and time, to the second), not only the
    // time of day.
    browser
        .wait_for(
            "an event time with its date",
            "(t => t && /^\\d{4}-\\d{2}-\\d{2} \\d{2}:\\d{2}:\\d{2}$/.test(t) && \
               Math.abs(Date.parse(t.replace(' ', 'T')) - Date.now()) < 3600e3)\
             (document.querySelector('#events tr[data-seq] td')?.textContent)",
            SHOWN,
        )
        .await?;
    charts_filled(browser, "kiwi-000").await?;
    browser
        .wait_for(
            "the robot view's live heartbeat, newer than its status",
            "(h => h && Date.parse(h.dataset.lastSeen) > Date.parse(h.dataset.statusTime))\
             (document.querySelector('#robot-facts [data-last-seen]'))",
            SHOWN,
        )
        .await?;
    screenshot(browser, "robot-simulated").await?;
    Ok(())
}

/// The robot view's CPU, memory and temperature charts of `robot` have samples.
async fn charts_filled(browser: &mut Browser, robot: &str) -> Result<()> {
    for metric in ["cpu_percent", "memory_percent", "temperature_c"] {
        browser
            .wait_for(
                &format!("{robot}'s {metric} chart"),
                &format!(
                    "Number(document.querySelector('svg[data-metric={metric}]')?.dataset.samples)"
                ),
                SHOWN,
            )
            .await?;
    }
    Ok(())
}

/// `lekiwi-sim`'s robots store telemetry as agents do: the API has their samples and the robot
/// view charts them.
async fn simulated_telemetry(
    browser: &mut Browser,
    op: &OperatorProcess,
    ns: &str,
    user: &str,
) -> Result<()> {
    let auth = format!("Bearer {user}");
    let path = format!("/api/v1/namespaces/{ns}/robots/sim-00001/telemetry");
    let metrics = wait_for("sim-00001's samples in the event store", SHOWN, || async {
        let (code, _, body) = http_request(
            op.gateway_port,
            "GET",
            &path,
            &[("authorization", &auth)],
            None,
        )
        .await
        .ok()?;
        let body: serde_json::Value = serde_json::from_slice(&body).ok()?;
        let metrics: std::collections::BTreeSet<String> = body["items"]
            .as_array()?
            .iter()
            .filter_map(|s| s["metric"].as_str().map(str::to_owned))
            .collect();
        (code == 200 && metrics.contains("temperature_c")).then_some(metrics)
    })
    .await?;
    for metric in [
        "cpu_percent",
        "memory_percent",
        "net_rx_bytes_per_s",
        "disk_percent",
    ] {
        ensure!(metrics.contains(metric), "no {metric} among {metrics:?}");
    }
    browser
        .eval(&format!("location.hash = '#/robots/{ns}/sim-00001'"))
        .await?;
    charts_filled(browser, "sim-00001").await
}

/// A Completed rollout that is paused shows both; Undo opens a dialog naming the rollout and
/// what undoing does, Cancel leaves it untouched, and only the dialog's confirmation undoes it.
async fn paused_and_undo(
    browser: &mut Browser,
    cp: &ControlPlane,
    ns: &str,
    server: &str,
    dir: &Path,
) -> Result<()> {
    let client = &cp.client().await?;
    let rollouts = Api::<RobotDeployment>::namespaced(client.clone(), ns);
    let robots = Api::<Robot>::namespaced(client.clone(), ns);
    for name in ["kiwi-000", "kiwi-001"] {
        let label = json!({"metadata": {"labels": {REAL: "true"}}});
        robots
            .patch(name, &PatchParams::default(), &Patch::Merge(&label))
            .await?;
    }
    let v1 = push_release(
        &cp.kubeconfig(),
        ns,
        server,
        None,
        &release_dir(dir, "1")?,
        "1.0.0",
    )?;
    let selector = LabelSelector {
        match_labels: Some([(REAL.to_owned(), "true".to_owned())].into()),
        match_expressions: None,
    };
    deploy(client, ns, &v1, selector).await?;
    browser.eval("location.hash = '#/rollouts'").await?;
    browser
        .wait_for(
            "rollout demo Completed",
            "document.querySelector('[data-rollout=demo]')?.dataset.phase === 'Completed'",
            Duration::from_secs(120),
        )
        .await?;
    let click = |action: &str| {
        format!(
            "document.querySelector('[data-rollout=demo] [data-action={action}]').click(); true"
        )
    };
    browser.eval(&click("pause")).await?;
    let badges = browser
        .wait_for(
            "Completed and Paused on demo",
            "(b => b.includes('Paused') ? b : null)\
             ([...document.querySelectorAll('[data-rollout=demo] .badge')].map(b => b.textContent))",
            SHOWN,
        )
        .await?;
    ensure!(badges == json!(["Completed", "Paused"]), "badges {badges}");
    screenshot(browser, "rollouts-paused").await?;

    let undo_requested = || async {
        let d = rollouts.get("demo").await?;
        anyhow::Ok(d.annotations().contains_key(UNDO_ANNOTATION))
    };
    browser.eval(&click("undo")).await?;
    let asked = browser
        .wait_for(
            "the undo dialog",
            "(d => d && d.open ? d.textContent : null)(document.getElementById('confirm'))",
            SHOWN,
        )
        .await?;
    let asked = asked.as_str().unwrap_or_default();
    ensure!(
        asked.contains("Undo rollout demo?") && asked.contains("back to the release it ran before"),
        "the dialog says {asked}"
    );
    screenshot(browser, "undo-dialog").await?;
    tokio::time::sleep(Duration::from_secs(1)).await;
    ensure!(!undo_requested().await?, "undone before the user confirmed");
    browser
        .eval("document.getElementById('confirm-cancel').click(); true")
        .await?;
    browser
        .wait_for(
            "the dialog closed",
            "!document.getElementById('confirm').open",
            SHOWN,
        )
        .await?;
    tokio::time::sleep(Duration::from_secs(1)).await;
    ensure!(!undo_requested().await?, "undone although cancelled");
    browser.eval(&click("undo")).await?;
    browser
        .wait_for(
            "the undo dialog again",
            "document.getElementById('confirm').open",
            SHOWN,
        )
        .await?;
    browser
        .eval("document.getElementById('confirm-ok').click(); true")
        .await?;
    wait_for("the undo annotation", SHOWN, || async {
        undo_requested().await.ok()?.then_some(())
    })
    .await?;
    Ok(())
}
