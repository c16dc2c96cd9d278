//! [`Text`]: an immutable string for status fields whose values repeat across a fleet (condition
//! types, reasons and messages, gateway names, agent versions and digests). Every gateway and
//! the controller keep every Robot in memory; deserialized, equal short values share one
//! allocation from a bounded table instead of one each. A `Text` made in code (a status about
//! to be written, then dropped) is a plain allocation and never touches the table.

use std::collections::HashSet;
use std::fmt;
use std::sync::{Arc, Mutex, OnceLock};

use schemars::{JsonSchema, Schema, SchemaGenerator};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// Longest value shared through the table; longer ones get their own allocation.
const MAX_SHARED_LEN: usize = 128;

/// Distinct values the table holds at most. Past it, new values get their own allocation: a
/// writer of ever new values (a hostile one, or messages naming each robot) cannot grow it.
const MAX_SHARED: usize = 4096;

/// An immutable string, serialized as a plain JSON string; equal short values read from JSON
/// share one allocation.
#[derive(Clone, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Text(Arc<str>);

impl Text {
    /// `s` as a `Text`, shared with an equal value seen before when the table allows.
    pub fn shared(s: &str) -> Self {
        if s.is_empty() || s.len() > MAX_SHARED_LEN {
            return Self(Arc::from(s));
        }
        static TABLE: OnceLock<Mutex<HashSet<Arc<str>>>> = OnceLock::new();
        let mut table = TABLE
            .get_or_init(Mutex::default)
            .lock()
            .unwrap_or_else(|p| p.into_inner());
        Self(share(&mut table, s, MAX_SHARED))
    }

    /// The string.
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

/// The value in `table` equal to `s`, or a new one, kept in the table while it has fewer than
/// `max` values.
fn share(table: &mut HashSet<Arc<str>>, s: &str, max: usize) -> Arc<str> {
    if let Some(found) = table.get(s) {
        return found.clone();
    }
    let new: Arc<str> = Arc::from(s);
    if table.len() < max {
        table.insert(new.clone());
    }
    new
}

impl std::ops::Deref for Text {
    type Target = str;
    fn deref(&self) -> &str {
        &self.0
    }
}

impl fmt::Debug for Text {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(&*self.0, f)
    }
}

impl fmt::Display for Text {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Display::fmt(&*self.0, f)
    }
}

impl From<&str> for Text {
    fn from(s: &str) -> Self {
        Self(Arc::from(s))
    }
}

impl From<String> for Text {
    fn from(s: String) -> Self {
        Self(Arc::from(s))
    }
}

impl From<Text> for String {
    fn from(t: Text) -> Self {
        t.0.to_string()
    }
}

impl PartialEq<str> for Text {
    fn eq(&self, other: &str) -> bool {
        *self.0 == *other
    }
}

impl PartialEq<&str> for Text {
    fn eq(&self, other: &&str) -> bool {
        *self.0 == **other
    }
}

impl PartialEq<String> for Text {
    fn eq(&self, other: &String) -> bool {
        *self.0 == **other
    }
}

impl PartialEq<Text> for String {
    fn eq(&self, other: &Text) -> bool {
        **self == *other.0
    }
}

impl Serialize for Text {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&self.0)
    }
}

impl<'de> Deserialize<'de> for Text {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl serde::de::Visitor<'_> for Visitor {
            type Value = Text;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a string")
            }
            fn visit_str<E: serde::de::Error>(self, s: &str) -> Result<Text, E> {
                Ok(Text::shared(s))
            }
        }
        d.deserialize_str(Visitor)
    }
}

impl JsonSchema for Text {
    fn inline_schema() -> bool {
        true
    }

    fn schema_name() -> std::borrow::Cow<'static, str> {
        String::schema_name()
    }

    fn schema_id() -> std::borrow::Cow<'static, str> {
        String::schema_id()
    }

    fn json_schema(generator: &mut SchemaGenerator) -> Schema {
        String::json_schema(generator)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn equal_short_values_share_one_allocation() {
        let a: Text = serde_json::from_str("\"Connected\"").unwrap();
        let b: Text = serde_json::from_str("\"Connected\"").unwrap();
        assert!(Arc::ptr_eq(&a.0, &b.0));
        assert_eq!(a, "Connected");
        assert_eq!(serde_json::to_string(&a).unwrap(), "\"Connected\"");
        let long = "x".repeat(MAX_SHARED_LEN + 1);
        let (c, d) = (Text::shared(&long), Text::shared(&long));
        assert!(!Arc::ptr_eq(&c.0, &d.0));
        assert_eq!(c, d);
    }

    #[test]
    fn the_table_stops_growing_at_its_bound() {
        let mut table = HashSet::new();
        let a = share(&mut table, "a", 2);
        let _ = share(&mut table, "b", 2);
        let (c1, c2) = (share(&mut table, "c", 2), share(&mut table, "c", 2));
        assert_eq!(table.len(), 2);
        // Past the bound: still the right value, no longer shared; what was shared stays so.
        assert!(!Arc::ptr_eq(&c1, &c2));
        assert_eq!(&*c1, "c");
        assert!(Arc::ptr_eq(&a, &share(&mut table, "a", 2)));
    }

    #[test]
    fn escaped_json_strings_are_read_whole() {
        let t: Text = serde_json::from_str(r#""a \"quoted\" \u00e9""#).unwrap();
        assert_eq!(t, "a \"quoted\" é");
    }
}
