//! Helpers the end-to-end tests share. Nothing here calls the code under test beyond starting
//! it.
#![allow(dead_code)] // each module uses its own share of the helpers

use isovox_proto::api::Problem;
use isovox_server::catalog::Catalog;
use isovox_server::http::{spawn, AppState, ServerConfig, Spawned};
use std::path::Path;

/// Serves every volume of `dir` as `config` says, on an ephemeral port, until dropped.
pub(crate) async fn serve(dir: &Path, config: ServerConfig) -> Spawned {
    let catalog = Catalog::open_dir(dir).unwrap();
    spawn("127.0.0.1:0", AppState::with_config(catalog, config))
        .await
        .unwrap()
}

/// An HTTP client. Linked with the server, reqwest has rustls without a built-in crypto provider
/// ([`isovox_server::client_tls`]), so the provider is installed first.
pub(crate) fn http() -> reqwest::Client {
    isovox_server::client_tls::install_provider();
    reqwest::Client::new()
}

/// Checks an RFC 9457 problem-details answer with `status`.
pub(crate) async fn problem(resp: reqwest::Response, status: u16) -> Problem {
    let url = resp.url().to_string();
    let got = resp.status().as_u16();
    let ctype = resp
        .headers()
        .get("content-type")
        .map(|v| v.to_str().unwrap().to_string());
    let body = resp.bytes().await.unwrap();
    assert_eq!(
        got,
        status,
        "{url}: status (body {:?})",
        String::from_utf8_lossy(&body)
    );
    assert_eq!(
        ctype.as_deref(),
        Some("application/problem+json"),
        "{url}: content type (body {:?})",
        String::from_utf8_lossy(&body)
    );
    let p: Problem = serde_json::from_slice(&body).unwrap();
    assert_eq!(p.status, status);
    assert_eq!(p.kind, "about:blank");
    assert!(!p.title.is_empty());
    assert!(!p.detail.is_empty());
    p
}
