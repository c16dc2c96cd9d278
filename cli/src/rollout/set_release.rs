//! `rollout set-release NAME --version V [--digest D]`: rolls another release out by setting
//! `spec.release`; without `--digest`, the digest of VERSION is looked up among the releases
//! pushed to the gateway (`GET /api/v1/namespaces/NS/releases`) or, on a gateway without that
//! route, among the releases the namespace's Robots and RobotDeployments name (what robots
//! run and were told to run, rollouts' targets and what their robots ran before).

use std::collections::BTreeSet;

use anyhow::bail;
use kube::Api;
use lekiwi_crds::{ReleaseRef, Robot, RobotDeployment};
use reqwest::{Method, StatusCode};
use serde_json::{Value, json};

use crate::release::{Gateway, ServerArgs};

/// Arguments of `rollout set-release`.
#[derive(Debug, clap::Args)]
pub struct SetReleaseArgs {
    /// The RobotDeployment.
    pub name: String,
    /// The release's version, as pushed (`release push --version`).
    #[arg(long)]
    pub version: String,
    /// The release manifest's digest (`sha256:...`, as `release push` prints it): no lookup.
    #[arg(long)]
    pub digest: Option<String>,
    /// Where the gateway is, for the lookup.
    #[command(flatten)]
    pub server: ServerArgs,
}

/// Sets the release and says so, as kubectl does (`robotdeployment/NAME release set to ...`).
pub(super) async fn run(
    kube: &crate::KubeContext,
    api: &Api<RobotDeployment>,
    args: SetReleaseArgs,
) -> anyhow::Result<()> {
    let digest = match args.digest {
        Some(d) => d,
        None => lookup(kube, &args.server, &args.version).await?,
    };
    let release = json!({"version": args.version, "digest": digest});
    super::merge(api, &args.name, json!({"spec": {"release": release}})).await?;
    println!(
        "robotdeployment/{} release set to {} ({digest})",
        args.name, args.version
    );
    Ok(())
}

/// The digest of `version` in the namespace: from the gateway's release list, else from the
/// releases its Robots and RobotDeployments name; an error when none or several match.
async fn lookup(
    kube: &crate::KubeContext,
    server: &ServerArgs,
    version: &str,
) -> anyhow::Result<String> {
    let ns = kube.namespace.as_str();
    let (digests, source) = match pushed(kube, server, version).await {
        Ok(Some(digests)) => (digests, "the releases pushed to the gateway"),
        Ok(None) => (
            known(kube, version).await?,
            "the namespace's robots and rollouts",
        ),
        Err(e) => {
            eprintln!("warning: cannot list the gateway's releases ({e:#}); looking at the robots");
            (
                known(kube, version).await?,
                "the namespace's robots and rollouts",
            )
        }
    };
    match digests.len() {
        1 => Ok(digests.into_iter().next().unwrap_or_default()),
        0 => bail!(
            "no release {version:?} among {source} in namespace {ns}: push it (kubectl lekiwi release push), or pass --digest"
        ),
        _ => bail!(
            "release {version:?} has several digests among {source} in namespace {ns} ({}): pass --digest",
            digests.into_iter().collect::<Vec<_>>().join(", ")
        ),
    }
}

/// Digests of `version` among the gateway's releases of the namespace; `None` when the gateway
/// has no release list (404: older than the route).
async fn pushed(
    kube: &crate::KubeContext,
    server: &ServerArgs,
    version: &str,
) -> anyhow::Result<Option<BTreeSet<String>>> {
    let gateway = Gateway::connect_api(kube, server).await?;
    let path = format!("/api/v1/namespaces/{}/releases", kube.namespace);
    let resp = gateway
        .request(Method::GET, &path)
        .send()
        .await
        .map_err(|e| anyhow::anyhow!("{}: {}", gateway.base, crate::http_error(&e)))?;
    match resp.status() {
        StatusCode::OK => {}
        StatusCode::NOT_FOUND => return Ok(None),
        s => bail!("{path}: {s}: {}", crate::release::message(resp).await),
    }
    Ok(Some(matching(&resp.json::<Value>().await?, version)))
}

/// Digests of `version` in a release list: an array, or an object with `items`, of objects
/// with `version` and `digest`.
fn matching(list: &Value, version: &str) -> BTreeSet<String> {
    let items = list
        .get("items")
        .and_then(Value::as_array)
        .or(list.as_array())
        .map(Vec::as_slice)
        .unwrap_or_default();
    items
        .iter()
        .filter(|r| r.get("version").and_then(Value::as_str) == Some(version))
        .filter_map(|r| r.get("digest").and_then(Value::as_str).map(str::to_owned))
        .collect()
}

/// Digests of `version` among the releases the namespace's Robots (desired, running) and
/// RobotDeployments (target, and what their robots ran before) name.
async fn known(kube: &crate::KubeContext, version: &str) -> anyhow::Result<BTreeSet<String>> {
    let ns = kube.namespace.as_str();
    let lp = kube::api::ListParams::default();
    let robots = Api::<Robot>::namespaced(kube.client.clone(), ns)
        .list(&lp)
        .await?;
    let rollouts = Api::<RobotDeployment>::namespaced(kube.client.clone(), ns)
        .list(&lp)
        .await?;
    let refs: Vec<&ReleaseRef> = robots
        .items
        .iter()
        .flat_map(|r| {
            let st = r.status.as_ref();
            [
                r.spec.release.as_ref(),
                st.and_then(|s| s.current_release.as_ref()),
            ]
        })
        .chain(rollouts.items.iter().flat_map(|d| {
            let rows = d.status.iter().flat_map(|s| &s.robots);
            let before = rows.map(|r| r.previous_release.as_ref());
            std::iter::once(d.spec.release.as_ref()).chain(before)
        }))
        .flatten()
        .collect();
    Ok(refs
        .into_iter()
        .filter(|r| r.version == *version)
        .map(|r| r.digest.to_string())
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_release_list_is_read_by_version() {
        let list = json!({"items": [
            {"version": "1.0.0", "digest": "sha256:a"},
            {"version": "2.0.0", "digest": "sha256:b"},
        ]});
        assert_eq!(
            matching(&list, "2.0.0"),
            BTreeSet::from(["sha256:b".to_owned()])
        );
        let bare = json!([{"version": "2.0.0", "digest": "sha256:c"}]);
        assert_eq!(matching(&bare, "2.0.0").len(), 1);
        assert!(matching(&json!({}), "2.0.0").is_empty());
    }
}
