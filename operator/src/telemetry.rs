//! Logging and tracing: `tracing` with an env-filter, as text or JSON, plus OpenTelemetry span
//! export over OTLP when the standard `OTEL_EXPORTER_OTLP_ENDPOINT` (or
//! `OTEL_EXPORTER_OTLP_TRACES_ENDPOINT`) is set; off otherwise.
//!
//! Exported spans are the ones the operator already makes: `reconcile` (per controller and
//! object), `session` (one agent connection), `blob_download` and `blob_upload`. The exporter
//! follows the standard variables: `OTEL_EXPORTER_OTLP_PROTOCOL` (`http/protobuf`, the default,
//! or `http/json`), `OTEL_SERVICE_NAME` (default `lekiwi-operator`), `OTEL_RESOURCE_ATTRIBUTES`,
//! `OTEL_EXPORTER_OTLP_HEADERS`, `OTEL_BSP_SCHEDULE_DELAY`, ...

use opentelemetry::trace::TracerProvider as _;
use opentelemetry_otlp::{Protocol, WithExportConfig};
use opentelemetry_sdk::Resource;
use opentelemetry_sdk::trace::SdkTracerProvider;
use std::io::IsTerminal;

use tracing_subscriber::{EnvFilter, Layer, fmt, prelude::*};

use crate::config::LogFormat;

/// Keeps the span exporter alive; [`Telemetry::shutdown`] flushes what is buffered.
pub struct Telemetry {
    provider: Option<SdkTracerProvider>,
}

impl Telemetry {
    /// Whether spans are exported.
    pub fn exporting(&self) -> bool {
        self.provider.is_some()
    }

    /// Flushes and stops the exporter (at most a few seconds).
    pub fn shutdown(self) {
        if let Some(p) = self.provider
            && let Err(e) = p.shutdown()
        {
            eprintln!("lekiwi-operator: flushing OpenTelemetry spans failed: {e}");
        }
    }
}

fn env_set(name: &str) -> bool {
    std::env::var(name).is_ok_and(|v| !v.trim().is_empty())
}

/// The values of `OTEL_EXPORTER_OTLP_PROTOCOL` the exporter takes (empty: the default,
/// `http/protobuf`). The chart's schema accepts exactly these (a test compares the two).
pub const OTLP_PROTOCOLS: [&str; 3] = ["", "http/protobuf", "http/json"];

/// The exporter protocol `value` names, or why it is refused.
fn otlp_protocol(value: &str) -> Result<Protocol, String> {
    match value.trim() {
        "" | "http/protobuf" => Ok(Protocol::HttpBinary),
        "http/json" => Ok(Protocol::HttpJson),
        other => Err(format!(
            "OTEL_EXPORTER_OTLP_PROTOCOL={other:?} is not supported: use http/protobuf or http/json"
        )),
    }
}

/// The OTLP span exporter and its provider, when the environment asks for one.
fn otlp() -> Result<Option<SdkTracerProvider>, Box<dyn std::error::Error + Send + Sync>> {
    if !env_set("OTEL_EXPORTER_OTLP_ENDPOINT") && !env_set("OTEL_EXPORTER_OTLP_TRACES_ENDPOINT") {
        return Ok(None);
    }
    let protocol = otlp_protocol(
        &std::env::var("OTEL_EXPORTER_OTLP_TRACES_PROTOCOL")
            .or_else(|_| std::env::var("OTEL_EXPORTER_OTLP_PROTOCOL"))
            .unwrap_or_default(),
    )?;
    // The endpoint and headers come from the standard variables, read by the exporter.
    let exporter = opentelemetry_otlp::SpanExporter::builder()
        .with_http()
        .with_protocol(protocol)
        .build()?;
    let service =
        std::env::var("OTEL_SERVICE_NAME").unwrap_or_else(|_| "lekiwi-operator".to_owned());
    let resource = Resource::builder()
        .with_service_name(service)
        .with_attribute(opentelemetry::KeyValue::new(
            "service.version",
            env!("CARGO_PKG_VERSION"),
        ))
        .build();
    Ok(Some(
        SdkTracerProvider::builder()
            .with_batch_exporter(exporter)
            .with_resource(resource)
            .build(),
    ))
}

/// Installs the global subscriber: logs, and spans over OTLP when configured.
pub fn init(
    format: &LogFormat,
    filter: &str,
) -> Result<Telemetry, Box<dyn std::error::Error + Send + Sync>> {
    let filter = EnvFilter::try_new(filter)?;
    let provider = otlp()?;
    let otel = provider.as_ref().map(|p| {
        tracing_opentelemetry::layer()
            .with_tracer(p.tracer("lekiwi-operator"))
            .boxed()
    });
    let logs = match format {
        LogFormat::Json => fmt::layer()
            .json()
            .flatten_event(true)
            .with_current_span(true)
            .boxed(),
        // No colour codes in a file or the journal: only a terminal gets them.
        LogFormat::Text => fmt::layer()
            .with_target(false)
            .with_ansi(std::io::stdout().is_terminal())
            .boxed(),
    };
    tracing_subscriber::registry()
        .with(filter)
        .with(logs)
        .with(otel)
        .try_init()?;
    if provider.is_some() {
        tracing::info!("exporting spans over OTLP");
    }
    Ok(Telemetry { provider })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What the chart's schema lets a user set as `otel.protocol` is exactly what the operator
    /// starts with: a value the schema passes never crash-loops the Pod.
    #[test]
    fn the_charts_otel_protocols_are_the_ones_the_exporter_takes() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../charts/lekiwi-operator/values.schema.json"
        );
        let schema: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        let allowed: Vec<&str> = schema["properties"]["otel"]["properties"]["protocol"]["enum"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap())
            .collect();
        assert_eq!(allowed, OTLP_PROTOCOLS);
        for p in OTLP_PROTOCOLS {
            assert!(otlp_protocol(p).is_ok(), "{p:?}");
        }
        assert!(otlp_protocol("grpc").unwrap_err().contains("grpc"));
    }
}
