//! The Helm chart: lints with every option, refuses bad values through its schema, renders to
//! objects the API server accepts (SQLite on a volume, TLS, external PostgreSQL), serves TLS by
//! default with a CA and certificate it makes (kept across upgrades), installs, ships
//! the dashboards kept in sync with `manifests/dashboards/`, and its RBAC is exactly enough: the
//! operator runs controllers and gateway with the chart's ServiceAccount token (enrollment, a
//! release push and a rollout included) and never meets a Forbidden.

use std::path::Path;
use std::process::{Command, Output};
use std::time::Duration;

use kube::Api;
use kube::api::{Patch, PatchParams};
use lekiwi_crds::{Robot, RobotDeployment, RobotPhase};
use lekiwi_tests::{
    ControlPlane, GatewayStandIn, OperatorProcess, bin, create_robot, get_robot, namespace,
    repo_root, wait_for,
};
use serde_json::json;
use serde_yaml::Value;

const CHART: &str = "charts/lekiwi-operator";

/// `helm VERB RELEASE CHART` in namespace `ns` with `watch` (`operator.watchNamespace=...`),
/// then `extra`. The user ClusterRoles are left out: they have fixed, cluster-wide names that
/// another test's release may hold at the same moment (helm refuses to adopt them);
/// hostile_authz.rs proves their rules.
fn helm_args<'a>(
    verb: &'a str,
    release: &'a str,
    ns: &'a str,
    watch: &'a str,
    extra: &[&'a str],
) -> Vec<&'a str> {
    let mut args = vec![
        verb,
        release,
        CHART,
        "-n",
        ns,
        "--set",
        watch,
        "--set",
        "rbac.userRoles=false",
    ];
    args.extend_from_slice(extra);
    args
}

fn ok(out: Output, what: &str) -> String {
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{what} failed:\n{text}");
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// What a render without the cluster needs to make the chart's own CA (it refuses otherwise).
const NEW_CA: [&str; 2] = ["--set", "gateway.tls.allowNewCaWithoutCluster=true"];

/// [`helm`] allowed to make the chart's CA without the cluster.
fn helm_new_ca(args: &[&str]) -> Output {
    helm(&[args, &NEW_CA[..]].concat())
}

/// Helm without a cluster (lint, template with the default capabilities).
fn helm(args: &[&str]) -> Output {
    Command::new(lekiwi_tests::tool("helm"))
        .args(args)
        .env("KUBECONFIG", "/dev/null")
        .current_dir(repo_root())
        .output()
        .expect("run helm")
}

/// The rendered documents, as YAML values (comments and empty documents dropped).
fn documents(rendered: &str) -> Vec<Value> {
    rendered
        .split("\n---")
        .filter_map(|doc| serde_yaml::from_str::<Value>(doc).ok())
        .filter(|v| v.is_mapping())
        .collect()
}

fn find<'a>(docs: &'a [Value], kind: &str, name: &str) -> &'a Value {
    docs.iter()
        .find(|d| d["kind"] == kind && d["metadata"]["name"] == name)
        .unwrap_or_else(|| panic!("no {kind} {name} rendered"))
}

fn json_files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut files: Vec<_> = std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .filter_map(|e| e.ok())
                .map(|e| e.path())
                .filter(|p| p.extension().is_some_and(|x| x == "json"))
                .map(|p| {
                    let name = p.file_name().unwrap().to_string_lossy().into_owned();
                    (name, std::fs::read(&p).expect("read dashboard"))
                })
                .collect()
        })
        .unwrap_or_default();
    files.sort();
    files
}

/// Every option switched on (replicas above one with PostgreSQL and ReadWriteMany blobs).
const ALL_OPTIONS: &str = r#"
nameOverride: kiwi
image: {repository: registry.example.com/lekiwi/operator, tag: 0.2.0-rc.1, pullPolicy: Always}
imagePullSecrets: [{name: regcred}]
replicaCount: 3
operator:
  role: all
  logFormat: text
  logLevel: debug
  watchNamespace: robots
  heartbeatGraceSeconds: 120
  concurrency: 4
  retentionDays: 7
  perRobotMetrics: true
  installCrds: true
  leaderElection: {leaseName: kiwi-leader, leaseDurationSeconds: 20, leaseRetrySeconds: 3}
  extraArgs: [--max-frame-bytes=65536]
httpPort: 9090
gateway:
  port: 9443
  heartbeatIntervalSeconds: 15
  maxConnections: 5000
  maxBlobBytes: 1073741824
  robotQuota: {rows: 100000, bytes: 67108864}
  sessionOpens: {perMinute: 0.5, burst: 3}
  enroll: {rate: 5, burst: 10}
  authLookup: {qps: 2.5, burst: 20}
  apiRateLimit: {perSecond: 5.5, burst: 7}
  graphql: {maxBodyBytes: 131072, maxDepth: 6, maxComplexity: 5000, maxConnections: 300, maxSubscriptionsPerUser: 9, maxConnectionsPerUser: 3, initTimeoutSeconds: 4}
  service:
    type: LoadBalancer
    port: 443
    nodePort: 30443
    annotations: {service.beta.kubernetes.io/aws-load-balancer-type: nlb}
    externalTrafficPolicy: Local
    loadBalancerSourceRanges: [10.0.0.0/8]
  tls: {existingSecret: gateway-tls, caBundle: "-----BEGIN CERTIFICATE-----\nMIIB\n-----END CERTIFICATE-----\n"}
api:
  separate: true
  port: 9444
  service: {type: LoadBalancer, port: 8443, nodePort: 30444, annotations: {a: b}, loadBalancerSourceRanges: [10.1.0.0/16]}
networkPolicy:
  enabled: true
  gateway: {from: [{ipBlock: {cidr: 10.20.0.0/16}}]}
  api: {from: [{namespaceSelector: {matchLabels: {team: lab}}}]}
  metrics: {namespaceSelector: {name: monitoring}, podSelector: {app: prometheus}}
  egress:
    apiServerCidrs: [10.96.0.1/32]
    apiServerPorts: [443]
    extra: [{to: [{ipBlock: {cidr: 10.30.0.5/32}}], ports: [{port: 5432, protocol: TCP}]}]
metrics:
  service: {port: 9090, labels: {scrape: "yes"}, annotations: {a: b}}
serviceMonitor:
  enabled: true
  labels: {release: kube-prometheus-stack}
  interval: 15s
  scrapeTimeout: 10s
  namespace: monitoring
dashboards:
  enabled: true
  label: grafana_dashboard_lekiwi
  labelValue: "yes"
  annotations: {grafana_folder: LeKiwi}
  namespace: monitoring
store:
  postgres: {existingSecret: lekiwi-postgres, key: dsn}
persistence:
  enabled: true
  size: 50Gi
  storageClass: nfs
  accessModes: [ReadWriteMany]
  annotations: {backup: daily}
podDisruptionBudget: {enabled: true, minAvailable: 2, maxUnavailable: null}
otel:
  endpoint: http://otel-collector.observability:4318
  protocol: http/json
  serviceName: lekiwi-fleet
  resourceAttributes: {deployment.environment: prod}
extraEnv: [{name: LEKIWI_AGENT_RATE, value: "10"}]
rbac: {create: true}
serviceAccount: {create: true, name: kiwi-operator, annotations: {team: robots}}
podAnnotations: {a: b}
podLabels: {team: robots}
priorityClassName: system-cluster-critical
resources: {requests: {cpu: 100m, memory: 128Mi}, limits: {cpu: "1", memory: 512Mi}}
nodeSelector: {kubernetes.io/arch: amd64}
tolerations: [{key: dedicated, operator: Exists}]
affinity: {}
topologySpreadConstraints:
  - {maxSkew: 1, topologyKey: topology.kubernetes.io/zone, whenUnsatisfiable: ScheduleAnyway}
"#;

#[test]
fn chart_lints_with_every_option_and_renders_them() -> anyhow::Result<()> {
    ok(helm(&["lint", "--strict", CHART]), "helm lint (defaults)");
    let dir = tempfile::tempdir()?;
    let values = dir.path().join("all.yaml");
    std::fs::write(&values, ALL_OPTIONS)?;
    let values = values.to_str().unwrap();
    ok(
        helm(&["lint", "--strict", CHART, "-f", values]),
        "helm lint (every option)",
    );
    let docs = documents(&ok(
        helm(&["template", "r", CHART, "-n", "fleet", "-f", values]),
        "helm template (every option)",
    ));
    let deploy = find(&docs, "Deployment", "r-kiwi");
    let pod = &deploy["spec"]["template"]["spec"];
    let c = &pod["containers"][0];
    let args: Vec<&str> = c["args"]
        .as_sequence()
        .unwrap()
        .iter()
        .filter_map(|a| a.as_str())
        .collect();
    for want in [
        "--tls-cert=/etc/lekiwi/tls/tls.crt",
        "--tls-key=/etc/lekiwi/tls/tls.key",
        "--gateway-addr=0.0.0.0:9443",
        "--api-addr=0.0.0.0:9444",
        "--http-addr=0.0.0.0:9090",
        "--watch-namespace=robots",
        "--install-crds",
        "--leader-lease=kiwi-leader",
        "--max-blob-bytes=1073741824",
        "--blob-dir=/var/lib/lekiwi/blobs",
        "--max-frame-bytes=65536",
        "--robot-quota-rows=100000",
        "--robot-quota-bytes=67108864",
        "--session-opens-per-minute=0.5",
        "--session-open-burst=3",
        "--enroll-rate=5",
        "--enroll-burst=10",
        "--auth-lookup-qps=2.5",
        "--auth-lookup-burst=20",
        "--api-rate=5.5",
        "--api-burst=7",
        "--graphql-max-body-bytes=131072",
        "--graphql-max-depth=6",
        "--graphql-max-complexity=5000",
        "--graphql-max-connections=300",
        "--graphql-max-subscriptions-per-user=9",
        "--graphql-max-connections-per-user=3",
        "--graphql-init-timeout-seconds=4",
    ] {
        assert!(args.contains(&want), "{want} missing from {args:?}");
    }
    assert!(
        !args.iter().any(|a| a.contains("api-token")),
        "no API token Secret any more: {args:?}"
    );
    assert!(
        !args.iter().any(|a| a.starts_with("--store-url")),
        "PostgreSQL comes from the Secret, not a flag: {args:?}"
    );
    assert!(
        deploy["spec"]["strategy"].is_null(),
        "rolling updates with PostgreSQL"
    );
    let env = c["env"].as_sequence().unwrap();
    let var = |name: &str| {
        env.iter()
            .find(|e| e["name"] == name)
            .unwrap_or_else(|| panic!("env {name} missing: {env:?}"))
    };
    assert_eq!(
        var("LEKIWI_STORE_URL")["valueFrom"]["secretKeyRef"],
        serde_yaml::from_str::<Value>("{name: lekiwi-postgres, key: dsn}")?
    );
    assert_eq!(
        var("OTEL_EXPORTER_OTLP_ENDPOINT")["value"],
        "http://otel-collector.observability:4318"
    );
    assert_eq!(var("OTEL_EXPORTER_OTLP_PROTOCOL")["value"], "http/json");
    assert_eq!(var("OTEL_SERVICE_NAME")["value"], "lekiwi-fleet");
    assert!(
        var("OTEL_RESOURCE_ATTRIBUTES")["value"]
            .as_str()
            .unwrap()
            .contains("deployment.environment=prod")
    );
    assert_eq!(var("LEKIWI_AGENT_RATE")["value"], "10");
    for port in c["ports"].as_sequence().unwrap() {
        assert_eq!(port["protocol"], "TCP", "{port:?}");
    }
    let volumes = serde_yaml::to_string(&pod["volumes"])?;
    assert!(
        volumes.contains("claimName: r-kiwi-data") && volumes.contains("secretName: gateway-tls"),
        "{volumes}"
    );
    let pvc = find(&docs, "PersistentVolumeClaim", "r-kiwi-data");
    assert_eq!(pvc["spec"]["accessModes"][0], "ReadWriteMany");
    assert_eq!(pvc["spec"]["storageClassName"], "nfs");
    assert_eq!(
        find(&docs, "PodDisruptionBudget", "r-kiwi")["spec"]["minAvailable"],
        2
    );
    let gw = find(&docs, "Service", "r-kiwi-gateway");
    assert_eq!(gw["spec"]["type"], "LoadBalancer");
    assert_eq!(gw["spec"]["ports"][0]["nodePort"], 30443);
    let api = find(&docs, "Service", "r-kiwi-api");
    assert_eq!(
        api["metadata"]["labels"]["app.kubernetes.io/component"],
        "api"
    );
    assert_eq!(api["spec"]["ports"][0]["targetPort"], "api");
    assert_eq!(api["spec"]["ports"][0]["nodePort"], 30444);
    assert_eq!(api["spec"]["loadBalancerSourceRanges"][0], "10.1.0.0/16");
    let ca = find(&docs, "ConfigMap", "r-kiwi-gateway-ca");
    assert!(
        ca["data"]["ca.crt"]
            .as_str()
            .unwrap()
            .contains("BEGIN CERTIFICATE")
    );
    network_policy(find(&docs, "NetworkPolicy", "r-kiwi"));
    // watchNamespace: the fleet permissions only in that namespace; the leases in the
    // release's; the reviews of people's tokens cluster-wide (they are cluster-scoped).
    let binding = find(&docs, "RoleBinding", "r-kiwi");
    assert_eq!(binding["metadata"]["namespace"], "robots");
    assert_eq!(binding["roleRef"]["kind"], "ClusterRole");
    assert!(
        !docs
            .iter()
            .any(|d| d["kind"] == "ClusterRoleBinding" && d["metadata"]["name"] == "r-kiwi"),
        "no cluster-wide fleet binding with watchNamespace"
    );
    let local = serde_yaml::to_string(&find(&docs, "Role", "r-kiwi-local")["rules"])?;
    assert!(
        !local.contains("secrets"),
        "no API token Secret to read: {local}"
    );
    let reviews = serde_yaml::to_string(&find(&docs, "ClusterRole", "r-kiwi-reviews")["rules"])?;
    assert!(
        reviews.contains("tokenreviews") && reviews.contains("subjectaccessreviews"),
        "{reviews}"
    );
    assert_eq!(
        find(&docs, "ClusterRoleBinding", "r-kiwi-reviews")["roleRef"]["name"],
        "r-kiwi-reviews"
    );
    // People's permissions on the gateway's API, aggregated into the built-in roles.
    let pusher = find(&docs, "ClusterRole", "lekiwi-release-pusher");
    let labels = &pusher["metadata"]["labels"];
    assert_eq!(
        labels["rbac.authorization.k8s.io/aggregate-to-edit"],
        "true"
    );
    assert_eq!(pusher["rules"][0]["resources"][0], "releases");
    let verbs = serde_yaml::to_string(&pusher["rules"][0]["verbs"])?;
    assert!(verbs.contains("create") && verbs.contains("get"), "{verbs}");
    let viewer = find(&docs, "ClusterRole", "lekiwi-viewer");
    assert_eq!(
        viewer["metadata"]["labels"]["rbac.authorization.k8s.io/aggregate-to-view"],
        "true"
    );
    let rules = serde_yaml::to_string(&viewer["rules"])?;
    for want in [
        "robots",
        "robotdeployments",
        "robots/events",
        "robots/telemetry",
        "list",
        "watch",
    ] {
        assert!(rules.contains(want), "{want}: {rules}");
    }
    assert!(!rules.contains("patch"), "viewers steer nothing: {rules}");
    // The Fleet API's rollout actions: users with `patch robotdeployments`, and the operator
    // that writes the patch once the SubjectAccessReview allowed it.
    let user = find(&docs, "ClusterRole", "lekiwi-operator-user");
    assert_eq!(
        user["metadata"]["labels"]["rbac.authorization.k8s.io/aggregate-to-edit"],
        "true"
    );
    assert!(
        user["metadata"]["labels"]["rbac.authorization.k8s.io/aggregate-to-view"].is_null(),
        "viewers must not aggregate patch"
    );
    let steer = user["rules"].as_sequence().unwrap().iter().any(|r| {
        r["resources"][0] == "robotdeployments"
            && r["verbs"].as_sequence().unwrap().len() == 1
            && r["verbs"][0] == "patch"
    });
    assert!(steer, "lekiwi-operator-user patches robotdeployments");
    let own = find(&docs, "ClusterRole", "r-kiwi")["rules"]
        .as_sequence()
        .unwrap();
    assert!(
        own.iter().any(|r| r["resources"][0] == "robotdeployments"
            && r["verbs"]
                .as_sequence()
                .unwrap()
                .iter()
                .any(|v| v == "patch")),
        "the operator patches robotdeployments for the Fleet API: {own:?}"
    );
    assert!(
        !docs.iter().any(|d| d["kind"] == "Secret"),
        "no API token Secret in the chart"
    );
    let crds = serde_yaml::to_string(&find(&docs, "ClusterRole", "r-kiwi-crds")["rules"])?;
    assert!(crds.contains("create") && crds.contains("patch"), "{crds}");
    Ok(())
}

/// The NetworkPolicy of ALL_OPTIONS: each port open to its own peers, metrics to the
/// monitoring namespace's Prometheus, egress to DNS, the API server and the extra rule.
fn network_policy(np: &Value) {
    let ingress = np["spec"]["ingress"].as_sequence().unwrap();
    let rule = |port: &str| {
        ingress
            .iter()
            .find(|r| r["ports"][0]["port"] == port)
            .unwrap_or_else(|| panic!("no ingress rule for port {port}: {ingress:?}"))
    };
    assert_eq!(
        rule("gateway")["from"][0]["ipBlock"]["cidr"],
        "10.20.0.0/16"
    );
    assert_eq!(
        rule("api")["from"][0]["namespaceSelector"]["matchLabels"]["team"],
        "lab"
    );
    let metrics = &rule("http")["from"][0];
    assert_eq!(
        metrics["namespaceSelector"]["matchLabels"]["name"],
        "monitoring"
    );
    assert_eq!(metrics["podSelector"]["matchLabels"]["app"], "prometheus");
    let egress = serde_yaml::to_string(&np["spec"]["egress"]).unwrap();
    for want in [
        "port: 53",
        "port: 443",
        "10.96.0.1/32",
        "10.30.0.5/32",
        "port: 5432",
    ] {
        assert!(
            egress.contains(want),
            "{want} missing from egress: {egress}"
        );
    }
}

/// The three sources of the gateway's certificate: the chart's CA (refused without the
/// cluster, where it would be made anew on every render, unless asked for), cert-manager (a
/// `Certificate` with the issuer, its Secret mounted) and a Secret of the user's; each lints.
#[test]
fn chart_certificate_sources_render_and_an_offline_ca_is_refused() -> anyhow::Result<()> {
    // (`helm lint` reports a template's `fail` but passes: the defaults lint.)
    let install = ["install", "r", CHART, "--dry-run=client"];
    for cmd in [&["template", "r", CHART][..], &install] {
        let out = helm(cmd);
        let text = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "helm {cmd:?} made a CA offline");
        for names in [
            "cannot see the cluster",
            "gateway.tls.certManager",
            "gateway.tls.existingSecret",
            "gateway.tls.allowNewCaWithoutCluster=true",
        ] {
            assert!(
                text.contains(names),
                "helm {cmd:?} must say {names}:\n{text}"
            );
        }
    }
    let cert_manager = [
        "--set",
        "gateway.tls.certManager.enabled=true",
        "--set",
        "gateway.tls.certManager.issuerRef.name=lab-ca",
        "--set",
        "gateway.tls.certManager.issuerRef.kind=ClusterIssuer",
        "--set",
        "gateway.tls.extraDnsNames={robots.lab.example}",
    ];
    let existing = ["--set", "gateway.tls.existingSecret=lab-tls"];
    for values in [&cert_manager[..], &existing] {
        ok(
            helm(&[&["lint", "--strict", CHART][..], values].concat()),
            "helm lint",
        );
    }
    let render = |values: &[&str]| -> anyhow::Result<Vec<Value>> {
        let all = [&["template", "r", CHART, "-n", "fleet"][..], values].concat();
        Ok(documents(&ok(helm(&all), "helm template")))
    };
    let mounted = |docs: &[Value]| {
        let deploy = find(docs, "Deployment", "r-lekiwi-operator");
        deploy["spec"]["template"]["spec"]["volumes"]
            .as_sequence()
            .unwrap()
            .iter()
            .find(|v| v["name"] == "tls")
            .map(|v| v["secret"]["secretName"].as_str().unwrap().to_owned())
    };
    let docs = render(&cert_manager)?;
    let cert = find(&docs, "Certificate", "r-lekiwi-operator-gateway");
    assert_eq!(cert["apiVersion"], "cert-manager.io/v1");
    assert_eq!(cert["spec"]["issuerRef"]["name"], "lab-ca");
    assert_eq!(cert["spec"]["issuerRef"]["kind"], "ClusterIssuer");
    assert_eq!(cert["spec"]["issuerRef"]["group"], "cert-manager.io");
    let dns = serde_yaml::to_string(&cert["spec"]["dnsNames"])?;
    for name in [
        "r-lekiwi-operator-gateway.fleet.svc",
        "r-lekiwi-operator-api.fleet.svc",
        "robots.lab.example",
    ] {
        assert!(dns.contains(name), "{name} missing: {dns}");
    }
    let secret = cert["spec"]["secretName"].as_str().unwrap();
    assert_eq!(mounted(&docs).as_deref(), Some(secret));
    assert!(
        !docs.iter().any(|d| d["kind"] == "Secret"),
        "no generated Secret"
    );

    let docs = render(&existing)?;
    assert_eq!(mounted(&docs).as_deref(), Some("lab-tls"));
    assert!(
        !docs
            .iter()
            .any(|d| d["kind"] == "Secret" || d["kind"] == "Certificate")
    );

    let docs = render(&NEW_CA)?;
    assert_eq!(
        mounted(&docs).as_deref(),
        Some("r-lekiwi-operator-gateway-tls")
    );
    find(&docs, "Secret", "r-lekiwi-operator-gateway-ca-key");

    // cert-manager without an issuer, or with a Secret too: said, not rendered.
    for (values, says) in [
        (&cert_manager[..2], "issuerRef.name"),
        (
            &[&cert_manager[..4], &existing[..]].concat()[..],
            "not both",
        ),
    ] {
        let out = helm(&[&["template", "r", CHART][..], values].concat());
        let text = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && text.contains(says),
            "{values:?}: {text}"
        );
    }
    Ok(())
}

#[test]
fn chart_servicemonitor_renders_only_when_enabled() -> anyhow::Result<()> {
    let off = ok(
        helm_new_ca(&["template", "r", CHART, "-n", "fleet"]),
        "template",
    );
    assert!(!off.contains("ServiceMonitor\n"), "{off}");
    let docs = documents(&ok(
        helm_new_ca(&[
            "template",
            "r",
            CHART,
            "-n",
            "fleet",
            "--set",
            "serviceMonitor.enabled=true",
            "--set",
            "serviceMonitor.labels.release=prom",
            "--set",
            "serviceMonitor.interval=10s",
        ]),
        "helm template with the ServiceMonitor",
    ));
    let sm = find(&docs, "ServiceMonitor", "r-lekiwi-operator");
    assert_eq!(sm["apiVersion"], "monitoring.coreos.com/v1");
    assert_eq!(sm["metadata"]["namespace"], "fleet");
    assert_eq!(sm["metadata"]["labels"]["release"], "prom");
    assert_eq!(
        sm["metadata"]["labels"]["app.kubernetes.io/managed-by"],
        "Helm"
    );
    let endpoint = &sm["spec"]["endpoints"][0];
    assert_eq!(endpoint["port"], "http-metrics");
    assert_eq!(endpoint["path"], "/metrics");
    assert_eq!(endpoint["interval"], "10s");
    assert_eq!(sm["spec"]["namespaceSelector"]["matchNames"][0], "fleet");
    // It selects the metrics Service, and only it, whose port is named as the endpoint says.
    let metrics = find(&docs, "Service", "r-lekiwi-operator-metrics");
    let selector = sm["spec"]["selector"]["matchLabels"].as_mapping().unwrap();
    for (k, v) in selector {
        assert_eq!(&metrics["metadata"]["labels"][k], v, "label {k:?}");
    }
    let gateway = find(&docs, "Service", "r-lekiwi-operator-gateway");
    assert!(
        selector
            .iter()
            .any(|(k, v)| &gateway["metadata"]["labels"][k] != v),
        "the ServiceMonitor must not select the gateway Service"
    );
    assert_eq!(metrics["spec"]["ports"][0]["name"], "http-metrics");
    assert_eq!(metrics["spec"]["ports"][0]["port"], 8080);
    Ok(())
}

#[test]
fn chart_schema_refuses_bad_values_naming_the_field() {
    let cases: &[(&[&str], &str)] = &[
        (&["--set", "replicaCount=0"], "/replicaCount"),
        (
            &["--set", "gateway.service.type=Bogus"],
            "/gateway/service/type",
        ),
        (&["--set", "gateway.port=abc"], "/gateway/port"),
        (&["--set", "httpPort=70000"], "/httpPort"),
        (&["--set", "replicaCont=2"], "replicaCont"),
        (&["--set", "persistence.size=10GB"], "/persistence/size"),
        (&["--set", "image.tag=bad tag!"], "/image/tag"),
        (&["--set", "operator.role=boss"], "/operator/role"),
        (&["--set", "operator.logFormat=xml"], "/operator/logFormat"),
        (&["--set", "otel.protocol=grpc"], "/otel/protocol"),
        (
            &["--set", "resources.requests.memory=lots"],
            "/resources/requests/memory",
        ),
        (
            &["--set", "persistence.accessModes={ReadWriteSometimes}"],
            "/persistence/accessModes",
        ),
        (
            &["--set", "gateway.tls.existingSecret=Not_A_Name"],
            "/gateway/tls/existingSecret",
        ),
        (
            &["--set", "gateway.tls.certManager.issuerRef.kind=Signer"],
            "/gateway/tls/certManager/issuerRef/kind",
        ),
        (&["--set", "api.port=0"], "/api/port"),
        (
            &["--set", "networkPolicy.egress.apiServerCidrs={10.0.0.1}"],
            "/networkPolicy/egress/apiServerCidrs",
        ),
    ];
    for (args, field) in cases {
        for cmd in ["template", "lint"] {
            let mut all = vec![cmd];
            if cmd == "template" {
                all.push("r");
            }
            all.push(CHART);
            all.extend_from_slice(args);
            let out = helm(&all);
            let text = format!(
                "{}{}",
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            );
            assert!(!out.status.success(), "helm {all:?} accepted it:\n{text}");
            assert!(
                text.contains(field) && text.contains("schema"),
                "helm {all:?} must name {field}:\n{text}"
            );
        }
    }
    // Rules relating several values: the templates refuse them and say what to change.
    let topology: &[(&[&str], &str)] = &[
        (
            &["--set", "replicaCount=2"],
            "store.postgres.existingSecret",
        ),
        (
            &[
                "--set",
                "replicaCount=2",
                "--set",
                "store.postgres.existingSecret=pg",
            ],
            "ReadWriteMany",
        ),
        (
            &[
                "--set",
                "replicaCount=2",
                "--set",
                "store.postgres.existingSecret=pg",
                "--set",
                "persistence.enabled=false",
            ],
            "emptyDir",
        ),
    ];
    for (args, says) in topology {
        let mut all = vec!["template", "r", CHART];
        all.extend_from_slice(args);
        let out = helm_new_ca(&all);
        let text = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(!out.status.success(), "helm {all:?} accepted it");
        assert!(text.contains(says), "helm {all:?} must say {says}:\n{text}");
    }
}

#[test]
fn chart_dashboards_match_manifests_and_render_as_configmaps() -> anyhow::Result<()> {
    let root = repo_root();
    let source = json_files(&root.join("manifests/dashboards"));
    let copy = json_files(&root.join(CHART).join("dashboards"));
    let names = |files: &[(String, Vec<u8>)]| files.iter().map(|f| f.0.clone()).collect::<Vec<_>>();
    assert_eq!(
        names(&copy),
        names(&source),
        "charts/lekiwi-operator/dashboards/ differs from manifests/dashboards/: \
         cp manifests/dashboards/*.json charts/lekiwi-operator/dashboards/ (and remove stale ones)"
    );
    for ((name, a), (_, b)) in source.iter().zip(&copy) {
        assert!(
            a == b,
            "dashboards/{name} differs from manifests/dashboards/{name}: cp manifests/dashboards/*.json charts/lekiwi-operator/dashboards/"
        );
    }

    let maps = |args: &[&str]| -> Vec<Value> {
        let mut all = vec!["template", "r", CHART, "-n", "fleet"];
        all.extend_from_slice(args);
        documents(&ok(helm_new_ca(&all), "helm template"))
            .into_iter()
            // The gateway's CA ConfigMap is not a dashboard.
            .filter(|d| d["kind"] == "ConfigMap" && d["data"]["ca.crt"].is_null())
            .collect()
    };
    let rendered = maps(&[]);
    assert_eq!(rendered.len(), source.len());
    for (name, bytes) in &source {
        let cm = rendered
            .iter()
            .find(|cm| cm["data"][name.as_str()].is_string())
            .unwrap_or_else(|| panic!("no ConfigMap holds {name}"));
        assert_eq!(cm["metadata"]["labels"]["grafana_dashboard"], "1");
        let text = cm["data"][name.as_str()].as_str().unwrap();
        let parsed: serde_json::Value = serde_json::from_str(text)?;
        assert_eq!(parsed, serde_json::from_slice::<serde_json::Value>(bytes)?);
    }
    let custom = maps(&[
        "--set",
        "dashboards.label=dash",
        "--set",
        "dashboards.labelValue=lekiwi",
    ]);
    assert!(
        custom
            .iter()
            .all(|cm| cm["metadata"]["labels"]["dash"] == "lekiwi"
                && cm["metadata"]["labels"]["grafana_dashboard"].is_null())
    );
    assert!(maps(&["--set", "dashboards.enabled=false"]).is_empty());

    // A chart without dashboard files renders no ConfigMap (and no empty document).
    let tmp = tempfile::tempdir()?;
    let chart = tmp.path().join("lekiwi-operator");
    copy_dir(&root.join(CHART), &chart)?;
    for (name, _) in &copy {
        std::fs::remove_file(chart.join("dashboards").join(name))?;
    }
    // (TLS off: the generated CA's ConfigMap is not a dashboard.)
    let out = ok(
        helm(&[
            "template",
            "r",
            chart.to_str().unwrap(),
            "--set",
            "gateway.tls.enabled=false",
        ]),
        "helm template without dashboards",
    );
    assert!(!out.contains("kind: ConfigMap"), "{out}");
    Ok(())
}

fn copy_dir(from: &Path, to: &Path) -> std::io::Result<()> {
    std::fs::create_dir_all(to)?;
    for entry in std::fs::read_dir(from)? {
        let entry = entry?;
        let target = to.join(entry.file_name());
        if entry.file_type()?.is_dir() {
            copy_dir(&entry.path(), &target)?;
        } else {
            std::fs::copy(entry.path(), target)?;
        }
    }
    Ok(())
}

#[tokio::test]
async fn chart_variants_are_accepted_by_the_api_server() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "chart-dry").await?;
    ok(
        cp.kubectl(&[
            "create",
            "secret",
            "generic",
            "gateway-tls",
            "-n",
            &ns,
            "--type=kubernetes.io/tls",
            "--from-literal=tls.crt=cert",
            "--from-literal=tls.key=key",
        ]),
        "create the TLS Secret",
    );
    ok(
        cp.kubectl(&[
            "create",
            "secret",
            "generic",
            "lekiwi-postgres",
            "-n",
            &ns,
            "--from-literal=url=postgres://lekiwi:secret@postgres:5432/lekiwi",
        ]),
        "create the PostgreSQL Secret",
    );
    let watch = format!("operator.watchNamespace={ns}");
    let variants: &[(&str, &[&str])] = &[
        ("sqlite", &[]),
        ("no-persistence", &["--set", "persistence.enabled=false"]),
        (
            "tls",
            &[
                "--set",
                "gateway.tls.existingSecret=gateway-tls",
                "--set",
                "gateway.service.type=LoadBalancer",
                "--set",
                "otel.endpoint=http://otel:4317",
                "--set",
                "networkPolicy.enabled=true",
                "--set",
                "networkPolicy.gateway.from[0].ipBlock.cidr=10.20.0.0/16",
                "--set",
                "networkPolicy.egress.apiServerCidrs={10.96.0.1/32}",
            ],
        ),
        (
            "postgres",
            &[
                "--set",
                "store.postgres.existingSecret=lekiwi-postgres",
                "--set",
                "store.postgres.key=url",
                "--set",
                "replicaCount=3",
                "--set",
                "persistence.accessModes={ReadWriteMany}",
                "--set",
                "podDisruptionBudget.minAvailable=2",
            ],
        ),
    ];
    let dir = tempfile::tempdir()?;
    for (name, args) in variants {
        let release = format!("{ns}-{name}");
        // The server's capabilities: its PodDisruptionBudget version (1.20: policy/v1beta1).
        // (Helm refuses to combine this with --include-crds: the CRDs are applied from crds/.)
        let mut all = helm_args("template", &release, &ns, &watch, &["--dry-run=server"]);
        all.extend_from_slice(args);
        let rendered = ok(cp.tool("helm", &all), &format!("helm template ({name})"));
        let file = dir.path().join(format!("{name}.yaml"));
        std::fs::write(&file, &rendered)?;
        let applied = ok(
            cp.kubectl(&[
                "apply",
                "--dry-run=server",
                "-n",
                &ns,
                "-f",
                file.to_str().unwrap(),
                "-f",
                &format!("{CHART}/crds"),
            ]),
            &format!("server dry-run of the rendered chart ({name})"),
        );
        for kind in [
            "deployment.apps",
            "service/",
            "poddisruptionbudget.policy",
            "serviceaccount/",
            "role.rbac",
            "configmap/",
        ] {
            assert!(applied.contains(kind), "{name}: no {kind} in\n{applied}");
        }
        assert_eq!(
            applied.contains("persistentvolumeclaim/"),
            *name != "no-persistence",
            "{name}: {applied}"
        );
        assert_eq!(
            applied.contains("networkpolicy.networking.k8s.io"),
            *name == "tls",
            "{name}: {applied}"
        );
    }
    Ok(())
}

#[tokio::test]
async fn chart_installs_and_its_rbac_suffices() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "chart").await?;
    let watch = format!("operator.watchNamespace={ns}");

    // Release named after the namespace so cluster-scoped RBAC objects never collide.
    ok(
        cp.tool(
            "helm",
            &helm_args("install", &ns, &ns, &watch, &["--wait=false"]),
        ),
        "helm install",
    );
    // The objects as the API server keeps them (no kubelet here: the pods never run).
    let dir = tempfile::tempdir()?;
    let full = format!("{ns}-lekiwi-operator");
    let get = |what: &str| -> anyhow::Result<serde_json::Value> {
        Ok(serde_json::from_str(&ok(
            cp.kubectl(&["get", what, "-n", &ns, "-o", "json"]),
            &format!("get {what}"),
        ))?)
    };
    let deploy = get(&format!("deployment/{full}"))?;
    let pod = &deploy["spec"]["template"]["spec"];
    assert_eq!(deploy["spec"]["replicas"], 1);
    assert_eq!(deploy["spec"]["strategy"]["type"], "Recreate");
    assert_eq!(pod["serviceAccountName"], full.as_str());
    assert_eq!(
        pod["volumes"][0]["persistentVolumeClaim"]["claimName"],
        format!("{full}-data")
    );
    let c = &pod["containers"][0];
    assert!(
        c["args"]
            .as_array()
            .unwrap()
            .contains(&json!("--store-url=sqlite:///var/lib/lekiwi/events.db"))
    );
    assert_eq!(c["securityContext"]["readOnlyRootFilesystem"], true);
    assert_eq!(c["livenessProbe"]["httpGet"]["path"], "/healthz");
    assert_eq!(c["readinessProbe"]["httpGet"]["path"], "/readyz");
    let gateway = get(&format!("service/{full}-gateway"))?;
    assert_eq!(gateway["spec"]["type"], "ClusterIP");
    assert_eq!(gateway["spec"]["ports"][0]["name"], "gateway");
    assert_eq!(gateway["spec"]["ports"][0]["port"], 8081);
    let metrics = get(&format!("service/{full}-metrics"))?;
    assert_eq!(metrics["spec"]["ports"][0]["name"], "http-metrics");
    assert_eq!(metrics["spec"]["ports"][0]["port"], 8080);
    let pvc = get(&format!("persistentvolumeclaim/{full}-data"))?;
    assert_eq!(pvc["spec"]["resources"]["requests"]["storage"], "10Gi");
    assert_eq!(
        get(&format!("poddisruptionbudget/{full}"))?["spec"]["maxUnavailable"],
        1
    );
    let dashboards = get("configmaps")?;
    let dashboards = dashboards["items"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|cm| cm["metadata"]["labels"]["grafana_dashboard"] == "1")
        .count();
    assert_eq!(
        dashboards,
        json_files(&repo_root().join("manifests/dashboards")).len()
    );
    let notes = ok(
        cp.tool("helm", &["get", "notes", &ns, "-n", &ns]),
        "helm get notes",
    );
    for want in [
        format!("port-forward svc/{full}-gateway 8081:8081"),
        "fleet.lekiwi.io/token=enrollment".to_owned(),
        "sha256sum".to_owned(),
        "enrollmentTokenFile".to_owned(),
        "lekiwi-release-pusher".to_owned(),
        "kubectl lekiwi release push".to_owned(),
    ] {
        assert!(notes.contains(&want), "NOTES lack {want}:\n{notes}");
    }
    let token = ok(
        cp.kubectl(&["create", "token", &full, "-n", &ns, "--duration=1h"]),
        "kubectl create token",
    );
    let kubeconfig = dir.path().join("kubeconfig-sa");
    cp.kubeconfig_with_token(token.trim(), &kubeconfig)?;

    // The Lease of a gateway gone for two hours, which no robot names: deleted by the
    // controller (under the chart's RBAC).
    let leases = Api::<k8s_openapi::api::coordination::v1::Lease>::namespaced(client.clone(), &ns);
    let two_hours_ago = jiff::Timestamp::now() - jiff::SignedDuration::from_hours(2);
    leases
        .create(
            &Default::default(),
            &serde_json::from_value(json!({
                "metadata": {"name": "gateway-gone", "labels": {"fleet.lekiwi.io/gateway": "true"}},
                "spec": {
                    "holderIdentity": "gateway-gone",
                    "leaseDurationSeconds": 15,
                    "renewTime": two_hours_ago.strftime("%Y-%m-%dT%H:%M:%S%.6fZ").to_string(),
                }
            }))?,
        )
        .await?;
    let mut op = OperatorProcess::start_with_kubeconfig(
        &kubeconfig,
        &ns,
        "chart-sa",
        &["--heartbeat-grace-seconds", "30"],
    )?;
    op.wait_ready().await?;
    wait_for("leadership", Duration::from_secs(10), || async {
        (op.metric("lekiwi_leader_election_is_leader").await == Some(1.0)).then_some(())
    })
    .await?;
    create_robot(&client, &ns, "kiwi-1", &[]).await?;
    let mut gw = GatewayStandIn::start(&client, &ns, "gateway-c", 10).await?;
    gw.connect("kiwi-1").await?;
    wait_for(
        "Online under the chart's RBAC",
        Duration::from_secs(20),
        || async {
            (get_robot(&client, &ns, "kiwi-1").await.ok()?.status?.phase
                == Some(RobotPhase::Online))
            .then_some(())
        },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", op.log_text()))?;
    // A release pushed to the gateway (which checks the pusher's token and permission under the
    // chart's RBAC: TokenReview, SubjectAccessReview) and rolled out: the controller watches the RobotDeployment, patches the robot's
    // spec.release and writes the deployment's status.
    let release = dir.path().join("release");
    std::fs::create_dir_all(release.join("lekiwi"))?;
    std::fs::write(release.join("lekiwi/config.yaml"), "robot_type: lekiwi\n")?;
    let pushed = Command::new(bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(cp.kubeconfig())
        .args([
            "release",
            "push",
            release.to_str().unwrap(),
            "--version",
            "1.0.0",
        ])
        .args(["-n", &ns])
        .args(["--server", &format!("http://127.0.0.1:{}", op.gateway_port)])
        .env_remove("LEKIWI_SERVER")
        .output()?;
    let digest = ok(pushed, "kubectl lekiwi release push").trim().to_owned();
    Api::<Robot>::namespaced(client.clone(), &ns)
        .patch(
            "kiwi-1",
            &PatchParams::default(),
            &Patch::Merge(json!({"metadata": {"labels": {"fleet.lekiwi.io/group": "chart"}}})),
        )
        .await?;
    let rollout: RobotDeployment = serde_json::from_value(json!({
        "apiVersion": "fleet.lekiwi.io/v1alpha1",
        "kind": "RobotDeployment",
        "metadata": {"name": "chart-rollout"},
        "spec": {
            "selector": {"matchLabels": {"fleet.lekiwi.io/group": "chart"}},
            "release": {"version": "1.0.0", "digest": digest},
            "strategy": {"batchSize": 1, "canary": 0, "robotTimeoutSeconds": 60}
        }
    }))?;
    let deployments = Api::<RobotDeployment>::namespaced(client.clone(), &ns);
    deployments.create(&Default::default(), &rollout).await?;
    wait_for(
        "the rollout to reach kiwi-1",
        Duration::from_secs(30),
        || async {
            let robot = get_robot(&client, &ns, "kiwi-1").await.ok()?;
            let status = deployments.get("chart-rollout").await.ok()?.status?;
            (robot.spec.release?.digest == digest && status.targeted == 1).then_some(())
        },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", op.log_text()))?;
    // The Fleet API under the same credentials: its watches, the reviews, and a rollout action
    // the operator patches in once the caller (here the admin) may.
    let admin = format!("Bearer {}", cp.admin_token()?);
    let action = format!("/api/v1/namespaces/{ns}/rollouts/chart-rollout/pause");
    let (code, _, body) = lekiwi_tests::http_request(
        op.gateway_port,
        "POST",
        &action,
        &[("authorization", &admin)],
        Some(b""),
    )
    .await?;
    assert_eq!(code, 200, "{}", String::from_utf8_lossy(&body));
    assert!(deployments.get("chart-rollout").await?.spec.paused);
    let robots = format!("/api/v1/namespaces/{ns}/robots");
    wait_for(
        "the Fleet API's Robot cache",
        Duration::from_secs(10),
        || async {
            let (code, _, body) =
                lekiwi_tests::http_get_with(op.gateway_port, &robots, &[("authorization", &admin)])
                    .await
                    .ok()?;
            (code == 200 && body.contains("kiwi-1")).then_some(())
        },
    )
    .await?;
    wait_for(
        "the stale gateway Lease deleted",
        Duration::from_secs(20),
        || async {
            leases
                .get_opt("gateway-gone")
                .await
                .ok()?
                .is_none()
                .then_some(())
        },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", op.log_text()))?;
    assert!(
        leases.get_opt("gateway-c").await?.is_some(),
        "a live gateway's Lease stays"
    );
    gw.disconnect("kiwi-1").await?;
    wait_for("Offline", Duration::from_secs(10), || async {
        (get_robot(&client, &ns, "kiwi-1").await.ok()?.status?.phase == Some(RobotPhase::Offline))
            .then_some(())
    })
    .await?;
    // The gateway under the same credentials: enrollment (creates a Robot and its token Secret),
    // presence, durable events, a legacy poll.
    let enroll = lekiwi_tests::enrollment_token(&client, &ns).await?;
    let (ws, welcome) = lekiwi_tests::connect_agent(&op, &enroll, &format!("{ns}/kiwi-2")).await?;
    let own = welcome
        .robot_token
        .expect("enrollment returns the robot's token");
    wait_for("enrolled robot Online", Duration::from_secs(20), || async {
        (get_robot(&client, &ns, "kiwi-2").await.ok()?.status?.phase == Some(RobotPhase::Online))
            .then_some(())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", op.log_text()))?;
    drop(ws);
    wait_for(
        "enrolled robot Offline",
        Duration::from_secs(20),
        || async {
            (get_robot(&client, &ns, "kiwi-2").await.ok()?.status?.phase
                == Some(RobotPhase::Offline))
            .then_some(())
        },
    )
    .await?;
    let (code, _, body) = lekiwi_tests::http_get_with(
        op.gateway_port,
        &format!("/v1/poll?robot={ns}/kiwi-2&version=0.1.0"),
        &[("authorization", &format!("Bearer {own}"))],
    )
    .await?;
    assert_eq!(code, 200, "{body}");

    // Events went through too (they are written with the same credentials).
    let events = ok(
        cp.kubectl(&[
            "get",
            "events",
            "-n",
            &ns,
            "-o",
            "jsonpath={.items[*].reason}",
        ]),
        "get events",
    );
    assert!(
        events.contains("RobotOnline") && events.contains("RobotOffline"),
        "events: {events}"
    );
    op.terminate()?;
    let log = op.log_text();
    assert!(
        !log.contains("Forbidden") && !log.contains("forbidden"),
        "RBAC gap:\n{log}"
    );
    assert!(log.contains("released the leader Lease"), "{log}");
    // Cluster-scoped objects go with the release (the volume claim is kept by its policy).
    ok(
        cp.tool("helm", &["uninstall", &ns, "-n", &ns]),
        "helm uninstall",
    );
    Ok(())
}

/// Runs `sh -c script` with `input` on stdin; its stdout.
fn shell(script: &str, input: &str) -> String {
    use std::io::Write;
    let mut child = Command::new("sh")
        .args(["-c", script])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("run sh");
    child
        .stdin
        .take()
        .unwrap()
        .write_all(input.as_bytes())
        .expect("write stdin");
    ok(child.wait_with_output().expect("wait sh"), script)
}

/// The certificate and CA (PEM) of the generated TLS Secret in `docs`, checked: the CA signed
/// the certificate, whose names are the gateway Service's DNS names, localhost and 127.0.0.1.
fn generated_tls(docs: &[Value], full: &str, ns: &str) -> (String, String) {
    let secret = find(docs, "Secret", &format!("{full}-gateway-tls"));
    assert_eq!(secret["type"], "kubernetes.io/tls");
    let field = |k: &str| shell("base64 -d", secret["data"][k].as_str().unwrap());
    let (crt, ca) = (field("tls.crt"), field("ca.crt"));
    assert!(field("tls.key").contains("PRIVATE KEY"));
    let cm = find(docs, "ConfigMap", &format!("{full}-gateway-ca"));
    assert_eq!(cm["data"]["ca.crt"].as_str().unwrap().trim(), ca.trim());
    let dir = tempfile::tempdir().unwrap();
    let (crt_file, ca_file) = (dir.path().join("tls.crt"), dir.path().join("ca.crt"));
    std::fs::write(&crt_file, &crt).unwrap();
    std::fs::write(&ca_file, &ca).unwrap();
    let verify = format!(
        "openssl verify -CAfile {} {}",
        ca_file.display(),
        crt_file.display()
    );
    assert!(
        shell(&verify, "").contains(": OK"),
        "the CA signed the certificate"
    );
    let sans = shell("openssl x509 -noout -ext subjectAltName", &crt);
    let svc = format!("{full}-gateway");
    for name in [
        format!("DNS:{svc}"),
        format!("DNS:{svc}.{ns}"),
        format!("DNS:{svc}.{ns}.svc"),
        format!("DNS:{svc}.{ns}.svc.cluster.local"),
        "DNS:localhost".to_owned(),
        "IP Address:127.0.0.1".to_owned(),
    ] {
        assert!(
            sans.split([',', '\n']).any(|s| s.trim() == name),
            "SAN {name} missing: {sans}"
        );
    }
    (crt, ca)
}

/// TLS is on by default: the chart makes a CA and a certificate for the gateway Service's
/// names, the gateway serves them, NOTES say wss:// and how agents get the CA, and an upgrade
/// keeps the same certificate. `gateway.tls.enabled=false` serves plain text, with a warning.
#[tokio::test]
async fn chart_tls_is_on_by_default_with_a_generated_ca_kept_across_upgrades() -> anyhow::Result<()>
{
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "chart-tls").await?;
    let watch = format!("operator.watchNamespace={ns}");
    let full = format!("{ns}-lekiwi-operator");
    let install = |verb: &str| {
        ok(
            cp.tool(
                "helm",
                &helm_args(verb, &ns, &ns, &watch, &["--wait=false"]),
            ),
            &format!("helm {verb}"),
        )
    };
    install("install");
    let manifest = ok(
        cp.tool("helm", &["get", "manifest", &ns, "-n", &ns]),
        "helm get manifest",
    );
    let docs = documents(&manifest);
    let (crt, ca) = generated_tls(&docs, &full, &ns);
    let deploy = find(&docs, "Deployment", &full);
    let args = serde_yaml::to_string(&deploy["spec"]["template"]["spec"]["containers"][0]["args"])?;
    for flag in [
        "--tls-cert=/etc/lekiwi/tls/tls.crt",
        "--tls-key=/etc/lekiwi/tls/tls.key",
    ] {
        assert!(args.contains(flag), "{flag} missing: {args}");
    }
    let volumes = serde_yaml::to_string(&deploy["spec"]["template"]["spec"]["volumes"])?;
    assert!(
        volumes.contains(&format!("secretName: {full}-gateway-tls")),
        "{volumes}"
    );
    let notes = ok(
        cp.tool("helm", &["get", "notes", &ns, "-n", &ns]),
        "helm get notes",
    );
    for want in [
        "gateway: wss://".to_owned(),
        "caFile: /etc/lekiwi/ca.crt".to_owned(),
        format!("get configmap {full}-gateway-ca -o jsonpath"),
        "--certificate-authority ca.crt".to_owned(),
    ] {
        assert!(notes.contains(&want), "NOTES lack {want}:\n{notes}");
    }
    assert!(!notes.contains("ws://<"), "{notes}");

    // An upgrade keeps the certificate and its CA (agents trust that CA).
    install("upgrade");
    let manifest = ok(
        cp.tool("helm", &["get", "manifest", &ns, "-n", &ns]),
        "helm get manifest",
    );
    let (crt_after, ca_after) = generated_tls(&documents(&manifest), &full, &ns);
    assert_eq!(crt_after, crt, "the upgrade made a new certificate");
    assert_eq!(ca_after, ca, "the upgrade made a new CA");
    let docs = documents(&manifest);
    let api = find(&docs, "Service", &format!("{full}-api"));
    assert_eq!(
        api["metadata"]["labels"]["app.kubernetes.io/component"],
        "api"
    );
    find(&docs, "Secret", &format!("{full}-gateway-ca-key"));

    // Names added on upgrade: a new certificate for them, signed by the same CA.
    let names = [
        "--wait=false",
        "--set",
        "gateway.tls.extraDnsNames={robots.lab.example}",
        "--set",
        "gateway.tls.extraIpAddresses={10.9.8.7}",
    ];
    ok(
        cp.tool("helm", &helm_args("upgrade", &ns, &ns, &watch, &names)),
        "helm upgrade (more names)",
    );
    let manifest = ok(
        cp.tool("helm", &["get", "manifest", &ns, "-n", &ns]),
        "helm get manifest",
    );
    let (crt_named, ca_named) = generated_tls(&documents(&manifest), &full, &ns);
    assert_eq!(ca_named, ca, "more names made a new CA");
    assert_ne!(crt_named, crt, "more names kept the old certificate");
    let sans = shell("openssl x509 -noout -ext subjectAltName", &crt_named);
    assert!(
        sans.contains("DNS:robots.lab.example") && sans.contains("IP Address:10.9.8.7"),
        "{sans}"
    );
    serves_the_generated_certificate(cp, &ns, &documents(&manifest), &full).await?;
    ok(
        cp.tool("helm", &["uninstall", &ns, "-n", &ns]),
        "helm uninstall",
    );

    // Plain text only when asked for, with a warning.
    let plain = ok(
        helm(&[
            "install",
            "plain",
            CHART,
            "-n",
            &ns,
            "--dry-run=client",
            "--set",
            "gateway.tls.enabled=false",
        ]),
        "helm install --dry-run (plain)",
    );
    assert!(!plain.contains("--tls-cert"), "{plain}");
    assert!(!plain.contains("kind: Secret\n"), "no TLS Secret: {plain}");
    assert!(plain.contains("gateway: ws://<gateway address>"), "{plain}");
    assert!(
        plain.contains("WARNING: gateway.tls.enabled=false"),
        "{plain}"
    );
    Ok(())
}

/// The gateway serves the chart's generated certificate: an agent given the CA from the
/// ConfigMap connects over wss://127.0.0.1, one without it refuses the certificate.
async fn serves_the_generated_certificate(
    cp: &ControlPlane,
    ns: &str,
    docs: &[Value],
    full: &str,
) -> anyhow::Result<()> {
    let secret = find(docs, "Secret", &format!("{full}-gateway-tls"));
    let dir = tempfile::tempdir()?;
    let path = |name: &str| dir.path().join(name);
    for key in ["tls.crt", "tls.key"] {
        let pem = shell("base64 -d", secret["data"][key].as_str().unwrap());
        std::fs::write(path(key), pem)?;
    }
    let cm = find(docs, "ConfigMap", &format!("{full}-gateway-ca"));
    std::fs::write(path("ca.crt"), cm["data"]["ca.crt"].as_str().unwrap())?;
    let (crt, key) = (path("tls.crt"), path("tls.key"));
    let args = [
        "--tls-cert",
        crt.to_str().unwrap(),
        "--tls-key",
        key.to_str().unwrap(),
    ];
    let mut op = OperatorProcess::start(cp, ns, "chart-tls", &args)?;
    op.wait_ready().await?;
    let client = cp.client().await?;
    let creds = lekiwi_agent::connection::Credentials {
        token: lekiwi_tests::enrollment_token(&client, ns).await?,
        robot: format!("{ns}/kiwi-tls"),
    };
    let url = format!("wss://127.0.0.1:{}/v1/agent", op.gateway_port);
    let connect = |ca: Option<std::path::PathBuf>| {
        let (url, creds) = (url.clone(), creds.clone());
        async move {
            let hello = lekiwi_tests::hello();
            let timeout = Duration::from_secs(10);
            lekiwi_agent::connection::connect_with_ca(&url, &creds, &hello, timeout, ca.as_deref())
                .await
        }
    };
    assert!(
        connect(None).await.is_err(),
        "an agent without the chart's CA accepted the certificate"
    );
    let (_ws, welcome) = connect(Some(path("ca.crt")))
        .await
        .map_err(|e| anyhow::anyhow!("an agent trusting the chart's CA: {e:?}"))?;
    assert_eq!(welcome.robot, format!("{ns}/kiwi-tls"));
    op.terminate()?;
    Ok(())
}
