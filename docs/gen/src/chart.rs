//! The chart values reference: every key of each chart's `values.schema.json`, with its default
//! from `values.yaml`.

use std::path::Path;

use anyhow::{Context as _, Result};
use serde_json::Value;

use crate::md;

/// One page per chart under `charts/`: `(file name, Markdown)`.
pub fn pages(root: &Path) -> Result<Vec<(String, String)>> {
    let mut charts: Vec<_> = std::fs::read_dir(root.join("charts"))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("values.schema.json").is_file())
        .collect();
    charts.sort();
    let mut pages = Vec::new();
    for dir in charts {
        let name = dir
            .file_name()
            .and_then(|n| n.to_str())
            .context("chart directory name")?
            .to_owned();
        let schema: Value = serde_json::from_str(
            &std::fs::read_to_string(dir.join("values.schema.json"))
                .context("read values.schema.json")?,
        )?;
        let values: Value =
            serde_yaml::from_str(&std::fs::read_to_string(dir.join("values.yaml"))?)?;
        pages.push((format!("chart-{name}.md"), page(&name, &schema, &values)));
    }
    Ok(pages)
}

fn page(name: &str, schema: &Value, values: &Value) -> String {
    let mut rows = Vec::new();
    walk(schema, schema, "", Some(values), &mut rows);
    let mut out = md::generated_note(&format!(
        "`charts/{name}/values.schema.json` and `values.yaml`"
    ));
    out.push_str(&format!(
        "# Chart values: {name}\n\n\
         Every value the chart takes, as its `values.schema.json` checks it (an unknown key or a \
         value of the wrong shape is refused by `helm install` and `helm upgrade`), with the \
         default from `values.yaml`.\n\n"
    ));
    out.push_str(&md::table(
        &["Key", "Type", "Default", "Description"],
        &rows,
    ));
    out
}

/// Resolves a local `$ref` (`#/definitions/NAME`), merging the referring schema's own
/// description over the definition's.
fn resolve(root: &Value, schema: &Value) -> Value {
    let Some(target) = schema["$ref"].as_str().and_then(|r| r.strip_prefix("#/")) else {
        return schema.clone();
    };
    let mut found = target.split('/').fold(root, |v, part| &v[part]).clone();
    if let (Some(d), Some(obj)) = (schema.get("description"), found.as_object_mut()) {
        obj.insert("description".into(), d.clone());
    }
    found
}

fn walk(
    root: &Value,
    schema: &Value,
    path: &str,
    value: Option<&Value>,
    rows: &mut Vec<Vec<String>>,
) {
    let schema = resolve(root, schema);
    let props = schema["properties"].as_object();
    if !path.is_empty() && (props.is_none() || schema.get("description").is_some()) {
        rows.push(vec![
            md::code(path),
            type_name(root, &schema),
            default(value, props.is_some()),
            md::cell(&describe(&schema)),
        ]);
    }
    for (key, sub) in props.into_iter().flatten() {
        let sub_path = if path.is_empty() {
            key.clone()
        } else {
            format!("{path}.{key}")
        };
        walk(root, sub, &sub_path, value.and_then(|v| v.get(key)), rows);
    }
}

fn type_name(root: &Value, schema: &Value) -> String {
    if let Some(alts) = schema["oneOf"].as_array() {
        let names: Vec<String> = alts
            .iter()
            .map(|a| type_name(root, &resolve(root, a)))
            .collect();
        return names.join(" or ");
    }
    if schema.get("enum").is_some() && schema.get("type").is_none() {
        return "string".into();
    }
    match &schema["type"] {
        Value::String(t) if t == "array" => {
            format!(
                "array of {}",
                type_name(root, &resolve(root, &schema["items"]))
            )
        }
        Value::String(t) if t == "object" && schema["additionalProperties"].is_object() => {
            format!(
                "map of {}",
                type_name(root, &resolve(root, &schema["additionalProperties"]))
            )
        }
        Value::String(t) => t.clone(),
        Value::Array(ts) => ts
            .iter()
            .filter_map(Value::as_str)
            .collect::<Vec<_>>()
            .join(" or "),
        _ if schema["properties"].is_object() => "object".into(),
        _ => "any".into(),
    }
}

/// The default as YAML flow text; objects with their own rows show none.
fn default(value: Option<&Value>, has_rows: bool) -> String {
    match value {
        None => "—".into(),
        Some(_) if has_rows => "—".into(),
        Some(Value::String(s)) if s.is_empty() => "`\"\"`".into(),
        Some(v) => md::code(&serde_json::to_string(v).unwrap_or_default()),
    }
}

fn describe(schema: &Value) -> String {
    let mut parts = Vec::new();
    if let Some(d) = schema["description"].as_str() {
        parts.push(d.trim().trim_end_matches('.').to_owned());
    }
    if let Some(values) = schema["enum"].as_array() {
        let values: Vec<String> = values.iter().map(|v| format!("`{}`", text(v))).collect();
        parts.push(format!("One of {}", values.join(", ")));
    }
    match (schema.get("minimum"), schema.get("maximum")) {
        (Some(lo), Some(hi)) => parts.push(format!("{} to {}", text(lo), text(hi))),
        (Some(lo), None) => parts.push(format!("At least {}", text(lo))),
        (None, Some(hi)) => parts.push(format!("At most {}", text(hi))),
        (None, None) => {}
    }
    if let Some(p) = schema["pattern"].as_str() {
        parts.push(format!("Matches `{p}`"));
    }
    if parts.is_empty() {
        return String::new();
    }
    parts.join(". ") + "."
}

fn text(v: &Value) -> String {
    match v {
        Value::String(s) => s.clone(),
        v => v.to_string(),
    }
}
