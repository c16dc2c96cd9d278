//! The Grafana dashboards in `manifests/dashboards/` against real data: a real Prometheus (the
//! Debian package) scrapes a real operator (`--per-robot-metrics`) while real agents
//! (`lekiwi-fleet`) and simulated ones (`lekiwi-sim`, which report vitals) run and two rollouts
//! happen, one completing and one rolling back; then every panel's PromQL and every template
//! variable's query is evaluated through Prometheus's HTTP API.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::{LabelSelector, LabelSelectorRequirement};
use kube::Api;
use kube::api::{Patch, PatchParams, PostParams};
use lekiwi_crds::deployment::RolloutPhase;
use lekiwi_crds::{ReleaseRef, Robot, RobotDeployment, RobotDeploymentSpec};
use lekiwi_tests::{
    ControlPlane, FleetProcess, FleetSpec, OperatorProcess, bin, enrollment_token, free_port,
    gateway_url, http_get, log_dir, namespace, push_release, repo_root, rollout_finished,
    test_strategy, wait_for, wait_online,
};
use serde_json::{Value, json};

const PROMETHEUS: &str = "/usr/bin/prometheus";
const HEALTH: &str = r#"test ! -e "$LEKIWI_RELEASE_DIR/../../fail-health""#;
const FLEET: usize = 10;
const SIMULATED: usize = 2;
/// Label that keeps the simulated robots (which cannot install releases) out of the rollouts.
const SIM_LABEL: &str = "lekiwi.test/simulated";

/// A child process killed (with its process group) when dropped.
struct Proc(Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn spawn(program: &Path, args: &[String], log: &Path) -> anyhow::Result<Proc> {
    let file = std::fs::File::create(log)?;
    let child = Command::new(program)
        .args(args)
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null())
        .stdout(file.try_clone()?)
        .stderr(file)
        .spawn()
        .with_context(|| format!("spawn {}", program.display()))?;
    Ok(Proc(child))
}

/// A real Prometheus scraping the operator every second.
struct Prometheus {
    _proc: Proc,
    port: u16,
    log: PathBuf,
}

impl Prometheus {
    async fn start(dir: &Path, target_port: u16, tag: &str) -> anyhow::Result<Self> {
        if !Path::new(PROMETHEUS).exists() {
            bail!("{PROMETHEUS} is missing: run scripts/setup.sh (installs Debian's prometheus)");
        }
        let config = dir.join("prometheus.yml");
        std::fs::write(
            &config,
            format!(
                "global:\n  scrape_interval: 1s\n  scrape_timeout: 1s\n  evaluation_interval: 1s\n\
                 scrape_configs:\n  - job_name: lekiwi-operator\n    static_configs:\n      \
                 - targets: ['127.0.0.1:{target_port}']\n"
            ),
        )?;
        let port = free_port();
        let log = log_dir().join(format!("prometheus-{tag}.log"));
        let args: Vec<String> = vec![
            format!("--config.file={}", config.display()),
            format!("--storage.tsdb.path={}", dir.join("tsdb").display()),
            format!("--web.listen-address=127.0.0.1:{port}"),
            "--log.level=warn".into(),
        ];
        let mut proc = spawn(Path::new(PROMETHEUS), &args, &log)?;
        let start = Instant::now();
        loop {
            if let Some(status) = proc.0.try_wait()? {
                bail!(
                    "prometheus exited with {status}:\n{}",
                    std::fs::read_to_string(&log).unwrap_or_default()
                );
            }
            if let Ok((200, _)) = http_get(port, "/-/ready").await {
                break;
            }
            if start.elapsed() > Duration::from_secs(30) {
                bail!("prometheus not ready in 30 s; log: {}", log.display());
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        Ok(Self {
            _proc: proc,
            port,
            log,
        })
    }

    /// `GET /api/v1/<path>?<params>`; the `data` of a successful answer.
    async fn api(&self, path: &str, params: &[(&str, &str)]) -> anyhow::Result<Value> {
        let query: Vec<String> = params
            .iter()
            .map(|(k, v)| format!("{}={}", encode(k), encode(v)))
            .collect();
        let (code, body) = http_get(self.port, &format!("/api/v1/{path}?{}", query.join("&")))
            .await
            .with_context(|| format!("prometheus answered nothing; log: {}", self.log.display()))?;
        let v: Value = serde_json::from_str(&body)
            .with_context(|| format!("HTTP {code}, not JSON: {body}"))?;
        if v["status"] != "success" {
            bail!("HTTP {code}: {} {}", v["errorType"], v["error"]);
        }
        Ok(v["data"].clone())
    }

    async fn instant(&self, expr: &str) -> anyhow::Result<Vec<Value>> {
        let data = self.api("query", &[("query", expr)]).await?;
        Ok(data["result"].as_array().cloned().unwrap_or_default())
    }

    async fn range(&self, expr: &str, over: Duration) -> anyhow::Result<Vec<Value>> {
        let end = jiff::Timestamp::now().as_second();
        let start = (end - over.as_secs() as i64).to_string();
        let end = end.to_string();
        let data = self
            .api(
                "query_range",
                &[
                    ("query", expr),
                    ("start", &start),
                    ("end", &end),
                    ("step", "2"),
                ],
            )
            .await?;
        Ok(data["result"].as_array().cloned().unwrap_or_default())
    }
}

/// Percent-encodes everything but RFC 3986's unreserved characters.
fn encode(s: &str) -> String {
    s.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                (b as char).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}

/// Whether a query result holds at least one number (NaN draws nothing in Grafana).
fn has_numbers(result: &[Value]) -> bool {
    result.iter().any(|series| {
        let single = series["value"]
            .as_array()
            .map(|v| vec![Value::Array(v.clone())]);
        let values =
            single.unwrap_or_else(|| series["values"].as_array().cloned().unwrap_or_default());
        values.iter().any(|v| {
            v[1].as_str()
                .is_some_and(|s| s.parse::<f64>().is_ok_and(f64::is_finite))
        })
    })
}

/// A release directory of a few files.
fn release_dir(root: &Path, tag: &str) -> anyhow::Result<PathBuf> {
    let dir = root.join(format!("release-{tag}"));
    std::fs::create_dir_all(dir.join("lekiwi"))?;
    for i in 0..5 {
        std::fs::write(
            dir.join("lekiwi").join(format!("f{i}.py")),
            format!("file {i} of {tag}\n").repeat(100),
        )?;
    }
    Ok(dir)
}

fn push(
    cp: &ControlPlane,
    op: &OperatorProcess,
    ns: &str,
    dir: &Path,
    version: &str,
) -> anyhow::Result<ReleaseRef> {
    let server = format!("http://127.0.0.1:{}", op.gateway_port);
    push_release(&cp.kubeconfig(), ns, &server, None, dir, version)
}

async fn finished(
    api: &Api<RobotDeployment>,
    name: &str,
    op: &OperatorProcess,
) -> anyhow::Result<RobotDeployment> {
    rollout_finished(api, name, Duration::from_secs(180))
        .await
        .map_err(|e| anyhow::anyhow!("{e}; operator log: {}", op.log.display()))
}

/// Replaces Grafana's variables with the test's values.
fn substitute(expr: &str, vars: &[(&str, &str)]) -> String {
    let mut out = expr.to_owned();
    // Longest names first: `$robot` must not eat part of a longer name.
    let mut vars = vars.to_vec();
    vars.sort_by_key(|(k, _)| std::cmp::Reverse(k.len()));
    for (k, v) in vars {
        out = out
            .replace(&format!("${{{k}}}"), v)
            .replace(&format!("${k}"), v);
    }
    out
}

/// Every panel, rows' nested panels included.
fn panels(dashboard: &Value) -> Vec<Value> {
    let mut out = Vec::new();
    for p in dashboard["panels"].as_array().into_iter().flatten() {
        out.extend(p["panels"].as_array().into_iter().flatten().cloned());
        if p["type"] != "row" {
            out.push(p.clone());
        }
    }
    out
}

#[tokio::test]
async fn every_dashboard_panel_returns_data_from_a_real_prometheus() -> anyhow::Result<()> {
    let t0 = Instant::now();
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "dash").await?;
    let dir = tempfile::tempdir()?;
    let blobs = dir.path().join("blobs");
    std::fs::create_dir_all(&blobs)?;
    let mut op = OperatorProcess::start(
        cp,
        &ns,
        "dash",
        &[
            "--blob-dir",
            blobs.to_str().unwrap(),
            "--per-robot-metrics",
            "--heartbeat-interval-seconds",
            "2",
        ],
    )?;
    op.wait_ready().await?;
    let prom = Prometheus::start(dir.path(), op.http_port, &ns).await?;
    wait_for(
        "prometheus to scrape the operator",
        Duration::from_secs(30),
        || async {
            let r = prom
                .instant("up{job=\"lekiwi-operator\"} == 1")
                .await
                .ok()?;
            (!r.is_empty()).then_some(())
        },
    )
    .await?;

    // Real agents that install releases, and simulated ones that report vitals (this machine
    // has no temperature sensor for the real agent to read).
    let token = enrollment_token(&client, &ns).await?;
    let token_file = dir.path().join("enroll");
    std::fs::write(&token_file, &token)?;
    let state_root = dir.path().join("robots");
    let _fleet = FleetProcess::start(FleetSpec {
        gateway: &gateway_url(&op),
        token_file: &token_file,
        namespace: &ns,
        robots: FLEET,
        state_root: &state_root,
        health_command: HEALTH,
        report_every: "5",
        rust_log: "warn",
        extra: &[],
    })?;
    let sim_args: Vec<String> = [
        "--gateway",
        &gateway_url(&op),
        "--enrollment-token",
        &token,
        "--namespace",
        &ns,
        "--robots",
        &SIMULATED.to_string(),
        "--prefix",
        "sim",
        "--heartbeat-interval",
        "1",
        "--report-every",
        "60",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let _sim = spawn(
        &bin("lekiwi-sim"),
        &sim_args,
        &log_dir().join(format!("sim-{ns}.log")),
    )?;
    let robots: Api<Robot> = Api::namespaced(client.clone(), &ns);
    wait_online(&client, &ns, FLEET + SIMULATED, Duration::from_secs(120)).await?;
    for i in 1..=SIMULATED {
        let patch = json!({"metadata": {"labels": {SIM_LABEL: "true"}}});
        robots
            .patch(
                &format!("sim-{i:05}"),
                &PatchParams::default(),
                &Patch::Merge(&patch),
            )
            .await?;
    }
    let online_at = t0.elapsed();

    // A rollout that completes, then one that rolls back: kiwi-002 and kiwi-003 (batch 1 after
    // the canary) fail their health check.
    let deployments: Api<RobotDeployment> = Api::namespaced(client.clone(), &ns);
    let v1 = push(cp, &op, &ns, &release_dir(dir.path(), "1")?, "1.0.0")?;
    let selector = LabelSelector {
        match_expressions: Some(vec![LabelSelectorRequirement {
            key: SIM_LABEL.into(),
            operator: "DoesNotExist".into(),
            values: None,
        }]),
        match_labels: None,
    };
    deployments
        .create(
            &PostParams::default(),
            &RobotDeployment::new(
                "fleet",
                RobotDeploymentSpec {
                    selector,
                    release: Some(v1),
                    agent: None,
                    strategy: test_strategy(3, 1),
                    paused: false,
                    analysis: None,
                    priority: 0,
                },
            ),
        )
        .await?;
    let d = finished(&deployments, "fleet", &op).await?;
    let st = d.status.unwrap_or_default();
    assert_eq!(st.phase, Some(RolloutPhase::Completed), "{:?}", st.message);
    assert_eq!((st.updated, st.targeted), (FLEET as i32, FLEET as i32));
    let first_at = t0.elapsed();

    for i in [2, 3] {
        std::fs::write(
            state_root.join(format!("kiwi-{i:03}")).join("fail-health"),
            "",
        )?;
    }
    let v2 = push(cp, &op, &ns, &release_dir(dir.path(), "2")?, "2.0.0")?;
    deployments
        .patch(
            "fleet",
            &PatchParams::default(),
            &Patch::Merge(&json!({"spec": {"release": v2}})),
        )
        .await?;
    let d = finished(&deployments, "fleet", &op).await?;
    let st = d.status.unwrap_or_default();
    assert_eq!(st.phase, Some(RolloutPhase::RolledBack), "{:?}", st.message);
    let second_at = t0.elapsed();

    // A few more scrapes after the last transition, so rates and current values are there.
    wait_for(
        "a scrape after the rollback",
        Duration::from_secs(30),
        || async {
            let r = prom
                .instant("lekiwi_rollouts_finished_total{outcome=\"rolled_back\"}")
                .await
                .ok()?;
            (!r.is_empty()).then_some(())
        },
    )
    .await?;
    tokio::time::sleep(Duration::from_secs(3)).await;
    let since_start = Duration::from_secs(t0.elapsed().as_secs() + 60);

    let vars: Vec<(&str, &str)> = vec![
        ("__rate_interval", "1m"),
        ("__interval", "2s"),
        ("__range", "1h"),
        ("datasource", "prometheus"),
        ("namespace", &ns),
        ("deployment", "fleet"),
        ("robot", "sim-00001"),
    ];
    let mut failures = Vec::new();
    let mut evaluated = 0;
    let dashboards_dir = repo_root().join("manifests/dashboards");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dashboards_dir)?
        .map(|e| e.map(|e| e.path()))
        .collect::<Result<_, _>>()?;
    files.retain(|p| p.extension().is_some_and(|e| e == "json"));
    files.sort();
    let names: Vec<String> = files
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    for expected in ["fleet-overview.json", "robot-detail.json", "rollouts.json"] {
        assert!(
            names.iter().any(|n| n == expected),
            "{expected} missing: {names:?}"
        );
    }
    for file in &files {
        let name = file.file_name().unwrap().to_string_lossy().into_owned();
        let dashboard: Value = serde_json::from_slice(&std::fs::read(file)?)
            .with_context(|| format!("{name} is not JSON"))?;
        assert!(
            dashboard["uid"].as_str().is_some_and(|u| !u.is_empty()),
            "{name}: no uid"
        );
        let all = panels(&dashboard);
        assert!(!all.is_empty(), "{name}: no panels");

        // Template variables: their query must offer the test's value.
        for var in dashboard["templating"]["list"]
            .as_array()
            .into_iter()
            .flatten()
        {
            if var["type"] != "query" {
                continue;
            }
            let var_name = var["name"].as_str().unwrap_or_default();
            let query = var["query"]["query"]
                .as_str()
                .or(var["query"].as_str())
                .unwrap_or_default();
            let Some(inner) = query
                .strip_prefix("label_values(")
                .and_then(|q| q.strip_suffix(')'))
            else {
                failures.push(format!(
                    "{name}: variable {var_name}: not label_values(): {query}"
                ));
                continue;
            };
            let Some((selector, label)) = inner.rsplit_once(',') else {
                failures.push(format!("{name}: variable {var_name}: {query}"));
                continue;
            };
            let selector = substitute(selector.trim(), &vars);
            let want = vars
                .iter()
                .find(|(k, _)| *k == var_name)
                .map(|(_, v)| *v)
                .unwrap_or_default();
            match prom
                .api(
                    &format!("label/{}/values", label.trim()),
                    &[("match[]", &selector)],
                )
                .await
            {
                Ok(values)
                    if values
                        .as_array()
                        .is_some_and(|a| a.iter().any(|v| v == want)) => {}
                Ok(values) => failures.push(format!(
                    "{name}: variable {var_name} ({query}) does not offer {want:?}: {values}"
                )),
                Err(e) => failures.push(format!("{name}: variable {var_name} ({query}): {e}")),
            }
        }

        for panel in &all {
            let title = panel["title"].as_str().unwrap_or("?");
            let targets = panel["targets"].as_array().cloned().unwrap_or_default();
            if targets.is_empty() {
                failures.push(format!("{name}: panel {title:?} has no targets"));
            }
            for target in targets {
                let Some(raw) = target["expr"].as_str() else {
                    failures.push(format!("{name}: panel {title:?}: a target without expr"));
                    continue;
                };
                let expr = substitute(raw, &vars);
                if expr.contains('$') {
                    failures.push(format!(
                        "{name}: panel {title:?}: unknown variable in {raw}"
                    ));
                    continue;
                }
                evaluated += 1;
                match prom.instant(&expr).await {
                    Ok(r) if has_numbers(&r) => {}
                    Ok(r) => failures.push(format!(
                        "{name}: panel {title:?}: no data now for {expr} ({} series)",
                        r.len()
                    )),
                    Err(e) => failures.push(format!("{name}: panel {title:?}: {expr}: {e}")),
                }
                if target["range"] != false {
                    match prom.range(&expr, since_start).await {
                        Ok(r) if has_numbers(&r) => {}
                        Ok(_) => failures.push(format!(
                            "{name}: panel {title:?}: no data over the test for {expr}"
                        )),
                        Err(e) => failures.push(format!("{name}: panel {title:?}: {expr}: {e}")),
                    }
                }
            }
        }
    }

    // The release history a rolled-back robot shows: 1.0.0, then 2.0.0, then 1.0.0 again.
    let history = prom
        .range(
            &format!(
                "max by (version) (lekiwi_robot_release_info{{namespace=\"{ns}\", robot=\"kiwi-001\"}})"
            ),
            since_start,
        )
        .await?;
    let versions: Vec<&str> = history
        .iter()
        .filter_map(|s| s["metric"]["version"].as_str())
        .collect();
    if !(versions.contains(&"1.0.0") && versions.contains(&"2.0.0")) {
        failures.push(format!(
            "kiwi-001's release history shows {versions:?}, not 1.0.0 and 2.0.0"
        ));
    }
    let rolled_back = prom
        .instant("sum(lekiwi_rollouts_finished_total{outcome=\"rolled_back\"})")
        .await?;
    if rolled_back
        .first()
        .and_then(|s| s["value"][1].as_str())
        .and_then(|v| v.parse::<f64>().ok())
        != Some(1.0)
    {
        failures.push(format!("one rollback expected: {rolled_back:?}"));
    }

    eprintln!(
        "{} dashboards, {evaluated} expressions; online after {online_at:?}, first rollout \
         done at {first_at:?}, rollback at {second_at:?}, checked by {:?}",
        files.len(),
        t0.elapsed()
    );
    if !failures.is_empty() {
        bail!(
            "{} dashboard checks failed:\n{}\noperator log: {}",
            failures.len(),
            failures.join("\n"),
            op.log.display()
        );
    }
    Ok(())
}
