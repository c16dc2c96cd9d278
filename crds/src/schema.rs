//! Hand-written schema fragments for what schemars cannot express on its own.

use schemars::{Schema, SchemaGenerator, json_schema};

/// `batchSize`: a positive count or a percentage from 1% to 100%.
pub fn batch_size(_: &mut SchemaGenerator) -> Schema {
    json_schema!({
        "description": "How many robots to update at once after the canary batch: a count (`5`) or a percentage of the targeted robots (`20%`, rounded up, at least one). Default `25%`.",
        "x-kubernetes-int-or-string": true,
        // Both constraints at once: `minimum` only judges integers and `pattern` only strings,
        // so `allOf` rejects `-3` and `150%` alike. (`anyOf` would let `-3` through the string
        // branch, and typed branches are not structural.)
        "allOf": [
            { "minimum": 1 },
            { "pattern": "^([1-9][0-9]?|100)%$" }
        ]
    })
}
