//! The one shape every HTTP route of the operator answers errors in (`{"error": code,
//! "message": text}`, with `Retry-After` where the client should come back), the bearer token of
//! a request, and the Kubernetes name rule routes check their path segments against.

use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use tracing::warn;

/// Errors answered over HTTP, as JSON; internal details are logged, never returned.
#[derive(Debug)]
pub enum ApiError {
    /// Missing or wrong credentials.
    Unauthorized(&'static str),
    /// Valid credentials that do not allow this (an enrollment token for an enrolled robot).
    Forbidden(String),
    /// A malformed request.
    BadRequest(String),
    /// The robot does not exist.
    NotFound(String),
    /// A request body beyond its route's limit: 413.
    TooLarge(String),
    /// The gateway is at its connection limit.
    Unavailable(&'static str),
    /// The gateway's budget of API reads for unauthenticated requests is spent: 503 with
    /// `Retry-After`.
    Throttled(&'static str),
    /// A robot opens sessions faster than its budget: 429 with `Retry-After` (seconds).
    TooManySessions(u64),
    /// More robots enroll than the gateway admits: 503 with `Retry-After` (seconds).
    EnrollmentsThrottled(u64),
    /// A person's or tool's requests to the Fleet API exceed their user's budget: 429 with
    /// `Retry-After` (seconds).
    RateLimited(u64),
    /// Something failed on our side.
    Internal(String),
}

/// A JSON error that tells the client when to come back (`Retry-After`, in seconds).
fn retry_later(status: StatusCode, code: &str, message: &str, seconds: u64) -> Response {
    let body = serde_json::json!({ "error": code, "message": message });
    (
        status,
        [
            (header::CONTENT_TYPE, "application/json".to_owned()),
            (header::RETRY_AFTER, seconds.to_string()),
        ],
        body.to_string(),
    )
        .into_response()
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let (status, code, message) = match self {
            ApiError::Unauthorized(m) => (StatusCode::UNAUTHORIZED, "unauthorized", m.to_owned()),
            ApiError::Forbidden(m) => (StatusCode::FORBIDDEN, "forbidden", m),
            ApiError::BadRequest(m) => (StatusCode::BAD_REQUEST, "bad_request", m),
            ApiError::NotFound(m) => (StatusCode::NOT_FOUND, "not_found", m),
            ApiError::TooLarge(m) => (StatusCode::PAYLOAD_TOO_LARGE, "too_large", m),
            ApiError::Unavailable(m) => {
                (StatusCode::SERVICE_UNAVAILABLE, "unavailable", m.to_owned())
            }
            ApiError::Throttled(m) => {
                return retry_later(StatusCode::SERVICE_UNAVAILABLE, "unavailable", m, 1);
            }
            ApiError::TooManySessions(seconds) => {
                return retry_later(
                    StatusCode::TOO_MANY_REQUESTS,
                    "too_many_sessions",
                    "this robot opens sessions too often; retry after Retry-After seconds",
                    seconds,
                );
            }
            ApiError::EnrollmentsThrottled(seconds) => {
                return retry_later(
                    StatusCode::SERVICE_UNAVAILABLE,
                    "unavailable",
                    "the gateway admits enrollments at a limited rate; retry after Retry-After seconds",
                    seconds,
                );
            }
            ApiError::RateLimited(seconds) => {
                return retry_later(
                    StatusCode::TOO_MANY_REQUESTS,
                    "rate_limited",
                    "too many requests from this user; retry after Retry-After seconds",
                    seconds,
                );
            }
            ApiError::Internal(detail) => {
                warn!(%detail, "internal error answering a request");
                (
                    StatusCode::INTERNAL_SERVER_ERROR,
                    "internal",
                    "internal error".to_owned(),
                )
            }
        };
        let body = serde_json::json!({ "error": code, "message": message });
        (
            status,
            [(header::CONTENT_TYPE, "application/json")],
            body.to_string(),
        )
            .into_response()
    }
}

/// The bearer token of a request, if any.
pub fn bearer(headers: &HeaderMap) -> Option<&str> {
    headers
        .get(header::AUTHORIZATION)?
        .to_str()
        .ok()?
        .strip_prefix("Bearer ")
        .map(str::trim)
}

/// Whether `name` is a valid Kubernetes object name (RFC 1123 subdomain).
pub fn valid_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 253
        && name.split('.').all(|part| {
            !part.is_empty()
                && part
                    .bytes()
                    .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-')
                && !part.starts_with('-')
                && !part.ends_with('-')
        })
}

/// Why a request was refused before it reached its route (logged and counted; never with the
/// token). The robots' routes refuse for every reason; the Fleet API for a missing or wrong
/// token and a throttled review.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refusal {
    /// No `Authorization: Bearer` header.
    MissingToken,
    /// The robot header is absent or not a valid name.
    BadRobotName,
    /// The robot's name is longer than a robot with a token can have (63 characters).
    RobotNameTooLong,
    /// A token nobody accepts (no robot's, no enrollment token, or one the API server refuses).
    WrongToken,
    /// An enrollment token where only the robot's own token may speak for it (legacy polls).
    EnrollmentToken,
    /// The cache could not decide and the budget of API reads for unauthenticated requests
    /// is spent: 503, retry later.
    Throttled,
}

impl Refusal {
    /// Bounded metric label and log text.
    pub fn as_str(self) -> &'static str {
        match self {
            Refusal::MissingToken => "missing_token",
            Refusal::BadRobotName => "bad_robot_name",
            Refusal::RobotNameTooLong => "robot_name_too_long",
            Refusal::WrongToken => "wrong_token",
            Refusal::EnrollmentToken => "enrollment_token",
            Refusal::Throttled => "lookup_throttled",
        }
    }

    /// The answer: 401 saying what is wrong, or 503 with `Retry-After` when throttled.
    pub fn answer(self) -> ApiError {
        ApiError::Unauthorized(match self {
            Refusal::Throttled => {
                return ApiError::Throttled(
                    "too many requests the gateway cannot authenticate from its cache; retry later",
                );
            }
            Refusal::MissingToken => "missing bearer token",
            Refusal::BadRobotName => "missing or invalid x-lekiwi-robot header (namespace/name)",
            Refusal::RobotNameTooLong => {
                "robot names are at most 63 characters (the robot's token Secret carries the name in a label)"
            }
            Refusal::WrongToken => "invalid token",
            Refusal::EnrollmentToken => {
                "an enrollment token cannot speak for a robot; use the robot's own token"
            }
        })
    }
}
