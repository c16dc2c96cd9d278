//! Output formats, as kubectl's `-o`: tables, JSON and YAML (a `List` for a list, as kubectl
//! prints one), resource names, and jsonpath templates.

use std::str::FromStr;

use jsonpath_rust::JsonPath as _;
use kube::Resource;
use serde::Serialize;
use serde_json::{Value, json};

use crate::sanitize;

/// Output format, as kubectl's `-o`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Output {
    /// A table.
    Table,
    /// A wider table.
    Wide,
    /// JSON.
    Json,
    /// YAML.
    Yaml,
    /// `kind.group/name` per line.
    Name,
    /// A kubectl jsonpath template: text with `{.path}` expressions (see [`jsonpath`]).
    JsonPath(String),
}

/// The formats `-o` takes, for errors and `--help`.
pub const FORMATS: &str = "table, wide, json, yaml, name, jsonpath=TEMPLATE";

impl FromStr for Output {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Ok(match s {
            "table" | "" => Output::Table,
            "wide" => Output::Wide,
            "json" => Output::Json,
            "yaml" => Output::Yaml,
            "name" => Output::Name,
            _ => match s.strip_prefix("jsonpath=") {
                Some(template) => {
                    // Checked now, so that a typo fails before anything is fetched.
                    jsonpath(template, &Value::Null)?;
                    Output::JsonPath(template.to_owned())
                }
                None => return Err(format!("unknown output format {s:?}: use {FORMATS}")),
            },
        })
    }
}

impl Output {
    /// Whether the wide table is asked for.
    pub fn wide(&self) -> bool {
        *self == Output::Wide
    }

    /// Whether a table is asked for (the command draws it).
    pub fn table(&self) -> bool {
        matches!(self, Output::Table | Output::Wide)
    }

    /// `value` as pretty JSON, YAML or the jsonpath template's text when that is the format
    /// asked for (JSON with a final newline); `None` for the table formats and `name`, which
    /// each command draws itself. Neither holds a raw control character: JSON escapes them (C0
    /// by serde_json, DEL and C1 by [`sanitize::json`]), YAML writes such strings double-quoted
    /// with escapes, jsonpath text keeps only newlines and tabs (and, as kubectl's, ends without
    /// a newline unless the template writes one).
    pub fn structured<T: Serialize + ?Sized>(&self, value: &T) -> anyhow::Result<Option<String>> {
        Ok(match self {
            Output::Json => Some(sanitize::json(serde_json::to_string_pretty(value)?) + "\n"),
            Output::Yaml => Some(serde_yaml::to_string(value)?),
            Output::JsonPath(template) => {
                let value = serde_json::to_value(value)?;
                let text = jsonpath(template, &value).map_err(anyhow::Error::msg)?;
                Some(sanitize::text(&text).into_owned())
            }
            Output::Table | Output::Wide | Output::Name => None,
        })
    }

    /// Kubernetes objects of one kind: a `List` of them (each with its `apiVersion` and
    /// `kind`) for JSON, YAML and jsonpath, `kind.group/name` lines for `name`; `None` for
    /// the tables.
    pub fn resources<K>(&self, objects: &[K]) -> anyhow::Result<Option<String>>
    where
        K: Resource<DynamicType = ()> + Serialize,
    {
        if *self == Output::Name {
            let kind = format!("{}.{}", K::kind(&()).to_lowercase(), K::group(&()));
            return Ok(Some(names(objects.iter().map(|o| {
                format!("{kind}/{}", o.meta().name.as_deref().unwrap_or_default())
            }))));
        }
        let items = objects
            .iter()
            .map(|o| {
                let mut v = serde_json::to_value(o)?;
                if let Some(map) = v.as_object_mut() {
                    map.insert("apiVersion".into(), K::api_version(&()).into());
                    map.insert("kind".into(), K::kind(&()).into());
                }
                Ok(v)
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        self.structured(&list(items))
    }

    /// Rows that are not Kubernetes objects (found agents, stored events, groups): a `List` of
    /// them for JSON, YAML and jsonpath; `name(row)` per line for `name`; `None` for tables.
    pub fn rows<T: Serialize>(
        &self,
        rows: &[T],
        name: impl Fn(&T) -> String,
    ) -> anyhow::Result<Option<String>> {
        if *self == Output::Name {
            return Ok(Some(names(rows.iter().map(name))));
        }
        let items = rows
            .iter()
            .map(serde_json::to_value)
            .collect::<Result<Vec<_>, _>>()?;
        self.structured(&list(items))
    }
}

/// One name a line, control characters escaped.
fn names(names: impl Iterator<Item = String>) -> String {
    names
        .map(|n| sanitize::cell(&n).into_owned() + "\n")
        .collect()
}

/// A `List` as kubectl prints one.
pub fn list(items: Vec<Value>) -> Value {
    json!({
        "apiVersion": "v1",
        "kind": "List",
        "items": items,
        "metadata": {"resourceVersion": ""},
    })
}

/// Fills in a kubectl jsonpath template: text outside braces is kept, `{"text"}` is the text
/// (with `\n`, `\t` escapes), and `{.path}` (or `{$.path}`, `{[0]}`) is every value the
/// JSONPath (RFC 9535, e.g. `{.items[*].metadata.name}`, `{.items[?@.status.phase=='Online']}`)
/// selects, strings as they are and other values as JSON, separated by spaces. kubectl's
/// `{range}`/`{end}` loops are not supported.
pub fn jsonpath(template: &str, value: &Value) -> Result<String, String> {
    let mut out = String::new();
    let mut rest = template;
    while let Some(open) = rest.find('{') {
        out.push_str(&rest[..open]);
        let after = &rest[open + 1..];
        let close = after
            .find('}')
            .ok_or_else(|| format!("jsonpath {template:?}: a '{{' without its '}}'"))?;
        out.push_str(&expression(after[..close].trim(), value, template)?);
        rest = &after[close + 1..];
    }
    out.push_str(rest);
    Ok(out)
}

/// One `{...}` of a template.
fn expression(expr: &str, value: &Value, template: &str) -> Result<String, String> {
    if let Some(text) = expr.strip_prefix('"').and_then(|e| e.strip_suffix('"')) {
        return Ok(text.replace("\\n", "\n").replace("\\t", "\t"));
    }
    let word = expr.split_whitespace().next().unwrap_or_default();
    if matches!(word, "range" | "end") {
        return Err(format!(
            "jsonpath {template:?}: {{{word}}} is not supported; use {{.items[*].FIELD}} or -o json"
        ));
    }
    let path = if expr.starts_with('$') {
        expr.to_owned()
    } else if expr.is_empty() || expr == "." {
        "$".to_owned()
    } else if expr.starts_with('[') {
        format!("${expr}")
    } else {
        format!("$.{}", expr.trim_start_matches('.'))
    };
    let found = value
        .query(&path)
        .map_err(|e| format!("jsonpath {template:?}: {expr}: {e}"))?;
    Ok(found
        .into_iter()
        .map(|v| match v {
            Value::String(s) => s.clone(),
            other => other.to_string(),
        })
        .collect::<Vec<_>>()
        .join(" "))
}

/// Rows as kubectl prints a table: each column as wide as its widest cell, three spaces
/// between columns, no trailing spaces.
pub fn aligned(rows: &[Vec<String>]) -> String {
    let columns = rows.iter().map(Vec::len).max().unwrap_or(0);
    let widths: Vec<usize> = (0..columns)
        .map(|i| {
            rows.iter()
                .filter_map(|r| r.get(i))
                .map(|c| c.chars().count())
                .max()
                .unwrap_or(0)
        })
        .collect();
    let mut out = String::new();
    for row in rows {
        let line: Vec<String> = row
            .iter()
            .zip(&widths)
            .map(|(c, w)| format!("{c:<w$}"))
            .collect();
        out.push_str(line.join("   ").trim_end());
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn doc() -> Value {
        list(vec![
            json!({"metadata": {"name": "kiwi-01"}, "status": {"phase": "Online", "n": 3}}),
            json!({"metadata": {"name": "kiwi-02"}, "status": {"phase": "Offline", "n": 4}}),
        ])
    }

    #[test]
    fn kubectl_jsonpath_templates() {
        let t = |s: &str| jsonpath(s, &doc());
        assert_eq!(t("{.items[*].metadata.name}").unwrap(), "kiwi-01 kiwi-02");
        assert_eq!(t("{.kind}/{.apiVersion}").unwrap(), "List/v1");
        assert_eq!(t("{$.items[1].status.n}").unwrap(), "4");
        assert_eq!(
            t("{.items[?@.status.phase=='Online'].metadata.name}{\"\\n\"}").unwrap(),
            "kiwi-01\n"
        );
        assert_eq!(
            t("names: {.items[0].metadata.name}").unwrap(),
            "names: kiwi-01"
        );
        assert!(t("{.items[*]").unwrap_err().contains("without"));
        assert!(
            t("{range .items[*]}{end}")
                .unwrap_err()
                .contains("not supported")
        );
    }

    #[test]
    fn formats_parse_as_kubectl_writes_them() {
        assert_eq!("wide".parse(), Ok(Output::Wide));
        assert_eq!("name".parse(), Ok(Output::Name));
        assert_eq!(
            "jsonpath={.items[*].metadata.name}".parse(),
            Ok(Output::JsonPath("{.items[*].metadata.name}".into()))
        );
        assert!("xml".parse::<Output>().unwrap_err().contains("jsonpath="));
    }

    #[test]
    fn lists_are_kubectl_lists() {
        let robot: lekiwi_crds::Robot = serde_json::from_value(json!({
            "apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "Robot",
            "metadata": {"name": "kiwi-01"}, "spec": {}
        }))
        .unwrap();
        let robots = [robot];
        let v: Value =
            serde_yaml::from_str(&Output::Yaml.resources(&robots).unwrap().unwrap()).unwrap();
        assert_eq!(
            (v["apiVersion"].as_str(), v["kind"].as_str()),
            (Some("v1"), Some("List"))
        );
        assert_eq!(v["items"][0]["kind"], "Robot");
        assert_eq!(v["items"][0]["metadata"]["name"], "kiwi-01");
        assert_eq!(
            Output::Name.resources(&robots).unwrap().unwrap(),
            "robot.fleet.lekiwi.io/kiwi-01\n"
        );
    }
}
