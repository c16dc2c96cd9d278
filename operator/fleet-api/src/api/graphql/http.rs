//! `POST /api/v1/graphql`: one query or mutation in a JSON body of at most
//! `--graphql-max-body-bytes` (beyond, 413 before the body is read further), answered as
//! `application/json`, or as `application/graphql-response+json` to a client whose `Accept`
//! names it (GraphQL over HTTP). Whatever is refused before the query runs (401, 429, 413, 400)
//! is the Fleet API's JSON error, never a bare status.

use axum::body::{Body, Bytes};
use axum::extract::State;
use axum::http::{HeaderMap, header};
use axum::response::{IntoResponse, Response};
use http_body_util::{BodyExt, LengthLimitError, Limited};

use super::Caller;
use crate::api::authorize;
use crate::{ApiError, FleetState, bearer};

/// The GraphQL-over-HTTP media type, answered to clients that ask for it.
pub const GRAPHQL_RESPONSE: &str = "application/graphql-response+json";

/// What a body must be, for the messages of a 400.
const SHAPE: &str = r#"{"query": "...", "variables": {...}, "operationName": "..."}"#;

/// `POST /api/v1/graphql`: the token is checked and its user's budget taken first (401, 429),
/// then the body is read (413 beyond the limit, 400 unless it is a GraphQL request), then the
/// query runs (200 with GraphQL's `{"data", "errors"}`).
pub async fn post(
    State(state): State<FleetState>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    let user = authorize(&state, &headers, None).await?;
    let gql = state.fleet.graphql.clone();
    let bytes = read(&headers, body, gql.max_body_bytes).await?;
    let request = gql.guard.run(|| decode(&bytes)).await?;
    let token = bearer(&headers).unwrap_or_default().to_owned();
    let request = request.data(Caller { token, user }).data(state);
    let response = gql.schema.execute(request).await;
    Ok(respond(&headers, &response))
}

/// The bytes of `body`: 413 when it is (or says it is) longer than `max` bytes.
async fn read(headers: &HeaderMap, body: Body, max: usize) -> Result<Bytes, ApiError> {
    let declared = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    if declared.is_some_and(|n| n > max as u64) {
        return Err(too_large(max));
    }
    match Limited::new(body, max).collect().await {
        Ok(collected) => Ok(collected.to_bytes()),
        Err(e) if e.is::<LengthLimitError>() => Err(too_large(max)),
        Err(e) => Err(ApiError::BadRequest(format!(
            "reading the request body failed: {e}"
        ))),
    }
}

/// The GraphQL request in `bytes`: 400 unless it is a JSON object with a `query`.
fn decode(bytes: &[u8]) -> Result<async_graphql::Request, ApiError> {
    let request: async_graphql::Request = serde_json::from_slice(bytes)
        .map_err(|e| ApiError::BadRequest(format!("the body must be {SHAPE}: {e}")))?;
    if request.query.trim().is_empty() {
        return Err(ApiError::BadRequest(format!(
            "the body names no query; it must be {SHAPE}"
        )));
    }
    Ok(request)
}

fn too_large(max: usize) -> ApiError {
    ApiError::TooLarge(format!(
        "a GraphQL request is at most {max} bytes (--graphql-max-body-bytes)"
    ))
}

/// `response` as JSON, with the media type the client accepts.
fn respond(headers: &HeaderMap, response: &async_graphql::Response) -> Response {
    let media = if accepts(headers, GRAPHQL_RESPONSE) {
        GRAPHQL_RESPONSE
    } else {
        "application/json"
    };
    match serde_json::to_vec(response) {
        Ok(body) => ([(header::CONTENT_TYPE, media)], body).into_response(),
        Err(e) => {
            ApiError::Internal(format!("serializing a GraphQL response: {e}")).into_response()
        }
    }
}

/// Whether the request's `Accept` names `media` (parameters such as `q` aside).
fn accepts(headers: &HeaderMap, media: &str) -> bool {
    headers
        .get_all(header::ACCEPT)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .filter_map(|range| range.split(';').next())
        .any(|m| m.trim().eq_ignore_ascii_case(media))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(pairs: &[(header::HeaderName, &str)]) -> HeaderMap {
        pairs
            .iter()
            .map(|(k, v)| (k.clone(), v.parse().unwrap()))
            .collect()
    }

    #[tokio::test]
    async fn a_body_is_a_graphql_request_within_the_limit() {
        let ok = r#"{"query": "{ __typename }", "variables": null, "operationName": null}"#;
        let read_decoded = |body: &'static str| async move {
            decode(&read(&HeaderMap::new(), Body::from(body), 100).await?)
        };
        let request = read_decoded(ok).await.unwrap();
        assert_eq!(request.query, "{ __typename }");
        for (body, says) in [
            ("", "must be"),
            ("{}", "no query"),
            (r#"[{"query": "{ a }"}]"#, "must be"),
            ("query { a }", "must be"),
        ] {
            match read_decoded(body).await {
                Err(ApiError::BadRequest(m)) => assert!(m.contains(says), "{body}: {m}"),
                other => panic!("{body}: {:?}", other.map(|r| r.query)),
            }
        }
        let long = format!(r#"{{"query": "{{ __typename }} #{}"}}"#, "x".repeat(100));
        let declared = headers(&[(header::CONTENT_LENGTH, "1000000")]);
        for (headers, body) in [(HeaderMap::new(), long.clone()), (declared, String::new())] {
            assert!(matches!(
                read(&headers, Body::from(body), 100).await,
                Err(ApiError::TooLarge(_))
            ));
        }
    }

    #[test]
    fn the_media_type_is_the_one_the_client_accepts() {
        let media = |accept: Option<&str>| {
            let h = accept.map_or_else(HeaderMap::new, |a| headers(&[(header::ACCEPT, a)]));
            let response = respond(
                &h,
                &async_graphql::Response::new(async_graphql::Value::Null),
            );
            response.headers()[header::CONTENT_TYPE].to_owned()
        };
        assert_eq!(media(None), "application/json");
        assert_eq!(media(Some("*/*")), "application/json");
        assert_eq!(media(Some("application/json")), "application/json");
        let both = "application/graphql-response+json, application/json;q=0.9";
        assert_eq!(media(Some(both)), GRAPHQL_RESPONSE);
    }
}
