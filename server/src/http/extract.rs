//! axum's extractors with [`ApiError`] as their rejection: a malformed path, query or body is
//! answered as problem details by `http/error.rs` like every other error, and handlers take
//! their arguments directly.

use super::request_body::read_json;
use super::{ApiError, AppState};
use crate::decimal::{self, NotCanonical};
use crate::volume::history::valid_tag;
use axum::extract::{FromRequest, FromRequestParts, MatchedPath, Request};
use axum::http::request::Parts;
use axum::http::Uri;
use serde::de::DeserializeOwned;
use serde::Deserialize;
use std::str::FromStr;

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

/// The `{name}` parameter of a route whose other parameters are read from [`RawPath`].
#[derive(Debug, Deserialize)]
pub struct Named {
    /// The volume's name (percent-decoded).
    pub name: String,
}

/// A route's path parameters as the client spelled them (not percent-decoded): for what must be
/// read exactly as sent, numbers (one spelling each, [`crate::decimal`]) and a view's path
/// within the view (`zarr%2Ejson` is not `zarr.json`).
#[derive(Debug)]
pub struct RawPath {
    uri: Uri,
    template: MatchedPath,
}

impl RawPath {
    /// Parameter `name` as sent: its segment, or for `{*name}` the rest of the path.
    pub fn param(&self, name: &str) -> Option<&str> {
        let (mut template, mut rest) = (self.template.as_str(), self.uri.path());
        loop {
            let (t, t_tail) = template.split_once('/').unwrap_or((template, ""));
            if t.strip_prefix("{*").and_then(|t| t.strip_suffix('}')) == Some(name) {
                return Some(rest);
            }
            let (seg, tail) = rest.split_once('/').unwrap_or((rest, ""));
            if t.strip_prefix('{').and_then(|t| t.strip_suffix('}')) == Some(name) {
                return Some(seg);
            }
            if template.is_empty() {
                return None;
            }
            (template, rest) = (t_tail, tail);
        }
    }

    /// Parameter `name` read as a number: 404 for another spelling of a number, 400 for text
    /// that is none (as axum's parser answered it).
    ///
    /// # Errors
    /// As said, and 500 if the route has no such parameter (a bug).
    pub fn number<T: FromStr>(&self, name: &str) -> Result<T, ApiError> {
        let raw = self.param(name).ok_or_else(|| {
            ApiError::Internal(format!(
                "route {} has no {{{name}}}",
                self.template.as_str()
            ))
        })?;
        number(raw, &format!("{name} in the path"))
    }
}

impl<S: Send + Sync> FromRequestParts<S> for RawPath {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, _state: &S) -> Result<Self, ApiError> {
        let template = parts
            .extensions
            .get::<MatchedPath>()
            .cloned()
            .ok_or_else(|| ApiError::Internal("a routed request without its route".into()))?;
        Ok(RawPath {
            uri: parts.uri.clone(),
            template,
        })
    }
}

/// `raw` (as sent) as a number, `what` naming it in the error.
fn number<T: FromStr>(raw: &str, what: &str) -> Result<T, ApiError> {
    decimal::parse(raw).map_err(|e| match e {
        NotCanonical::OtherSpelling => ApiError::NotFound(format!(
            "{what} is {raw:?}: numbers in URLs are plain decimal digits without a sign, \
             leading zeros or escapes, and no other spelling names anything"
        )),
        NotCanonical::NotANumber => {
            ApiError::BadRequest(format!("malformed {what}: {raw:?} is not a number"))
        }
    })
}

/// Query parameter `key` of `uri` read as a number, as sent (see [`crate::decimal`]); `None`
/// when the query does not have it.
///
/// # Errors
/// 404 for another spelling of a number, 400 for text that is none or a parameter given twice.
pub fn query_number<T: FromStr>(uri: &Uri, key: &str) -> Result<Option<T>, ApiError> {
    let mut values = uri
        .query()
        .unwrap_or_default()
        .split('&')
        .filter_map(|pair| pair.split_once('=').filter(|(k, _)| *k == key));
    let Some((_, raw)) = values.next() else {
        return Ok(None);
    };
    if values.next().is_some() {
        return Err(ApiError::BadRequest(format!(
            "malformed query: {key} is given more than once"
        )));
    }
    number(raw, &format!("?{key}")).map(Some)
}

/// `?version=N` or `?version=TAG`: the version to read, the newest when absent; `N` read as
/// [`query_number`] says, a tag looked up in the volume of the path (404 when it has none of
/// that name).
#[derive(Debug, Clone, Copy)]
pub struct VersionParam(pub Option<u64>);

impl FromRequestParts<AppState> for VersionParam {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &AppState) -> Result<Self, ApiError> {
        let mut given = parts
            .uri
            .query()
            .unwrap_or_default()
            .split('&')
            .filter_map(|pair| pair.strip_prefix("version="));
        // Given twice: `query_number` says so.
        match (given.next(), given.next()) {
            (Some(tag), None) if valid_tag(tag) => {
                let name = parts
                    .uri
                    .path()
                    .strip_prefix("/v1/volumes/")
                    .and_then(|rest| rest.split('/').next())
                    .map(|n| percent_encoding::percent_decode_str(n).decode_utf8_lossy())
                    .ok_or_else(|| ApiError::BadRequest("?version=TAG needs a volume".into()))?
                    .into_owned();
                let tag = tag.to_string();
                // Reading the history may wait on an object store: where `read_volume` says.
                let version = state
                    .read_volume(&name, move |_, vol| vol.tagged(&tag))
                    .await?;
                Ok(VersionParam(Some(version)))
            }
            _ => query_number(&parts.uri, "version").map(VersionParam),
        }
    }
}

/// `?channel=NAME`: which stream of a volume to read: an attribute channel by name, or
/// `density` (the default when absent).
#[derive(Debug, Clone)]
pub struct ChannelParam(pub Option<String>);

impl<S: Send + Sync> FromRequestParts<S> for ChannelParam {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, _: &S) -> Result<Self, ApiError> {
        let mut given = parts
            .uri
            .query()
            .unwrap_or_default()
            .split('&')
            .filter_map(|pair| pair.strip_prefix("channel="));
        match (given.next(), given.next()) {
            (None, _) => Ok(ChannelParam(None)),
            (Some(_), Some(_)) => Err(ApiError::BadRequest(
                "?channel= is given twice: name one channel".into(),
            )),
            (Some(name), None) => {
                let name = percent_encoding::percent_decode_str(name).decode_utf8_lossy();
                let plain = !name.is_empty()
                    && name.len() <= isovox_proto::channel::MAX_NAME_LEN
                    && name.bytes().all(|c| c.is_ascii_alphanumeric() || c == b'_');
                if !plain {
                    return Err(ApiError::BadRequest(format!(
                        "?channel={name:?} is not a channel name (letters, digits and _)"
                    )));
                }
                Ok(ChannelParam((name != "density").then(|| name.into_owned())))
            }
        }
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
        read_json(&parts.headers, body, MAX_JSON_BODY, "a JSON request body")
            .await
            .map(Json)
    }
}
