//! The metrics reference: every metric in the operator's registry, with its type and help.

use crate::md;

/// The page, from the registry's catalogue with every subsystem registered (per-robot series
/// included).
pub fn page() -> String {
    let metrics = lekiwi_metrics::Metrics::new(true);
    let rows: Vec<Vec<String>> = metrics
        .catalogue()
        .iter()
        .map(|m| {
            vec![
                md::code(&exposed(&m.name, &m.kind)),
                m.kind.clone(),
                md::cell(&m.help),
            ]
        })
        .collect();
    let mut out = md::generated_note("the operator's metrics registry (`lekiwi_metrics`)");
    out.push_str(
        "# Metrics\n\n\
         Every metric the operator serves on `/metrics` (`--http-addr`), in the OpenMetrics text \
         format, in the order it is exported; a metric appears in a scrape once it has a series. \
         A counter is exported with the suffix `_total`, a histogram as `_bucket`, `_sum` and \
         `_count`. The `lekiwi_robot_*` series exist only with `--per-robot-metrics`. Labels are \
         bounded: their values are the ones the description names, never text a robot sends.\n\n",
    );
    out.push_str(&md::table(&["Metric", "Type", "Description"], &rows));
    out
}

/// The name a scrape shows: counters carry `_total`.
fn exposed(name: &str, kind: &str) -> String {
    if kind == "counter" && !name.ends_with("_total") {
        format!("{name}_total")
    } else {
        name.to_owned()
    }
}
