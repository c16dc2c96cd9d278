//! A list answer decoded one object at a time, each trimmed as soon as it is read.
//!
//! kube's `Api::list` decodes the whole answer into objects first; a reader that trims them
//! afterwards (drops managed fields, say) has held every object whole at once, and what it keeps
//! then sits scattered over all the memory the whole objects took, which the allocator cannot
//! hand back. For 10,000 Robots that was a step of some 280 MiB in a gateway's RSS at every
//! relist. Here each object is trimmed before the next is read, so the memory one object's
//! dropped parts took is reused by the next, and the list costs its answer's text and what is
//! kept. `cargo bench -p lekiwi-core --bench list_decode` compares the two.

use std::fmt;
use std::marker::PhantomData;

use kube::api::ListParams;
use kube::{Api, Resource};
use serde::de::{DeserializeOwned, DeserializeSeed, Deserializer, IgnoredAny, MapAccess, Visitor};

/// Every object `params` asks of `api`, each through `trim` as it is decoded.
pub async fn list_trimmed<K>(
    api: &Api<K>,
    params: &ListParams,
    trim: fn(&mut K),
) -> kube::Result<Vec<K>>
where
    K: Resource + Clone + DeserializeOwned,
{
    let mut request = kube::core::Request::new(api.resource_url())
        .list(params)
        .map_err(kube::Error::BuildRequest)?;
    // As `Api::list` marks it, for the client's own tracing.
    request.extensions_mut().insert("list");
    let text = api.clone().into_client().request_text(request).await?;
    decode(&text, trim).map_err(kube::Error::SerdeError)
}

/// The `items` of a list answer, each through `trim` as it is decoded; every other field of
/// the answer is skipped.
pub fn decode<K: DeserializeOwned>(text: &str, trim: fn(&mut K)) -> serde_json::Result<Vec<K>> {
    let mut de = serde_json::Deserializer::from_str(text);
    let items = ListSeed { trim }.deserialize(&mut de)?;
    de.end()?;
    Ok(items)
}

/// Reads a list answer (an object) for its `items`.
struct ListSeed<K> {
    trim: fn(&mut K),
}

impl<'de, K: DeserializeOwned> DeserializeSeed<'de> for ListSeed<K> {
    type Value = Vec<K>;

    fn deserialize<D: Deserializer<'de>>(self, de: D) -> Result<Vec<K>, D::Error> {
        de.deserialize_map(self)
    }
}

impl<'de, K: DeserializeOwned> Visitor<'de> for ListSeed<K> {
    type Value = Vec<K>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("a list answer (an object with items)")
    }

    fn visit_map<M: MapAccess<'de>>(self, mut map: M) -> Result<Vec<K>, M::Error> {
        let mut items = None;
        while let Some(key) = map.next_key::<std::borrow::Cow<'de, str>>()? {
            if key == "items" {
                items = Some(map.next_value_seed(ItemsSeed {
                    trim: self.trim,
                    kind: PhantomData,
                })?);
            } else {
                map.next_value::<IgnoredAny>()?;
            }
        }
        // An empty list may come as `"items": null`, or without the field.
        Ok(items.unwrap_or_default())
    }
}

/// Reads the `items` array one object at a time.
struct ItemsSeed<K> {
    trim: fn(&mut K),
    kind: PhantomData<K>,
}

impl<'de, K: DeserializeOwned> DeserializeSeed<'de> for ItemsSeed<K> {
    type Value = Vec<K>;

    fn deserialize<D: Deserializer<'de>>(self, de: D) -> Result<Vec<K>, D::Error> {
        de.deserialize_any(self)
    }
}

impl<'de, K: DeserializeOwned> Visitor<'de> for ItemsSeed<K> {
    type Value = Vec<K>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("an array of objects, or null")
    }

    fn visit_unit<E>(self) -> Result<Vec<K>, E> {
        Ok(Vec::new())
    }

    fn visit_seq<S: serde::de::SeqAccess<'de>>(self, mut seq: S) -> Result<Vec<K>, S::Error> {
        let mut items = Vec::with_capacity(seq.size_hint().unwrap_or(0));
        while let Some(mut item) = seq.next_element::<K>()? {
            (self.trim)(&mut item);
            items.push(item);
        }
        items.shrink_to_fit();
        Ok(items)
    }
}

#[cfg(test)]
mod tests {
    use super::decode;
    use serde::Deserialize;

    #[derive(Debug, Deserialize, PartialEq)]
    struct Thing {
        name: String,
        #[serde(default)]
        bulk: Option<String>,
    }

    fn drop_bulk(t: &mut Thing) {
        t.bulk = None;
    }

    #[test]
    fn items_are_decoded_in_order_and_trimmed_and_other_fields_skipped() {
        let text = r#"{"kind":"ThingList","metadata":{"resourceVersion":"7","x":[1,{"y":2}]},
            "items":[{"name":"a","bulk":"xxxx"},{"name":"b"}],"apiVersion":"v1"}"#;
        let items = decode(text, drop_bulk).unwrap();
        assert_eq!(
            items,
            vec![
                Thing {
                    name: "a".into(),
                    bulk: None
                },
                Thing {
                    name: "b".into(),
                    bulk: None
                }
            ]
        );
    }

    #[test]
    fn an_empty_list_may_have_null_or_no_items() {
        assert!(
            decode::<Thing>(r#"{"items":null}"#, drop_bulk)
                .unwrap()
                .is_empty()
        );
        assert!(
            decode::<Thing>(r#"{"kind":"ThingList"}"#, drop_bulk)
                .unwrap()
                .is_empty()
        );
        assert!(
            decode::<Thing>(r#"{"items":[]}"#, drop_bulk)
                .unwrap()
                .is_empty()
        );
    }

    #[test]
    fn a_malformed_answer_is_an_error_not_a_short_list() {
        for text in [
            r#"{"items":[{"name":"a"},{"nam"#,
            r#"{"items":[{"name":"a"}]} trailing"#,
            r#"{"items":[{"bulk":"no name"}]}"#,
            r#"{"items":{"name":"a"}}"#,
            r#"[]"#,
        ] {
            assert!(decode(text, drop_bulk).is_err(), "{text}");
        }
    }
}
