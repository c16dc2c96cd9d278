//! `docgen`: writes the book's generated reference pages, or with `--check` lists the stale ones.

use anyhow::{Result, bail};

fn main() -> Result<()> {
    let root = lekiwi_docgen::repo_root();
    match std::env::args().nth(1).as_deref() {
        Some("--help" | "-h") => {
            println!(
                "Usage: docgen [--check]\n\nWrites {} (CRD fields, flags, metrics, chart values) \
                 from the code; with --check, lists the pages that differ and exits 1.",
                lekiwi_docgen::REFERENCE_DIR
            );
            Ok(())
        }
        Some("--check") => {
            let stale = lekiwi_docgen::stale(&root)?;
            for path in &stale {
                println!("stale: {}", path.display());
            }
            if !stale.is_empty() {
                bail!(
                    "{} reference page(s) stale: run `cargo run -p lekiwi-docgen`",
                    stale.len()
                );
            }
            Ok(())
        }
        Some(other) => bail!("unknown argument {other:?} (try --help)"),
        None => {
            let dir = root.join(lekiwi_docgen::REFERENCE_DIR);
            std::fs::create_dir_all(&dir)?;
            for entry in std::fs::read_dir(&dir)?.flatten() {
                std::fs::remove_file(entry.path())?;
            }
            for (path, text) in lekiwi_docgen::pages(&root)? {
                std::fs::write(root.join(&path), text)?;
                println!("wrote {}", path.display());
            }
            Ok(())
        }
    }
}
