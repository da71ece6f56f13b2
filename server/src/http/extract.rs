//! axum's extractors with [`ApiError`] as their rejection: a malformed path, query or body is
//! answered as problem details by `http/error.rs` like every other error, and handlers take
//! their arguments directly.

use super::request_body::{is_json, read_limited};
use super::ApiError;
use axum::extract::{FromRequest, FromRequestParts, Request};
use axum::http::request::Parts;
use serde::de::DeserializeOwned;

/// Path parameters ([`axum::extract::Path`]); 400 when they do not parse.
#[derive(Debug)]
pub struct Path<T>(pub T);

impl<T, S> FromRequestParts<S> for Path<T>
where
    T: DeserializeOwned + Send,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ApiError> {
        let axum::extract::Path(value) =
            axum::extract::Path::<T>::from_request_parts(parts, state).await?;
        Ok(Path(value))
    }
}

/// The query string ([`axum::extract::Query`]); 400 when it does not parse.
#[derive(Debug)]
pub struct Query<T>(pub T);

impl<T, S> FromRequestParts<S> for Query<T>
where
    T: DeserializeOwned,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ApiError> {
        let axum::extract::Query(value) =
            axum::extract::Query::<T>::from_request_parts(parts, state).await?;
        Ok(Query(value))
    }
}

/// Largest JSON request body (batch key lists are the biggest: well under this).
pub const MAX_JSON_BODY: usize = 1 << 20;

/// A JSON body of at most [`MAX_JSON_BODY`] bytes; 400, 413 or 415 as the body is malformed,
/// too large or not JSON.
#[derive(Debug)]
pub struct Json<T>(pub T);

impl<T, S> FromRequest<S> for Json<T>
where
    T: DeserializeOwned,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request(request: Request, _state: &S) -> Result<Self, ApiError> {
        let (parts, body) = request.into_parts();
        if !is_json(&parts.headers) {
            return Err(ApiError::UnsupportedMedia(
                "the request body is JSON: send Content-Type: application/json".into(),
            ));
        }
        let bytes =
            read_limited(&parts.headers, body, MAX_JSON_BODY, "a JSON request body").await?;
        serde_json::from_slice(&bytes)
            .map(Json)
            .map_err(|e| ApiError::BadRequest(format!("malformed request body: {e}")))
    }
}
