#![allow(clippy::unwrap_used)] // tests fail loudly on purpose
//! Shutting a server down, the same over plain HTTP (`http::run`) and over TLS
//! (`http::run_tls`), on real sockets with a raw HTTP/1.1 client:
//!
//! - open change feeds end at once, with the response's last chunk, and the server stops; the
//!   grace is an hour here, so neither can be the grace running out;
//! - a request that would never finish (its body never comes) is cut when the grace runs out,
//!   and the server stops.
//!
//! The TLS server gets a certificate made by `openssl` (as `.ci/run` installs it); the client
//! trusts exactly that certificate.

use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::catalog::Catalog;
use isovox_server::generate::WorldSource;
use isovox_server::http::{run, run_tls, AppState, ServerConfig};
use isovox_server::store::{build_vod2, BuildOptions};
use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio_rustls::rustls;
use tokio_rustls::rustls::client::danger::{
    HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier,
};
use tokio_rustls::rustls::crypto::CryptoProvider;
use tokio_rustls::rustls::pki_types::pem::PemObject;
use tokio_rustls::rustls::pki_types::{CertificateDer, ServerName, UnixTime};
use tokio_rustls::rustls::{DigitallySignedStruct, SignatureScheme};

/// Far longer than anything here should take: reaching it means the shutdown hangs.
const HANGS: Duration = Duration::from_secs(60);

/// A byte stream to the server, plain or TLS.
trait Stream: AsyncRead + AsyncWrite + Unpin + Send {}
impl<T: AsyncRead + AsyncWrite + Unpin + Send> Stream for T {}

/// The TLS side of a test: the server's settings and a client that trusts its certificate.
struct Tls {
    server: Arc<rustls::ServerConfig>,
    client: tokio_rustls::TlsConnector,
    _dir: tempfile::TempDir,
}

fn tls() -> Tls {
    let dir = tempfile::tempdir().unwrap();
    let (cert, key) = (dir.path().join("cert.pem"), dir.path().join("key.pem"));
    let made = std::process::Command::new("openssl")
        .args(["req", "-x509", "-newkey", "ec", "-pkeyopt"])
        .args(["ec_paramgen_curve:prime256v1", "-nodes", "-days", "2"])
        .args([
            "-subj",
            "/CN=127.0.0.1",
            "-addext",
            "subjectAltName=IP:127.0.0.1",
        ])
        .arg("-keyout")
        .arg(&key)
        .arg("-out")
        .arg(&cert)
        .output()
        .unwrap_or_else(|e| panic!("cannot run openssl (install it, as .ci/run does): {e}"));
    assert!(made.status.success(), "openssl: {made:?}");
    let server = isovox_server::http::tls::config(&cert, &key).unwrap();
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let pinned = Pinned {
        cert: CertificateDer::from_pem_file(&cert).unwrap(),
        provider: provider.clone(),
    };
    let mut client = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .unwrap()
        .dangerous()
        .with_custom_certificate_verifier(Arc::new(pinned))
        .with_no_client_auth();
    client.alpn_protocols = vec![b"http/1.1".to_vec()];
    Tls {
        server,
        client: tokio_rustls::TlsConnector::from(Arc::new(client)),
        _dir: dir,
    }
}

/// Trusts one certificate, the test's own (self-signed, so no certificate authority vouches
/// for it); the handshake's signatures are checked as usual.
#[derive(Debug)]
struct Pinned {
    cert: CertificateDer<'static>,
    provider: Arc<CryptoProvider>,
}

impl ServerCertVerifier for Pinned {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        _: &[CertificateDer<'_>],
        _: &ServerName<'_>,
        _: &[u8],
        _: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        if end_entity.as_ref() == self.cert.as_ref() {
            Ok(ServerCertVerified::assertion())
        } else {
            Err(rustls::Error::General("not the test's certificate".into()))
        }
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls12_signature(
            message,
            cert,
            dss,
            &self.provider.signature_verification_algorithms,
        )
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls13_signature(
            message,
            cert,
            dss,
            &self.provider.signature_verification_algorithms,
        )
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.provider
            .signature_verification_algorithms
            .supported_schemes()
    }
}

/// A small world `w.vod` in `dir`.
fn world(dir: &Path) {
    let layout = VolumeLayout::new([64, 32, 64], 16, VoxelType::U8).unwrap();
    let source = WorldSource::new(layout.clone(), 7);
    build_vod2(
        &dir.join("w.vod"),
        &layout,
        [1.0; 3],
        &source,
        &BuildOptions::default(),
    )
    .unwrap();
}

/// A server on an ephemeral port, plain or TLS: where it listens, the sender that starts its
/// shutdown, and the task that ends when the shutdown is done.
struct Running {
    addr: SocketAddr,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<std::io::Result<()>>,
}

async fn start(dir: &Path, grace: Duration, tls: Option<&Tls>) -> Running {
    let config = ServerConfig {
        shutdown_grace: grace,
        ..ServerConfig::default()
    };
    let state = AppState::with_config(Catalog::open_dir(dir).unwrap(), config);
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let shutdown = async {
        let _ = stopped.await;
    };
    let task = match tls {
        None => tokio::spawn(run(listener, state, shutdown)),
        Some(tls) => tokio::spawn(run_tls(listener, tls.server.clone(), state, shutdown)),
    };
    Running { addr, stop, task }
}

async fn connect(addr: SocketAddr, tls: Option<&Tls>) -> Box<dyn Stream> {
    let tcp = TcpStream::connect(addr).await.unwrap();
    match tls {
        None => Box::new(tcp),
        Some(tls) => {
            let name = ServerName::IpAddress(addr.ip().into());
            Box::new(tls.client.connect(name, tcp).await.unwrap())
        }
    }
}

/// Reads until `bytes` holds `needle`.
async fn read_until(stream: &mut dyn Stream, bytes: &mut Vec<u8>, needle: &str) {
    let mut buf = [0u8; 4096];
    while !String::from_utf8_lossy(bytes).contains(needle) {
        let n = stream.read(&mut buf).await.unwrap();
        assert!(n > 0, "the connection closed before {needle:?}: {bytes:?}");
        bytes.extend_from_slice(&buf[..n]);
    }
}

/// Reads until the server closes the connection (a TLS connection cut without `close_notify`
/// ends with an error, which counts as closed too).
async fn read_to_close(stream: &mut dyn Stream, bytes: &mut Vec<u8>) {
    let mut buf = [0u8; 4096];
    while let Ok(n @ 1..) = stream.read(&mut buf).await {
        bytes.extend_from_slice(&buf[..n]);
    }
}

/// Starts the shutdown and waits until the server has stopped.
async fn stop(server: Running, which: &str) {
    let _ = server.stop.send(());
    tokio::time::timeout(HANGS, server.task)
        .await
        .unwrap_or_else(|_| panic!("{which}: the server did not stop within {HANGS:?}"))
        .unwrap()
        .unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_ends_open_change_feeds_over_http_and_tls() {
    let dir = tempfile::tempdir().unwrap();
    world(dir.path());
    let tls = tls();
    for tls in [None, Some(&tls)] {
        let which = if tls.is_some() { "TLS" } else { "plain HTTP" };
        let server = start(dir.path(), Duration::from_secs(3600), tls).await;
        let mut feeds = Vec::new();
        for _ in 0..3 {
            let mut feed = connect(server.addr, tls).await;
            feed.write_all(b"GET /v1/volumes/w/events HTTP/1.1\r\nHost: isovox\r\n\r\n")
                .await
                .unwrap();
            let mut bytes = Vec::new();
            read_until(feed.as_mut(), &mut bytes, "event: hello").await;
            let head = String::from_utf8_lossy(&bytes).to_string();
            assert!(head.starts_with("HTTP/1.1 200"), "{which}: {head}");
            assert!(head.contains("text/event-stream"), "{which}: {head}");
            feeds.push((feed, bytes));
        }

        // The server stops although the feeds' clients have not read a byte since: it does not
        // wait for them.
        stop(server, which).await;
        for (mut feed, mut bytes) in feeds {
            tokio::time::timeout(HANGS, read_to_close(feed.as_mut(), &mut bytes))
                .await
                .unwrap_or_else(|_| panic!("{which}: a feed was still open after {HANGS:?}"));
            // The chunked response ended with its last chunk: the feed ended, it was not cut.
            let text = String::from_utf8_lossy(&bytes);
            assert!(text.ends_with("\r\n0\r\n\r\n"), "{which}: {text:?}");
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_closes_a_request_still_running_when_the_grace_runs_out() {
    let dir = tempfile::tempdir().unwrap();
    world(dir.path());
    let tls = tls();
    for tls in [None, Some(&tls)] {
        let which = if tls.is_some() { "TLS" } else { "plain HTTP" };
        let server = start(dir.path(), Duration::from_millis(200), tls).await;
        // A batch request whose body never comes: it would wait for it forever.
        let mut stalled = connect(server.addr, tls).await;
        stalled
            .write_all(
                b"POST /v1/volumes/w/batch HTTP/1.1\r\nHost: isovox\r\n\
                  Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{\"keys\":",
            )
            .await
            .unwrap();
        stalled.flush().await.unwrap();
        // The server is serving: another connection is answered meanwhile.
        let mut other = connect(server.addr, tls).await;
        other
            .write_all(b"GET /healthz HTTP/1.1\r\nHost: isovox\r\n\r\n")
            .await
            .unwrap();
        let mut answer = Vec::new();
        read_until(other.as_mut(), &mut answer, "\r\n\r\nok").await;

        stop(server, which).await;
        let mut bytes = Vec::new();
        tokio::time::timeout(HANGS, read_to_close(stalled.as_mut(), &mut bytes))
            .await
            .unwrap_or_else(|_| panic!("{which}: the stalled request's connection stayed open"));
        // Closed without an answer: the request was cut, not answered.
        assert!(
            bytes.is_empty(),
            "{which}: {:?}",
            String::from_utf8_lossy(&bytes)
        );
    }
}
