//! Checks at start that our CRDs are installed, or installs them with `--install-crds`.

use std::time::Duration;

use k8s_openapi::apiextensions_apiserver::pkg::apis::apiextensions::v1::CustomResourceDefinition;
use kube::Api;
use kube::api::{Patch, PatchParams};
use tracing::info;

use crate::error::{Error, Result};

/// Ensures every CRD exists and is Established, installing them first when asked to.
pub async fn ensure(client: kube::Client, install: bool) -> Result<()> {
    let api: Api<CustomResourceDefinition> = Api::all(client);
    for crd in lekiwi_crds::crds() {
        let name = crd.metadata.name.clone().unwrap_or_default();
        if install {
            api.patch(
                &name,
                &PatchParams::apply(lekiwi_crds::contract::managers::CRD_INSTALLER).force(),
                &Patch::Apply(&crd),
            )
            .await
            .map_err(|source| Error::Crd {
                name: name.clone(),
                source,
            })?;
            info!(crd = %name, "installed CRD");
        }
        wait_established(&api, &name).await?;
    }
    Ok(())
}

async fn wait_established(api: &Api<CustomResourceDefinition>, name: &str) -> Result<()> {
    for _ in 0..100 {
        let crd = api
            .get_opt(name)
            .await
            .map_err(|source| Error::Crd {
                name: name.to_owned(),
                source,
            })?
            .ok_or_else(|| Error::CrdMissing(name.to_owned()))?;
        let established = crd
            .status
            .and_then(|s| s.conditions)
            .unwrap_or_default()
            .iter()
            .any(|c| c.type_ == "Established" && c.status == "True");
        if established {
            return Ok(());
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    Err(Error::CrdNotEstablished(name.to_owned()))
}
