//! Who a Fleet API request comes from and whether it may go on: a person's bearer token and
//! permission checked ([`FleetState::check_user`]), and the answers to a request that is not let
//! through (401, 403, 503), each counted in `lekiwi_gateway_refused_total{kind}`.

use axum::http::HeaderMap;
use lekiwi_metrics::KindLabels;
use tracing::warn;

use crate::kube_auth;
use crate::{ApiError, FleetState, bearer};
use lekiwi_core::http::Refusal;

impl FleetState {
    /// Counts a refused request in `lekiwi_gateway_refused_total{kind}`.
    pub fn count_refusal(&self, kind: &'static str) {
        self.metrics
            .refused
            .get_or_create(&KindLabels { kind })
            .inc();
    }

    /// Counts and logs a refused request (a missing or wrong token, a throttled review) and
    /// answers it (401, or 503 with `Retry-After`).
    pub fn refused(&self, reason: Refusal) -> ApiError {
        self.count_refusal(reason.as_str());
        // Never log the token itself.
        warn!(reason = reason.as_str(), "refused an API request");
        reason.answer()
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
