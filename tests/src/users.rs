//! People and tools as the Fleet API sees them: the chart's user ClusterRoles, and
//! ServiceAccounts bound to them with tokens from `kubectl create token`.

use anyhow::{Context as _, Result, ensure};
use k8s_openapi::api::core::v1::ServiceAccount;
use k8s_openapi::api::rbac::v1::{ClusterRole, RoleBinding};
use kube::Api;
use kube::api::{DeleteParams, PostParams};
use serde_json::{Value, json};

use crate::ControlPlane;

/// The chart's user ClusterRoles, created under names of this test (cluster-scoped) and
/// without the aggregation labels, so the shared cluster's built-in roles stay as they are.
/// Returns the names of the viewer and the operator user.
pub async fn chart_roles(
    cp: &ControlPlane,
    client: &kube::Client,
    prefix: &str,
) -> Result<[String; 2]> {
    chart_roles_named(
        cp,
        client,
        prefix,
        ["lekiwi-viewer", "lekiwi-operator-user"],
    )
    .await
}

/// Every user ClusterRole of the chart (`helm template`), created as `chart_roles` says;
/// returns the new names of the roles `wanted` names, in that order.
pub async fn chart_roles_named<const N: usize>(
    cp: &ControlPlane,
    client: &kube::Client,
    prefix: &str,
    wanted: [&str; N],
) -> Result<[String; N]> {
    let out = cp.tool(
        "helm",
        &[
            "template",
            "r",
            "charts/lekiwi-operator",
            "--show-only",
            "templates/user-roles.yaml",
            // Rendered without the cluster: the chart's CA would be refused otherwise.
            "--set",
            "gateway.tls.allowNewCaWithoutCluster=true",
        ],
    );
    ensure!(
        out.status.success(),
        "helm template: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let api = Api::<ClusterRole>::all(client.clone());
    let mut names = Vec::new();
    for doc in String::from_utf8(out.stdout)?.split("\n---") {
        let Ok(value) = serde_yaml::from_str::<Value>(doc) else {
            continue;
        };
        let Some(name) = value["metadata"]["name"].as_str() else {
            continue;
        };
        let renamed = format!("{prefix}-{name}");
        let role = json!({"metadata": {"name": renamed}, "rules": value["rules"]});
        let _ = api.delete(&renamed, &DeleteParams::default()).await;
        api.create(&PostParams::default(), &serde_json::from_value(role)?)
            .await
            .with_context(|| format!("create ClusterRole {renamed}"))?;
        names.push((name.to_owned(), renamed));
    }
    let find = |want: &str| {
        names
            .iter()
            .find(|(n, _)| n == want)
            .map(|(_, r)| r.clone())
            .with_context(|| format!("the chart has no ClusterRole {want}: {names:?}"))
    };
    let mut found = Vec::with_capacity(N);
    for want in wanted {
        found.push(find(want)?);
    }
    Ok(found.try_into().expect("one name for each wanted role"))
}

/// A ServiceAccount `name` in `ns`, bound to ClusterRole `role` there when one is given; its
/// token as `kubectl create token` makes it.
pub async fn account(
    cp: &ControlPlane,
    client: &kube::Client,
    ns: &str,
    name: &str,
    role: Option<&str>,
) -> Result<String> {
    Api::<ServiceAccount>::namespaced(client.clone(), ns)
        .create(
            &PostParams::default(),
            &serde_json::from_value(json!({"metadata": {"name": name}}))?,
        )
        .await?;
    if let Some(role) = role {
        let binding = json!({
            "metadata": {"name": name},
            "roleRef": {"apiGroup": "rbac.authorization.k8s.io", "kind": "ClusterRole", "name": role},
            "subjects": [{"kind": "ServiceAccount", "name": name, "namespace": ns}],
        });
        Api::<RoleBinding>::namespaced(client.clone(), ns)
            .create(&PostParams::default(), &serde_json::from_value(binding)?)
            .await?;
    }
    let out = cp.kubectl(&["create", "token", name, "-n", ns, "--duration=1h"]);
    ensure!(
        out.status.success(),
        "kubectl create token: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    Ok(String::from_utf8(out.stdout)?.trim().to_owned())
}
