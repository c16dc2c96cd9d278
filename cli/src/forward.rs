//! A port on this machine's loopback forwarded to the gateway through the API server (kube's
//! portforward, as `kubectl port-forward` does it, to a ready Pod of the gateway Service), so
//! the plugin reaches the gateway from the kubeconfig alone: no port to forward by hand.
//!
//! The API server's service proxy is not used: it drops the `Authorization` header once it has
//! authenticated the user, and the gateway needs the user's token to ask RBAC.

use std::net::SocketAddr;

use anyhow::{Context as _, bail};
use k8s_openapi::api::core::v1::Pod;
use k8s_openapi::apimachinery::pkg::util::intstr::IntOrString;
use kube::api::ListParams;
use kube::{Api, ResourceExt};

use crate::locate::Located;

/// A local port forwarded to the gateway; closed when dropped.
pub struct Forward {
    /// Where to connect: `127.0.0.1` and a port of the system's choosing.
    pub local: SocketAddr,
    /// Whether the gateway serves TLS on that port (its Pod runs with `--tls-cert`).
    pub tls: bool,
    task: tokio::task::JoinHandle<()>,
}

impl Drop for Forward {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// A ready Pod behind the gateway Service and the port the Service sends to in it.
async fn target(client: &kube::Client, gw: &Located) -> anyhow::Result<(Pod, u16)> {
    let selector: Vec<String> = gw
        .selector
        .iter()
        .map(|(k, v)| format!("{k}={v}"))
        .collect();
    if selector.is_empty() {
        bail!("the gateway Service {} selects no Pods", gw.service);
    }
    let pods: Api<Pod> = Api::namespaced(client.clone(), &gw.namespace);
    let list = pods
        .list(&ListParams::default().labels(&selector.join(",")))
        .await
        .with_context(|| format!("cannot list the gateway's Pods in {}", gw.namespace))?;
    let ready = |p: &&Pod| {
        p.status
            .as_ref()
            .and_then(|s| s.conditions.as_ref())
            .is_some_and(|c| c.iter().any(|c| c.type_ == "Ready" && c.status == "True"))
    };
    let Some(pod) = list.items.iter().find(ready) else {
        bail!(
            "no ready Pod behind the gateway Service {}/{}",
            gw.namespace,
            gw.service
        );
    };
    let containers = pod
        .spec
        .as_ref()
        .map(|s| s.containers.as_slice())
        .unwrap_or_default();
    let port = match &gw.target_port {
        Some(IntOrString::Int(p)) => Some(*p),
        Some(IntOrString::String(name)) => containers
            .iter()
            .flat_map(|c| c.ports.iter().flatten())
            .find(|p| p.name.as_deref() == Some(name))
            .map(|p| p.container_port),
        None => Some(i32::from(gw.port)),
    };
    let port = port.and_then(|p| u16::try_from(p).ok()).with_context(|| {
        format!(
            "the gateway Pod {} has no port {:?}",
            pod.name_any(),
            gw.target_port
        )
    })?;
    Ok((pod.clone(), port))
}

/// Whether the Pod's gateway serves TLS: it is started with `--tls-cert` (flag or environment).
fn serves_tls(pod: &Pod) -> bool {
    pod.spec.iter().flat_map(|s| &s.containers).any(|c| {
        c.args.iter().flatten().any(|a| a.starts_with("--tls-cert"))
            || c.env.iter().flatten().any(|e| e.name == "LEKIWI_TLS_CERT")
    })
}

/// Opens the forward: a listener on the loopback whose every connection becomes a port-forward
/// stream to the gateway Pod.
pub async fn open(client: &kube::Client, gw: &Located) -> anyhow::Result<Forward> {
    let (pod, port) = target(client, gw).await?;
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let local = listener.local_addr()?;
    let pods: Api<Pod> = Api::namespaced(client.clone(), &gw.namespace);
    let name = pod.name_any();
    let task = tokio::spawn(async move {
        while let Ok((mut tcp, _)) = listener.accept().await {
            let pods = pods.clone();
            let name = name.clone();
            tokio::spawn(async move {
                let Ok(mut forwarder) = pods.portforward(&name, &[port]).await else {
                    return;
                };
                if let Some(mut stream) = forwarder.take_stream(port) {
                    let _ = tokio::io::copy_bidirectional(&mut tcp, &mut stream).await;
                    drop(stream);
                }
                let _ = forwarder.join().await;
            });
        }
    });
    Ok(Forward {
        local,
        tls: serves_tls(&pod),
        task,
    })
}
