//! Who a Fleet API request comes from and whether it may go on: a person's bearer token and
//! permission checked ([`FleetState::check_user`]), and the answers to a request that is not let
//! through (401, 403, 503), each counted in `lekiwi_gateway_refused_total{kind}`.

use axum::http::HeaderMap;
use lekiwi_metrics::KindLabels;
use tracing::warn;

use crate::kube_auth;
use crate::{ApiError, FleetState, bearer};

/// Why a person's or tool's request was refused before any permission check.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refusal {
    /// No `Authorization: Bearer` header.
    MissingToken,
    /// A token the API server does not accept.
    WrongToken,
    /// Token reviews are beyond their budget: 503, retry later.
    Throttled,
}

impl Refusal {
    /// Bounded metric label and log text, the same as the robots' refusals of that kind.
    pub fn as_str(self) -> &'static str {
        match self {
            Refusal::MissingToken => "missing_token",
            Refusal::WrongToken => "wrong_token",
            Refusal::Throttled => "lookup_throttled",
        }
    }
}

impl FleetState {
    /// Counts a refused request in `lekiwi_gateway_refused_total{kind}`.
    pub fn count_refusal(&self, kind: &'static str) {
        self.metrics
            .refused
            .get_or_create(&KindLabels { kind })
            .inc();
    }

    /// Counts and logs a refused request and answers it (401, or 503 with `Retry-After`).
    pub fn refused(&self, reason: Refusal) -> ApiError {
        self.count_refusal(reason.as_str());
        // Never log the token itself.
        warn!(reason = reason.as_str(), "refused an API request");
        match reason {
            Refusal::MissingToken => ApiError::Unauthorized("missing bearer token"),
            Refusal::WrongToken => ApiError::Unauthorized("invalid token"),
            Refusal::Throttled => ApiError::Throttled(
                "too many requests the gateway cannot authenticate from its cache; retry later",
            ),
        }
    }

    /// Lets a person's or tool's request through when the API server accepts its bearer token
    /// and RBAC allows `access` (see [`kube_auth`]): 401 for a token the API server refuses,
    /// 403 naming the missing permission, 400 when the request names no namespace (`None`).
    pub async fn check_user(
        &self,
        headers: &HeaderMap,
        access: Option<kube_auth::Access>,
    ) -> Result<(), ApiError> {
        let Some(token) = bearer(headers).filter(|t| !t.is_empty()) else {
            return Err(self.refused(Refusal::MissingToken));
        };
        let Some(access) = access else {
            return Err(ApiError::BadRequest(
                "name the namespace: ?namespace=NAME".into(),
            ));
        };
        self.kube_auth
            .check(token, &access)
            .await
            .map_err(|d| self.denied(d))
    }

    /// The answer to a request [`kube_auth`] did not let through: 401 for a token the API
    /// server refuses, 403 naming the missing permission, 503 when reviews are throttled.
    pub fn denied(&self, denied: kube_auth::Denied) -> ApiError {
        match denied {
            kube_auth::Denied::Unauthenticated => self.refused(Refusal::WrongToken),
            kube_auth::Denied::Forbidden(permission) => {
                self.count_refusal("forbidden");
                // The code (`forbidden`) is the body's `error`; GraphQL puts it before the message.
                ApiError::Forbidden(format!("this needs {permission}"))
            }
            kube_auth::Denied::Unavailable(detail) => ApiError::Internal(detail),
            kube_auth::Denied::Throttled => self.refused(Refusal::Throttled),
        }
    }
}
