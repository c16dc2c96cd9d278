//! A real node (`scripts/testbed/cluster.sh`): a Pod from a locally built and imported image runs with a
//! Pod IP under a locked-down securityContext that is enforced (non-root user, read-only root
//! filesystem, no capabilities, seccomp filter; a root container is refused), its PVC binds to
//! the default StorageClass and the Pod writes to it, a Service reaches it through kube-proxy by
//! ClusterIP and by NodePort from the host, and `kubectl logs` reads its output. The node lives in
//! a network namespace of its own: the host's holds none of its bridge, addresses or iptables
//! chains.

use std::net::SocketAddr;
use std::time::Duration;

use k8s_openapi::api::core::v1::{
    PersistentVolume, PersistentVolumeClaim, Pod, Service, ServiceAccount,
};
use kube::Api;
use kube::api::PostParams;
use lekiwi_tests::cluster::{Cluster, busybox_image, http_get_at};
use lekiwi_tests::netns::NetView;
use lekiwi_tests::{namespace, wait_for};
use serde_json::json;

const IMAGE: &str = "lekiwi.local/busybox-httpd:test";
const PAGE: &str = "served-by-a-real-pod";

/// The container's script: reports what the kernel enforces on it, writes to the claim, serves.
const SCRIPT: &str = "b=/bin/busybox; echo uid=$($b id -u); \
    $b grep -E '^(CapEff|Seccomp):' /proc/self/status; \
    if $b touch /probe 2>/dev/null; then echo rootfs=writable; else echo rootfs=readonly; fi; \
    echo pvc-ok > /data/written && echo pvc=written; \
    exec $b httpd -f -p 8080 -h /www";

fn locked_down(run_as_user: i64) -> serde_json::Value {
    json!({
        "runAsNonRoot": true,
        "runAsUser": run_as_user,
        "readOnlyRootFilesystem": true,
        "allowPrivilegeEscalation": false,
        "capabilities": {"drop": ["ALL"]},
        "seccompProfile": {"type": "RuntimeDefault"},
    })
}

fn pod(name: &str, run_as_user: i64, claim: Option<&str>) -> Pod {
    let mut spec = json!({
        "automountServiceAccountToken": false,
        "terminationGracePeriodSeconds": 1,
        "containers": [{
            "name": "web",
            "image": IMAGE,
            "imagePullPolicy": "Never",
            "command": ["/bin/busybox", "sh", "-c", SCRIPT],
            "ports": [{"containerPort": 8080}],
            "securityContext": locked_down(run_as_user),
            "volumeMounts": [],
        }],
    });
    if let Some(claim) = claim {
        spec["containers"][0]["volumeMounts"] = json!([{"name": "data", "mountPath": "/data"}]);
        spec["volumes"] = json!([{"name": "data", "persistentVolumeClaim": {"claimName": claim}}]);
    }
    serde_json::from_value(json!({
        "metadata": {"name": name, "labels": {"app": name}},
        "spec": spec,
    }))
    .expect("pod")
}

/// Builds the busybox image and imports it into the node's containerd.
fn import_busybox(cluster: &Cluster) {
    let tmp = tempfile::tempdir().expect("tempdir");
    let page = tmp.path().join("index.html");
    std::fs::write(&page, PAGE).expect("write page");
    let archive = tmp.path().join("busybox.tar");
    let files = [format!("{}:/www/index.html", page.display())];
    busybox_image(&archive, IMAGE, &files).expect("build the busybox image");
    cluster.import_image(&archive).expect("import the image");
}

/// Deletes the test's namespace however the test ends, so its claim releases the PV (the next
/// `cluster.sh up` makes it Available again).
struct DeleteNamespace<'a>(&'a Cluster, String);

impl Drop for DeleteNamespace<'_> {
    fn drop(&mut self) {
        let _ = self
            .0
            .kubectl(&["delete", "namespace", &self.1, "--wait=false"]);
    }
}

async fn wait_running(pods: &Api<Pod>, cluster: &Cluster, ns: &str, name: &str) -> String {
    let found = wait_for(
        "the Pod Running with a Pod IP",
        Duration::from_secs(90),
        || async {
            let p = pods.get(name).await.ok()?;
            let status = p.status?;
            (status.phase.as_deref() == Some("Running")).then_some(status.pod_ip?)
        },
    )
    .await;
    found.unwrap_or_else(|e| {
        let why = cluster.kubectl(&["-n", ns, "describe", "pod", name]);
        panic!("{e}:\n{}", why.unwrap_or_else(|e| e.to_string()))
    })
}

#[tokio::test(flavor = "multi_thread")]
async fn pods_run_serve_store_and_log_on_a_real_node() {
    let cluster = Cluster::shared();
    let client = cluster.client().await.expect("client");
    import_busybox(cluster);
    let ns = namespace(&client, "node").await.expect("namespace");
    let _cleanup = DeleteNamespace(cluster, ns.clone());
    // The ServiceAccount admission plugin refuses Pods until the controller-manager made the
    // namespace's default ServiceAccount.
    let accounts: Api<ServiceAccount> = Api::namespaced(client.clone(), &ns);
    wait_for(
        "the default ServiceAccount",
        Duration::from_secs(30),
        || async { accounts.get_opt("default").await.ok().flatten() },
    )
    .await
    .expect("default ServiceAccount");

    // A claim without a class gets the default one and binds to a pre-made PV.
    let claims: Api<PersistentVolumeClaim> = Api::namespaced(client.clone(), &ns);
    let claim: PersistentVolumeClaim = serde_json::from_value(json!({
        "metadata": {"name": "data"},
        "spec": {"accessModes": ["ReadWriteOnce"], "resources": {"requests": {"storage": "100Mi"}}},
    }))
    .unwrap();
    claims
        .create(&PostParams::default(), &claim)
        .await
        .expect("create PVC");
    let volume = wait_for("the PVC Bound", Duration::from_secs(30), || async {
        let c = claims.get("data").await.ok()?;
        (c.status?.phase.as_deref() == Some("Bound")).then_some(c.spec?)
    })
    .await
    .expect("PVC bound");
    assert_eq!(volume.storage_class_name.as_deref(), Some("standard"));
    let pv = Api::<PersistentVolume>::all(client.clone())
        .get(volume.volume_name.as_deref().expect("volume name"))
        .await
        .expect("bound PV");
    let host_dir = pv.spec.unwrap().host_path.expect("hostPath PV").path;

    let pods: Api<Pod> = Api::namespaced(client.clone(), &ns);
    pods.create(&PostParams::default(), &pod("web", 65532, Some("data")))
        .await
        .expect("create Pod");
    let pod_ip = wait_running(&pods, cluster, &ns, "web").await;
    assert!(
        cluster
            .pod_cidr
            .contains(&pod_ip.parse::<std::net::IpAddr>().expect("Pod IP")),
        "Pod IP {pod_ip} is not from the bridge's range"
    );

    // The securityContext is enforced, as the container itself sees it, and the claim written.
    let logs = wait_for(
        "the container's report in kubectl logs",
        Duration::from_secs(20),
        || {
            let logs = cluster
                .kubectl(&["-n", &ns, "logs", "web"])
                .unwrap_or_default();
            async move { logs.contains("pvc=written").then_some(logs) }
        },
    )
    .await
    .expect("kubectl logs");
    for line in [
        "uid=65532",
        "CapEff:\t0000000000000000",
        "Seccomp:\t2",
        "rootfs=readonly",
    ] {
        assert!(
            logs.lines().any(|l| l == line),
            "no `{line}` in the Pod's logs:\n{logs}"
        );
    }
    let written = std::fs::read_to_string(format!("{host_dir}/written")).expect("the PV's file");
    assert_eq!(written.trim(), "pvc-ok");

    // kube-proxy: the Service by its ClusterIP and by the NodePort on the node's IP.
    let service: Service = serde_json::from_value(json!({
        "metadata": {"name": "web"},
        "spec": {"type": "NodePort", "selector": {"app": "web"},
                 "ports": [{"port": 80, "targetPort": 8080}]},
    }))
    .unwrap();
    let service = Api::<Service>::namespaced(client.clone(), &ns)
        .create(&PostParams::default(), &service)
        .await
        .expect("create Service");
    let spec = service.spec.expect("service spec");
    let cluster_ip: SocketAddr = format!("{}:80", spec.cluster_ip.expect("ClusterIP"))
        .parse()
        .unwrap();
    let node_port = spec.ports.unwrap()[0].node_port.expect("nodePort");
    let node_port: SocketAddr = format!("{}:{node_port}", cluster.node_ip).parse().unwrap();
    for addr in [cluster_ip, node_port] {
        let body = wait_for(
            &format!("the page through {addr}"),
            Duration::from_secs(30),
            || async move {
                let (code, body) = http_get_at(addr, "/index.html").await.ok()?;
                (code == 200).then_some(body)
            },
        )
        .await
        .expect("Service reachable through kube-proxy");
        assert_eq!(body, PAGE);
    }

    // runAsNonRoot is enforced by the kubelet, not just stored: a root container never starts.
    pods.create(&PostParams::default(), &pod("root", 0, None))
        .await
        .expect("create the root Pod");
    let reason = wait_for(
        "the root container refused",
        Duration::from_secs(60),
        || async {
            let p = pods.get("root").await.ok()?;
            let state = p.status?.container_statuses?.first()?.state.clone()?;
            state
                .waiting?
                .reason
                .filter(|r| r == "CreateContainerConfigError")
        },
    )
    .await;
    assert!(reason.is_ok(), "{reason:?}");
}

/// While the node is up, the host's network namespace holds no bridge of the node, no node IP,
/// Pod- or Service-range address, no route into those ranges but through the node IP, and no
/// `KUBE-*`/`CNI-*` iptables chain: all of them are in the node's namespace (checked too, so the
/// check looks for things that exist).
#[test]
fn the_hosts_network_namespace_holds_nothing_of_the_node() {
    let cluster = Cluster::shared();
    let host = NetView::of(None).expect("the host's network namespace");
    let traces = cluster.traces_in(&host);
    assert!(
        traces.is_empty(),
        "the host's network namespace holds the node's {traces:#?}"
    );
    let node = NetView::of(Some(&cluster.netns)).expect("the node's network namespace");
    let traces = cluster.traces_in(&node);
    for wanted in [
        format!("bridge {}", cluster.bridge),
        format!("address {}/", cluster.node_ip),
        format!("route to {} on {}", cluster.pod_cidr, cluster.bridge),
        "iptables chain KUBE-SERVICES".to_owned(),
    ] {
        assert!(
            traces.iter().any(|t| t.starts_with(&wanted)),
            "no `{wanted}` in the node's network namespace: {traces:#?}"
        );
    }
}
