//! Label selectors in the syntax `kubectl get -l` takes: `a=b`, `a==b`, `a!=b`, `a`, `!a`,
//! `a in (x,y)`, `a notin (x,y)`, joined by commas; every requirement must hold.

use std::collections::BTreeMap;

/// One requirement on a label.
#[derive(Clone, Debug, PartialEq, Eq)]
enum Requirement {
    /// The label exists (with any value in the set, if one is given).
    In(String, Option<Vec<String>>),
    /// The label is absent (or its value is not in the set, if one is given).
    NotIn(String, Option<Vec<String>>),
}

/// A parsed label selector; the empty selector selects everything.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Selector(Vec<Requirement>);

impl Selector {
    /// Parses `text`; the error says what is wrong where.
    pub fn parse(text: &str) -> Result<Self, String> {
        let mut requirements = Vec::new();
        for part in split_top_level(text)? {
            let part = part.trim();
            if part.is_empty() {
                continue;
            }
            requirements.push(requirement(part)?);
        }
        Ok(Self(requirements))
    }

    /// One `key=value` requirement of the selector, if it has one: only objects with that
    /// label can match, so a list may read the label's index instead of every object.
    pub fn equality(&self) -> Option<(&str, &str)> {
        self.0.iter().find_map(|r| match r {
            Requirement::In(key, Some(values)) if values.len() == 1 => {
                Some((key.as_str(), values[0].as_str()))
            }
            _ => None,
        })
    }

    /// Whether `labels` satisfy every requirement.
    pub fn matches(&self, labels: &BTreeMap<String, String>) -> bool {
        self.0.iter().all(|r| match r {
            Requirement::In(key, None) => labels.contains_key(key),
            Requirement::In(key, Some(values)) => {
                labels.get(key).is_some_and(|v| values.contains(v))
            }
            Requirement::NotIn(key, None) => !labels.contains_key(key),
            Requirement::NotIn(key, Some(values)) => {
                labels.get(key).is_none_or(|v| !values.contains(v))
            }
        })
    }
}

/// Splits at commas outside parentheses.
fn split_top_level(text: &str) -> Result<Vec<&str>, String> {
    let (mut parts, mut depth, mut start) = (Vec::new(), 0i32, 0);
    for (i, c) in text.char_indices() {
        match c {
            '(' => depth += 1,
            ')' => depth -= 1,
            ',' if depth == 0 => {
                parts.push(&text[start..i]);
                start = i + 1;
            }
            _ => {}
        }
        if !(0..=1).contains(&depth) {
            return Err(format!("unbalanced parentheses in label selector {text:?}"));
        }
    }
    if depth != 0 {
        return Err(format!("unbalanced parentheses in label selector {text:?}"));
    }
    parts.push(&text[start..]);
    Ok(parts)
}

fn requirement(part: &str) -> Result<Requirement, String> {
    if let Some(key) = part.strip_prefix('!') {
        return Ok(Requirement::NotIn(label_key(key)?, None));
    }
    if let Some((key, value)) = part.split_once("!=") {
        return Ok(Requirement::NotIn(
            label_key(key)?,
            Some(vec![label_value(value)?]),
        ));
    }
    if let Some((key, value)) = part.split_once("==").or_else(|| part.split_once('=')) {
        return Ok(Requirement::In(
            label_key(key)?,
            Some(vec![label_value(value)?]),
        ));
    }
    if let Some((key, set)) = part.split_once(" notin ") {
        return Ok(Requirement::NotIn(label_key(key)?, Some(value_set(set)?)));
    }
    if let Some((key, set)) = part.split_once(" in ") {
        return Ok(Requirement::In(label_key(key)?, Some(value_set(set)?)));
    }
    Ok(Requirement::In(label_key(part)?, None))
}

fn value_set(set: &str) -> Result<Vec<String>, String> {
    let inner = set
        .trim()
        .strip_prefix('(')
        .and_then(|s| s.strip_suffix(')'))
        .ok_or_else(|| format!("expected a set of values in parentheses, got {set:?}"))?;
    inner.split(',').map(label_value).collect()
}

fn label_key(key: &str) -> Result<String, String> {
    let key = key.trim();
    let ok = !key.is_empty()
        && key.len() <= 317
        && key
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_./".contains(c));
    ok.then(|| key.to_owned())
        .ok_or_else(|| format!("{key:?} is not a valid label key"))
}

fn label_value(value: &str) -> Result<String, String> {
    let value = value.trim();
    let ok = value.len() <= 63
        && value
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c));
    ok.then(|| value.to_owned())
        .ok_or_else(|| format!("{value:?} is not a valid label value"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn labels(pairs: &[(&str, &str)]) -> BTreeMap<String, String> {
        pairs
            .iter()
            .map(|(k, v)| ((*k).to_owned(), (*v).to_owned()))
            .collect()
    }

    #[test]
    fn every_form_kubectl_takes() {
        let l = labels(&[("lab", "b2"), ("arm", "so100")]);
        for (sel, want) in [
            ("", true),
            ("lab=b2", true),
            ("lab==b2,arm=so100", true),
            ("lab!=b2", false),
            ("lab", true),
            ("!lab", false),
            ("!gripper", true),
            ("lab in (b1, b2)", true),
            ("lab notin (b1,b2)", false),
            ("lab in (b1,b3),arm", false),
        ] {
            assert_eq!(Selector::parse(sel).unwrap().matches(&l), want, "{sel}");
        }
    }

    #[test]
    fn malformed_selectors_are_refused_with_a_reason() {
        for bad in ["lab=b 2", "lab in b1", "lab in (b1", "=x", "a=(", "lab))"] {
            assert!(Selector::parse(bad).is_err(), "{bad}");
        }
    }
}
