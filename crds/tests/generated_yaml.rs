//! The committed CRD YAML must be exactly what `crdgen` writes today.

use std::path::PathBuf;

#[test]
fn committed_crds_match_generated() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut stale = Vec::new();
    for dir in ["manifests/crds", "charts/lekiwi-operator/crds"] {
        for crd in lekiwi_crds::crds() {
            let name = crd.metadata.name.clone().unwrap();
            let path = root.join(dir).join(format!("{name}.yaml"));
            let want = lekiwi_crds::crd_yaml(&crd).unwrap();
            let have = std::fs::read_to_string(&path).unwrap_or_default();
            if have != want {
                stale.push(path.display().to_string());
            }
        }
    }
    assert!(
        stale.is_empty(),
        "CRD YAML out of date: {stale:?}\nrun `cargo run -p lekiwi-crds --bin crdgen` and commit the result"
    );
}

#[test]
fn examples_parse_as_our_types() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../manifests/examples");
    let mut robots = 0;
    let mut deployments = 0;
    for entry in std::fs::read_dir(&root).unwrap() {
        let text = std::fs::read_to_string(entry.unwrap().path()).unwrap();
        for doc in serde_yaml::Deserializer::from_str(&text) {
            let value = serde_yaml::Value::deserialize(doc).unwrap();
            match value["kind"].as_str() {
                Some("Robot") => {
                    serde_yaml::from_value::<lekiwi_crds::Robot>(value).unwrap();
                    robots += 1;
                }
                Some("RobotDeployment") => {
                    serde_yaml::from_value::<lekiwi_crds::RobotDeployment>(value).unwrap();
                    deployments += 1;
                }
                _ => {}
            }
        }
    }
    assert!(robots >= 3, "expected example robots, found {robots}");
    assert!(deployments >= 1, "expected an example deployment");
}

use serde::Deserialize;
