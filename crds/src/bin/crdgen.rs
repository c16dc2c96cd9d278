//! Writes the CRD YAML of every LeKiwi resource to `manifests/crds/` and the chart's `crds/`.

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let targets: Vec<PathBuf> = match std::env::args().nth(1).as_deref() {
        Some("--help" | "-h") => {
            println!(
                "Usage: crdgen [--stdout | DIR...]\n\nWrites the CRDs to manifests/crds/ and charts/lekiwi-operator/crds/ (default), to the given directories, or to stdout."
            );
            return Ok(());
        }
        Some("--stdout") => {
            for crd in lekiwi_crds::crds() {
                print!("---\n{}", lekiwi_crds::crd_yaml(&crd)?);
            }
            return Ok(());
        }
        Some(_) => std::env::args().skip(1).map(PathBuf::from).collect(),
        None => vec![
            root.join("manifests/crds"),
            root.join("charts/lekiwi-operator/crds"),
        ],
    };
    for dir in targets {
        std::fs::create_dir_all(&dir)?;
        for crd in lekiwi_crds::crds() {
            let name = crd.metadata.name.clone().unwrap_or_default();
            let path = dir.join(format!("{name}.yaml"));
            std::fs::write(&path, lekiwi_crds::crd_yaml(&crd)?)?;
            println!("wrote {}", path.display());
        }
    }
    Ok(())
}
