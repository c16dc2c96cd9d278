//! The CRD reference: every field of each resource's schema, as the API server holds it.

use anyhow::{Context as _, Result};
use serde_json::Value;

use crate::md;

/// One page per CRD: `(file name, Markdown)`.
pub fn pages() -> Result<Vec<(String, String)>> {
    let mut pages = Vec::new();
    for crd in lekiwi_crds::crds() {
        let crd = serde_json::to_value(&crd)?;
        let kind = crd["spec"]["names"]["kind"]
            .as_str()
            .context("CRD without a kind")?;
        pages.push((format!("{}.md", kind.to_ascii_lowercase()), page(&crd)?));
    }
    Ok(pages)
}

fn page(crd: &Value) -> Result<String> {
    let spec = &crd["spec"];
    let names = &spec["names"];
    let kind = names["kind"].as_str().unwrap_or_default();
    let mut out = md::generated_note("the CRD schema (`lekiwi-crds`, `manifests/crds/`)");
    out.push_str(&format!("# {kind}\n\n"));
    for version in spec["versions"]
        .as_array()
        .context("CRD without versions")?
    {
        let schema = &version["schema"]["openAPIV3Schema"];
        out.push_str(&md::cell(
            schema["description"].as_str().unwrap_or_default(),
        ));
        out.push_str("\n\n");
        out.push_str(&names_table(spec, version));
        out.push_str(&columns(version));
        let mut rows = Vec::new();
        for part in ["spec", "status"] {
            if let Some(sub) = schema["properties"].get(part) {
                walk(sub, part, false, &mut rows);
            }
        }
        out.push_str("## Fields\n\n");
        out.push_str(&md::table(&["Field", "Type", "Description"], &rows));
        out.push('\n');
    }
    Ok(out)
}

/// Group, version, names and scope.
fn names_table(spec: &Value, version: &Value) -> String {
    let names = &spec["names"];
    let list = |v: &Value| -> String {
        v.as_array()
            .map(|a| {
                a.iter()
                    .filter_map(Value::as_str)
                    .map(md::code)
                    .collect::<Vec<_>>()
                    .join(", ")
            })
            .unwrap_or_else(|| "—".into())
    };
    let rows = vec![
        vec![
            "API version".into(),
            md::code(&format!(
                "{}/{}",
                spec["group"].as_str().unwrap_or_default(),
                version["name"].as_str().unwrap_or_default()
            )),
        ],
        vec![
            "Scope".into(),
            spec["scope"].as_str().unwrap_or_default().into(),
        ],
        vec![
            "Plural".into(),
            md::code(names["plural"].as_str().unwrap_or_default()),
        ],
        vec!["Short names".into(), list(&names["shortNames"])],
        vec!["Categories".into(), list(&names["categories"])],
        vec![
            "Subresources".into(),
            version["subresources"]
                .as_object()
                .map(|o| o.keys().map(|k| md::code(k)).collect::<Vec<_>>().join(", "))
                .unwrap_or_else(|| "—".into()),
        ],
    ];
    md::table(&["", ""], &rows) + "\n"
}

/// The columns `kubectl get` prints (those with a priority only with `-o wide`).
fn columns(version: &Value) -> String {
    let Some(cols) = version["additionalPrinterColumns"].as_array() else {
        return String::new();
    };
    let rows: Vec<Vec<String>> = cols
        .iter()
        .map(|c| {
            vec![
                md::cell(c["name"].as_str().unwrap_or_default()),
                md::code(c["jsonPath"].as_str().unwrap_or_default()),
                if c["priority"].as_i64().unwrap_or(0) > 0 {
                    "`-o wide`".into()
                } else {
                    "always".into()
                },
            ]
        })
        .collect();
    format!(
        "## Columns of `kubectl get`\n\n{}\n",
        md::table(&["Column", "Value", "Shown"], &rows)
    )
}

/// One row for `schema` at `path`, then one per field below it.
fn walk(schema: &Value, path: &str, required: bool, rows: &mut Vec<Vec<String>>) {
    rows.push(vec![
        md::code(path),
        type_name(schema),
        md::cell(&describe(schema, required)),
    ]);
    let req: Vec<&str> = schema["required"]
        .as_array()
        .map(|r| r.iter().filter_map(Value::as_str).collect())
        .unwrap_or_default();
    if let Some(props) = schema["properties"].as_object() {
        for (name, sub) in props {
            walk(
                sub,
                &format!("{path}.{name}"),
                req.contains(&name.as_str()),
                rows,
            );
        }
    }
    let items = &schema["items"];
    if items["properties"].is_object() {
        walk_items(items, &format!("{path}[]"), rows);
    }
    let map = &schema["additionalProperties"];
    if map["properties"].is_object() {
        walk_items(map, &format!("{path}.*"), rows);
    }
}

/// The fields of an array's items or a map's values (the element itself has no row).
fn walk_items(schema: &Value, path: &str, rows: &mut Vec<Vec<String>>) {
    let req: Vec<&str> = schema["required"]
        .as_array()
        .map(|r| r.iter().filter_map(Value::as_str).collect())
        .unwrap_or_default();
    for (name, sub) in schema["properties"].as_object().into_iter().flatten() {
        walk(
            sub,
            &format!("{path}.{name}"),
            req.contains(&name.as_str()),
            rows,
        );
    }
}

fn type_name(schema: &Value) -> String {
    if schema["x-kubernetes-int-or-string"].as_bool() == Some(true) {
        return "integer or string".into();
    }
    let base = match schema["type"].as_str() {
        Some("array") => format!("array of {}", type_name(&schema["items"])),
        Some("object") if schema["additionalProperties"].is_object() => {
            format!("map of {}", type_name(&schema["additionalProperties"]))
        }
        Some(t) => t.to_owned(),
        None if schema["properties"].is_object() => "object".into(),
        None => "any".into(),
    };
    match schema["format"].as_str() {
        Some(f) => format!("{base} ({f})"),
        None => base,
    }
}

/// The schema's description, then what the API server enforces.
fn describe(schema: &Value, required: bool) -> String {
    let mut parts = Vec::new();
    if let Some(d) = schema["description"].as_str() {
        parts.push(d.trim().trim_end_matches('.').to_owned());
    }
    if required {
        parts.push("Required".into());
    }
    if let Some(values) = schema["enum"].as_array() {
        let values: Vec<String> = values.iter().map(|v| format!("`{}`", plain(v))).collect();
        parts.push(format!("One of {}", values.join(", ")));
    }
    for (min, max, unit) in [
        ("minimum", "maximum", ""),
        ("minLength", "maxLength", " characters"),
        ("minItems", "maxItems", " items"),
    ] {
        let (lo, hi) = (schema.get(min).map(plain), schema.get(max).map(plain));
        match (lo, hi) {
            (Some(lo), Some(hi)) => parts.push(format!("{lo} to {hi}{unit}")),
            (Some(lo), None) => parts.push(format!("At least {lo}{unit}")),
            (None, Some(hi)) => parts.push(format!("At most {hi}{unit}")),
            (None, None) => {}
        }
    }
    if let Some(p) = schema["pattern"].as_str() {
        parts.push(format!("Matches `{p}`"));
    }
    if let Some(d) = schema.get("default") {
        parts.push(format!("Default `{}`", plain(d)));
    }
    if let Some(one_of) = schema["oneOf"].as_array() {
        let fields: Vec<String> = one_of
            .iter()
            .filter_map(|o| o["required"].as_array())
            .flatten()
            .filter_map(Value::as_str)
            .map(|f| format!("`{f}`"))
            .collect();
        parts.push(format!("Exactly one of {}", fields.join(", ")));
    }
    if let Some(keys) = schema["x-kubernetes-list-map-keys"].as_array() {
        let keys: Vec<String> = keys.iter().map(|k| format!("`{}`", plain(k))).collect();
        parts.push(format!("A list keyed by {}", keys.join(", ")));
    }
    if parts.is_empty() {
        return String::new();
    }
    parts.join(". ") + "."
}

/// A JSON value as text, strings without their quotes.
fn plain(v: &Value) -> String {
    match v {
        Value::String(s) => s.clone(),
        v => v.to_string(),
    }
}
