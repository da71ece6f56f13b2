//! TLS for the requests this process makes (http(s) imports, the object store): rustls with
//! ring, as the HTTPS listener uses, trusting the system's certificate store.
//!
//! reqwest 0.13 builds in aws-lc-rs as its only crypto provider; Isovox keeps ring (no aws-lc C
//! build) and so enables reqwest's `rustls-no-provider`. reqwest then takes rustls's
//! process-wide default provider, and panics when a client is built before one is installed.
//! Cargo unifies features across a build, so any reqwest client in a program that links this
//! crate (the typed client in the tools and tests included) has TLS and needs the provider.

use tokio_rustls::rustls::crypto::ring;

/// Makes ring rustls's process-wide crypto provider, unless the program installed one already
/// (then that one stays). Cheap and idempotent: call it before building any reqwest client.
pub fn install_provider() {
    // An error only says that a provider is installed already, which is all that is needed.
    let _ = ring::default_provider().install_default();
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_client_with_tls_builds_once_the_provider_is_installed() {
        super::install_provider();
        super::install_provider();
        assert!(tokio_rustls::rustls::crypto::CryptoProvider::get_default().is_some());
        assert!(reqwest::blocking::Client::builder().build().is_ok());
    }
}
