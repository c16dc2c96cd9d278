//! What a GraphQL request costs before it runs, kept off the async runtime and bounded. The JSON
//! body, the query's parsing and its validation are CPU work in proportion to the request's
//! length (tens of milliseconds for 64 KiB): they run on a blocking thread
//! ([`tokio::task::block_in_place`]), at most half the CPUs' worth at once, so REST requests,
//! WebSockets and agents are served while a long query is parsed. A parsed query is measured
//! before async-graphql validates it, with every fragment spread expanded: fragments that spread
//! each other twice make a query of a kilobyte expand exponentially (a "fragment bomb"), which
//! validation would walk for hours; one that expands to more fields than
//! `--graphql-max-complexity` is refused as too complex, as its complexity (at least 1 per field)
//! would be. The same walk measures the depth the `--graphql-max-depth` limit applies to, in
//! which introspection's `ofType` (the one type a list or non-null type wraps, which cannot
//! multiply an answer) does not count: the standard introspection query (GraphiQL's, Apollo's,
//! code generators') nests `ofType` nine deep.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;

use async_graphql::extensions::{
    Extension, ExtensionContext, ExtensionFactory, NextParseQuery, NextValidation,
};
use async_graphql::parser::types::{
    ExecutableDocument, FragmentDefinition, Selection, SelectionSet,
};
use async_graphql::{Name, Positioned, ServerError, ServerResult, ValidationResult, Variables};
use tokio::runtime::{Handle, RuntimeFlavor};
use tokio::sync::Semaphore;

/// The introspection field that does not count towards a query's depth.
const WRAPPED_TYPE: &str = "ofType";

/// Runs requests' CPU work off the runtime and refuses queries too deep or too large.
pub struct Guard {
    cpu: Semaphore,
    max_depth: usize,
    max_fields: usize,
}

impl Guard {
    /// A guard refusing queries deeper than `max_depth` or expanding to more than
    /// `max_complexity` fields.
    pub fn new(max_depth: usize, max_complexity: usize) -> Self {
        let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
        Self {
            cpu: Semaphore::new((cpus / 2).max(1)),
            max_depth,
            max_fields: max_complexity,
        }
    }

    /// Runs `work`, CPU-bound, where it blocks no task of the runtime, once a permit is free.
    pub async fn run<R>(&self, work: impl FnOnce() -> R) -> R {
        // The semaphore is never closed; a permit is held until `work` is done.
        let _permit = self.cpu.acquire().await.ok();
        match Handle::try_current().map(|h| h.runtime_flavor()) {
            Ok(RuntimeFlavor::MultiThread) => tokio::task::block_in_place(work),
            // A single-threaded runtime (unit tests) has no other thread to hand its tasks to.
            _ => work(),
        }
    }

    /// Refuses `doc` when its fragments spread themselves or nest too deep, when it expands to
    /// more fields than allowed (before depth, as async-graphql checks complexity first) or
    /// nests deeper than allowed.
    fn check(&self, doc: &ExecutableDocument) -> ServerResult<()> {
        let shape = measure(doc)?;
        if shape.fields > self.max_fields {
            return Err(ServerError::new("Query is too complex.", None));
        }
        if shape.depth > self.max_depth {
            return Err(ServerError::new("Query is nested too deep.", None));
        }
        Ok(())
    }
}

/// Installs a [`Guard`] in a schema.
pub struct Guarded(pub Arc<Guard>);

impl ExtensionFactory for Guarded {
    fn create(&self) -> Arc<dyn Extension> {
        self.0.clone()
    }
}

#[async_graphql::async_trait::async_trait]
impl Extension for Guard {
    /// Parses and measures the query; `next` (async-graphql's parse, then its recursion check,
    /// which walks fragment spreads as often as they are spread) is not run: the measure does
    /// what that check does, fragments once.
    async fn parse_query(
        &self,
        _ctx: &ExtensionContext<'_>,
        query: &str,
        _variables: &Variables,
        _next: NextParseQuery<'_>,
    ) -> ServerResult<ExecutableDocument> {
        self.run(|| {
            let doc = async_graphql::parser::parse_query(query)?;
            self.check(&doc)?;
            Ok(doc)
        })
        .await
    }

    async fn validation(
        &self,
        ctx: &ExtensionContext<'_>,
        next: NextValidation<'_>,
    ) -> Result<ValidationResult, Vec<ServerError>> {
        self.run(|| futures::executor::block_on(next.run(ctx)))
            .await
    }
}

/// Deepest nesting of selection sets (a field's, a fragment's, an inline fragment's) a query
/// may have: async-graphql's own limit, which its validation relies on as it walks a query
/// recursively.
const MAX_NESTING: usize = 32;

/// How a selection nests and how many fields it holds, fragments expanded.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Shape {
    /// Fields nested in fields (`ofType` aside), the depth `--graphql-max-depth` limits.
    depth: usize,
    /// Fields, each counted as often as it is spread.
    fields: usize,
    /// Selection sets nested below this one.
    nest: usize,
}

impl Shape {
    /// Two selections side by side.
    fn and(self, other: Shape) -> Shape {
        Shape {
            depth: self.depth.max(other.depth),
            fields: self.fields.saturating_add(other.fields),
            nest: self.nest.max(other.nest),
        }
    }

    /// This selection set inside another one.
    fn nested(self) -> Shape {
        Shape {
            nest: self.nest + 1,
            ..self
        }
    }
}

/// The shape of every operation and fragment definition of `doc` together (async-graphql's
/// validation walks both), each fragment measured once however often it is spread; an error
/// for fragments that spread themselves or nest deeper than [`MAX_NESTING`].
fn measure(doc: &ExecutableDocument) -> ServerResult<Shape> {
    let mut walk = Walk {
        fragments: &doc.fragments,
        measured: HashMap::new(),
        open: HashSet::new(),
    };
    let mut total = Shape::default();
    for (_, operation) in doc.operations.iter() {
        total = total.and(walk.set(&operation.node.selection_set.node, 0)?);
    }
    for name in doc.fragments.keys() {
        total = total.and(walk.fragment(name, 0)?);
    }
    Ok(total)
}

fn too_nested() -> ServerError {
    ServerError::new(
        format!("The recursion depth of the query cannot be greater than `{MAX_NESTING}`"),
        None,
    )
}

/// A walk of a document that remembers each fragment's shape.
struct Walk<'a> {
    fragments: &'a HashMap<Name, Positioned<FragmentDefinition>>,
    measured: HashMap<&'a str, Shape>,
    /// Fragments being measured: one spread inside itself is a cycle.
    open: HashSet<&'a str>,
}

impl<'a> Walk<'a> {
    /// The shape of `set`, which is `level` selection sets deep.
    fn set(&mut self, set: &'a SelectionSet, level: usize) -> ServerResult<Shape> {
        if level > MAX_NESTING {
            return Err(too_nested());
        }
        let mut shape = Shape::default();
        for item in &set.items {
            let inner = match &item.node {
                Selection::Field(field) => {
                    let sub = &field.node.selection_set.node;
                    let below = if sub.items.is_empty() {
                        Shape::default()
                    } else {
                        self.set(sub, level + 1)?.nested()
                    };
                    Shape {
                        depth: below.depth + usize::from(field.node.name.node != WRAPPED_TYPE),
                        fields: below.fields.saturating_add(1),
                        nest: below.nest,
                    }
                }
                Selection::FragmentSpread(spread) => self
                    .fragment(&spread.node.fragment_name.node, level + 1)?
                    .nested(),
                Selection::InlineFragment(inline) => self
                    .set(&inline.node.selection_set.node, level + 1)?
                    .nested(),
            };
            shape = shape.and(inner);
        }
        Ok(shape)
    }

    /// The shape of fragment `name`'s selection set, `level` sets deep.
    fn fragment(&mut self, name: &'a str, level: usize) -> ServerResult<Shape> {
        if let Some(shape) = self.measured.get(name) {
            if level + shape.nest > MAX_NESTING {
                return Err(too_nested());
            }
            return Ok(*shape);
        }
        // An unknown fragment is validation's to report.
        let Some(fragment) = self.fragments.get(name) else {
            return Ok(Shape::default());
        };
        if !self.open.insert(name) {
            return Err(ServerError::new(
                format!("Cannot spread fragment \"{name}\" within itself."),
                None,
            ));
        }
        let shape = self.set(&fragment.node.selection_set.node, level)?;
        self.open.remove(name);
        self.measured.insert(name, shape);
        Ok(shape)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shape(query: &str) -> Shape {
        measure(&async_graphql::parser::parse_query(query).unwrap()).unwrap()
    }

    fn refusal(query: &str) -> String {
        measure(&async_graphql::parser::parse_query(query).unwrap())
            .unwrap_err()
            .message
    }

    #[test]
    fn fragments_count_as_often_as_they_are_spread() {
        let plain = shape("{ a { b c } }");
        assert_eq!((plain.depth, plain.fields, plain.nest), (2, 3, 1));
        // F is measured standalone too, as validation walks it.
        let spread = shape("{ a { ...F } d { ...F } } fragment F on T { b { c } }");
        assert_eq!((spread.depth, spread.fields, spread.nest), (3, 8, 3));
        let inline = shape("{ a { ... on T { b } } }");
        assert_eq!((inline.depth, inline.fields, inline.nest), (2, 2, 2));
        let cycle = "{ ...A } fragment A on Q { x ...B } fragment B on Q { y ...A }";
        assert!(
            refusal(cycle).contains("within itself"),
            "{}",
            refusal(cycle)
        );
    }

    #[test]
    fn nesting_is_limited_through_fragments_too() {
        let chain = |n: usize| {
            let mut query = format!("{{ ...F{n} }} fragment F0 on Q {{ a }}");
            for i in 1..=n {
                query.push_str(&format!(" fragment F{i} on Q {{ ...F{} }}", i - 1));
            }
            query
        };
        assert_eq!(shape(&chain(MAX_NESTING - 1)).nest, MAX_NESTING);
        for n in [MAX_NESTING, 2000] {
            assert!(refusal(&chain(n)).contains("recursion depth"), "{n}");
        }
        // Unused by the operation, and still walked by validation.
        let unused = chain(2000).replacen("{ ...F2000 }", "{ a }", 1);
        assert!(refusal(&unused).contains("recursion depth"));
    }

    #[test]
    fn a_fragment_bomb_is_measured_at_once() {
        let mut query = String::from("{ ...F30 } fragment F0 on Q { a }");
        for i in 1..=30 {
            query.push_str(&format!(
                " fragment F{i} on Q {{ ...F{p} ...F{p} }}",
                p = i - 1
            ));
        }
        let measured = shape(&query);
        assert_eq!(measured.depth, 1);
        assert!(measured.fields > 1 << 30, "{measured:?}");
    }

    #[test]
    fn of_type_does_not_nest() {
        let wrapped = "{ __type(name: \"Robot\") { ofType { ofType { ofType { name } } } } }";
        assert_eq!(shape(wrapped).depth, 2);
    }
}
