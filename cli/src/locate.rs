//! The chart's gateway as the cluster knows it, in `--gateway-namespace`: its Service (label
//! `app.kubernetes.io/component=gateway`, the port named `gateway`), the CA ConfigMap that
//! signs its certificate (same label, key `ca.crt`), and the address robots reach it at.

use anyhow::{Context as _, bail};
use k8s_openapi::api::core::v1::{ConfigMap, Node, Service};
use kube::api::ListParams;
use kube::{Api, ResourceExt};

/// The gateway namespace when neither the flag nor its environment variable says.
pub const DEFAULT_GATEWAY_NAMESPACE: &str = "lekiwi-system";
/// The label the chart puts on the gateway's Service and CA ConfigMap.
pub const COMPONENT_SELECTOR: &str = "app.kubernetes.io/component=gateway";
/// Name of the Service port robots (and the plugin) use.
pub const GATEWAY_PORT_NAME: &str = "gateway";

/// The gateway the chart installed.
#[derive(Clone, Debug)]
pub struct Located {
    /// Its namespace.
    pub namespace: String,
    /// The Service's name.
    pub service: String,
    /// The Service port named `gateway` (or its only port).
    pub port: u16,
    /// The Service's type and how robots reach it.
    pub service_type: String,
    /// The NodePort of that port, if any.
    pub node_port: Option<u16>,
    /// The load balancer's address, if any.
    pub ingress: Option<String>,
    /// The CA that signs its certificate (PEM), when the chart made one.
    pub ca_pem: Option<String>,
    /// The Service's Pod selector.
    pub selector: std::collections::BTreeMap<String, String>,
    /// The port in the Pods that the Service port sends to.
    pub target_port: Option<k8s_openapi::apimachinery::pkg::util::intstr::IntOrString>,
}

/// Finds the gateway in `namespace`. Services labelled as the gateway's component are taken in
/// name order, the first with a port named `gateway` (a chart may add other Services with the
/// label, e.g. for the API).
pub async fn locate(client: &kube::Client, namespace: &str) -> anyhow::Result<Located> {
    match find(client, namespace, COMPONENT_SELECTOR, GATEWAY_PORT_NAME).await? {
        Some(found) => Ok(found),
        None => bail!(
            "no gateway Service (label {COMPONENT_SELECTOR}, port `{GATEWAY_PORT_NAME}`) in \
             namespace {namespace}: pass --gateway-namespace (or LEKIWI_GATEWAY_NAMESPACE) with \
             the namespace the chart is installed in"
        ),
    }
}

/// Finds the Fleet API in `namespace`: the chart's API Service (label
/// `app.kubernetes.io/component=api`, port `api`) when it serves the API apart, else the
/// gateway, which then serves it too.
pub async fn locate_api(client: &kube::Client, namespace: &str) -> anyhow::Result<Located> {
    match find(client, namespace, API_SELECTOR, API_PORT_NAME).await? {
        Some(found) => Ok(found),
        None => locate(client, namespace).await,
    }
}

/// The label the chart puts on the Fleet API's own Service.
pub const API_SELECTOR: &str = "app.kubernetes.io/component=api";
/// Name of the Service port of the Fleet API.
pub const API_PORT_NAME: &str = "api";

/// The first Service labelled `selector` (in name order) with a port named `port_name` (or a
/// single port), with the gateway's CA.
async fn find(
    client: &kube::Client,
    namespace: &str,
    selector: &str,
    port_name: &str,
) -> anyhow::Result<Option<Located>> {
    let by_label = ListParams::default().labels(selector);
    let services: Api<Service> = Api::namespaced(client.clone(), namespace);
    let mut found = services.list(&by_label).await.with_context(|| {
        format!("cannot list Services in namespace {namespace} (the gateway's namespace)")
    })?;
    found.items.sort_by_key(|s| s.name_any());
    let Some((svc, port)) = found.items.iter().find_map(|s| {
        let ports = s.spec.as_ref()?.ports.as_ref()?;
        let port = ports
            .iter()
            .find(|p| p.name.as_deref() == Some(port_name))
            .or_else(|| (ports.len() == 1).then(|| &ports[0]))?;
        Some((s, port.clone()))
    }) else {
        return Ok(None);
    };
    let spec = svc.spec.clone().unwrap_or_default();
    let ingress = svc
        .status
        .as_ref()
        .and_then(|s| s.load_balancer.as_ref())
        .and_then(|lb| lb.ingress.as_ref())
        .and_then(|i| i.first())
        .and_then(|i| i.ip.clone().or_else(|| i.hostname.clone()));
    Ok(Some(Located {
        namespace: namespace.to_owned(),
        service: svc.name_any(),
        port: u16::try_from(port.port).context("the gateway Service's port is out of range")?,
        service_type: spec.type_.clone().unwrap_or_else(|| "ClusterIP".into()),
        node_port: port.node_port.and_then(|p| u16::try_from(p).ok()),
        ingress,
        ca_pem: ca_pem(client, namespace).await?,
        selector: spec.selector.clone().unwrap_or_default(),
        target_port: port.target_port.clone(),
    }))
}

/// The `ca.crt` of the gateway's CA ConfigMap, if the chart made one.
async fn ca_pem(client: &kube::Client, namespace: &str) -> anyhow::Result<Option<String>> {
    let maps: Api<ConfigMap> = Api::namespaced(client.clone(), namespace);
    let mut found = maps
        .list(&ListParams::default().labels(COMPONENT_SELECTOR))
        .await
        .with_context(|| format!("cannot list ConfigMaps in namespace {namespace}"))?;
    found.items.sort_by_key(|m| m.name_any());
    Ok(found
        .items
        .into_iter()
        .find_map(|m| m.data?.remove("ca.crt")))
}

impl Located {
    /// The pin of the gateway's CA (`sha256:...`), when the chart published it.
    pub fn ca_cert_hash(&self) -> anyhow::Result<Option<String>> {
        use rustls_pki_types::CertificateDer;
        use rustls_pki_types::pem::PemObject as _;
        let Some(pem) = &self.ca_pem else {
            return Ok(None);
        };
        let cert = CertificateDer::pem_slice_iter(pem.as_bytes())
            .next()
            .context("the gateway's CA ConfigMap holds no certificate")??;
        Ok(Some(lekiwi_protocol::join::ca_cert_hash(&cert)?))
    }

    /// The agent URL robots use: the load balancer's address, else a node's address and the
    /// NodePort; `None` for a ClusterIP Service, which robots outside the cluster cannot reach.
    pub async fn robot_url(&self, client: &kube::Client) -> anyhow::Result<Option<String>> {
        let url = |host: &str, port: u16| {
            let host = if host.contains(':') {
                format!("[{host}]")
            } else {
                host.to_owned()
            };
            format!("wss://{host}:{port}{}", lekiwi_protocol::AGENT_PATH)
        };
        if let Some(ingress) = &self.ingress {
            return Ok(Some(url(ingress, self.port)));
        }
        let Some(node_port) = self.node_port else {
            return Ok(None);
        };
        let nodes: Api<Node> = Api::all(client.clone());
        let list = nodes
            .list(&ListParams::default())
            .await
            .context("cannot list Nodes for the gateway's NodePort address (pass --gateway)")?;
        let address = list.items.iter().find_map(|n| {
            let addresses = n.status.as_ref()?.addresses.as_ref()?;
            ["ExternalIP", "InternalIP"]
                .iter()
                .find_map(|t| addresses.iter().find(|a| a.type_ == *t))
                .map(|a| a.address.clone())
        });
        Ok(address.map(|a| url(&a, node_port)))
    }
}
