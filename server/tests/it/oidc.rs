//! Sign-in with an OpenID Connect issuer (`serve --oidc-issuer --oidc-audience`), against the
//! real `isovox serve`: the test is the issuer. It makes an RSA and an EC P-256 key (`openssl`,
//! as the TLS tests do), signs its own JWTs with them, and serves its discovery document and
//! JWKS on 127.0.0.1 from a small thread that counts the key-set fetches, so key rotation and
//! the bound on refreshes can be seen. A last test reads the keys from a file, with an issuer
//! that cannot be reached.

use crate::server_process::ServerProcess;
use jsonwebtoken::jwk::Jwk;
use jsonwebtoken::{Algorithm, EncodingKey, Header};
use reqwest::blocking::Client;
use reqwest::header::{AUTHORIZATION, CONTENT_TYPE};
use reqwest::StatusCode;
use serde_json::{json, Value};
use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::Path;
use std::process::Command;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

pub(crate) const AUDIENCE: &str = "isovox-test";

/// A signing key of the test issuer: its kid, algorithm, private key and public JWK.
pub(crate) struct Key {
    kid: String,
    alg: Algorithm,
    private: EncodingKey,
    jwk: Value,
}

impl Key {
    /// A fresh key made by `openssl genpkey` (RSA 2048 for RS256, P-256 for ES256).
    pub(crate) fn new(dir: &Path, kid: &str, alg: Algorithm) -> Key {
        let pem = dir.join(format!("{kid}.pem"));
        let options: &[&str] = match alg {
            Algorithm::RS256 => &["-algorithm", "RSA", "-pkeyopt", "rsa_keygen_bits:2048"],
            _ => &["-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256"],
        };
        let made = Command::new("openssl")
            .arg("genpkey")
            .args(options)
            .arg("-out")
            .arg(&pem)
            .output()
            .unwrap_or_else(|e| panic!("cannot run openssl (install it, as .ci/run does): {e}"));
        assert!(made.status.success(), "openssl: {made:?}");
        let bytes = std::fs::read(&pem).unwrap();
        let private = match alg {
            Algorithm::RS256 => EncodingKey::from_rsa_pem(&bytes).unwrap(),
            _ => EncodingKey::from_ec_pem(&bytes).unwrap(),
        };
        let mut jwk = Jwk::from_encoding_key(&private, alg).unwrap();
        jwk.common.key_id = Some(kid.to_string());
        let mut jwk = serde_json::to_value(jwk).unwrap();
        jwk["use"] = json!("sig");
        Key {
            kid: kid.to_string(),
            alg,
            private,
            jwk,
        }
    }

    /// A JWT signed by this key, naming this key's kid, with `claims`.
    pub(crate) fn sign(&self, claims: &Value) -> String {
        let mut header = Header::new(self.alg);
        header.kid = Some(self.kid.clone());
        jsonwebtoken::encode(&header, claims, &self.private).unwrap()
    }
}

fn now() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_secs()
}

/// The claims of a token of `issuer` for `user` with `roles`, valid for ten minutes.
pub(crate) fn claims(issuer: &str, user: &str, roles: &[&str]) -> Value {
    json!({
        "iss": issuer,
        "aud": AUDIENCE,
        "sub": format!("id-{user}"),
        "preferred_username": user,
        "iat": now(),
        "exp": now() + 600,
        "isovox_roles": roles,
    })
}

/// The test's issuer: `/.well-known/openid-configuration` and `/jwks` on 127.0.0.1, one
/// request per connection; the key set can be replaced (rotation) and its fetches are counted.
pub(crate) struct Issuer {
    pub(crate) url: String,
    jwks: Arc<Mutex<Value>>,
    fetches: Arc<AtomicUsize>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl Issuer {
    pub(crate) fn start(keys: &[&Key]) -> Issuer {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let jwks = Arc::new(Mutex::new(Value::Null));
        let fetches = Arc::new(AtomicUsize::new(0));
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let (url, jwks, fetches, stop) =
                (url.clone(), jwks.clone(), fetches.clone(), stop.clone());
            std::thread::spawn(move || {
                for stream in listener.incoming() {
                    if stop.load(Ordering::SeqCst) {
                        break;
                    }
                    if let Ok(stream) = stream {
                        answer(stream, &url, &jwks, &fetches);
                    }
                }
            })
        };
        let issuer = Issuer {
            url,
            jwks,
            fetches,
            stop,
            thread: Some(thread),
        };
        issuer.publish(keys);
        issuer
    }

    /// Serves `keys` as the key set from now on.
    fn publish(&self, keys: &[&Key]) {
        *self.jwks.lock().unwrap() =
            json!({"keys": keys.iter().map(|k| k.jwk.clone()).collect::<Vec<_>>()});
    }

    fn fetches(&self) -> usize {
        self.fetches.load(Ordering::SeqCst)
    }
}

impl Drop for Issuer {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        // Wake the accept loop so it sees the flag.
        let _ = TcpStream::connect(self.url.trim_start_matches("http://"));
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Answers one request of the test issuer.
fn answer(mut stream: TcpStream, url: &str, jwks: &Mutex<Value>, fetches: &AtomicUsize) {
    stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") && head.len() < 16 << 10 {
        match stream.read(&mut byte) {
            Ok(1) => head.push(byte[0]),
            _ => return,
        }
    }
    let head = String::from_utf8_lossy(&head);
    let path = head.split_whitespace().nth(1).unwrap_or_default();
    let (status, body) = match path {
        "/.well-known/openid-configuration" => (
            "200 OK",
            json!({"issuer": url, "jwks_uri": format!("{url}/jwks")}).to_string(),
        ),
        "/jwks" => {
            fetches.fetch_add(1, Ordering::SeqCst);
            ("200 OK", jwks.lock().unwrap().to_string())
        }
        _ => ("404 Not Found", "{}".to_string()),
    };
    let _ = write!(
        stream,
        "HTTP/1.1 {status}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
}

/// A data directory holding the volume `w`.
fn data_dir() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_isovox"))
        .args(["generate", "world", "-o"])
        .arg(dir.path().join("w.vod"))
        .args(["--dims", "32,32,32", "--brick", "16"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "isovox generate failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    dir
}

fn serve(dir: &Path, options: &[&str]) -> ServerProcess {
    let mut args: Vec<&std::ffi::OsStr> = vec!["--data".as_ref(), dir.as_os_str()];
    args.extend(options.iter().map(std::ffi::OsStr::new));
    // Info logs: the edits name their user, and no token may show up there.
    ServerProcess::start(&args, &[("RUST_LOG", "info"), ("ISOVOX_LOG", "info")])
}

fn client() -> Client {
    isovox_server::client_tls::install_provider();
    Client::builder()
        .timeout(Duration::from_secs(30))
        .build()
        .unwrap()
}

/// Status and problem detail (or body) of a request with `token`.
fn send(request: reqwest::blocking::RequestBuilder, token: Option<&str>) -> (StatusCode, String) {
    let request = match token {
        Some(t) => request.header(AUTHORIZATION, format!("Bearer {t}")),
        None => request,
    };
    let response = request.send().unwrap();
    let status = response.status();
    let body = response.text().unwrap();
    let detail = serde_json::from_str::<Value>(&body)
        .ok()
        .and_then(|v| v.get("detail").and_then(Value::as_str).map(str::to_string))
        .unwrap_or(body);
    (status, detail)
}

fn edit(c: &Client, s: &ServerProcess, volume: &str, token: Option<&str>) -> (StatusCode, String) {
    let body = json!({"op": "union", "term": {"cuboid": {"origin": [4, 4, 4], "size": [8, 8, 8]}}});
    send(
        c.post(s.url(&format!("/v1/volumes/{volume}/edits")))
            .header(CONTENT_TYPE, "application/json")
            .body(body.to_string()),
        token,
    )
}

fn read(c: &Client, s: &ServerProcess, volume: &str, token: Option<&str>) -> (StatusCode, String) {
    send(c.get(s.url(&format!("/v1/volumes/{volume}"))), token)
}

/// A 401 whose detail contains `words` and never the token.
#[track_caller]
fn refused(answer: (StatusCode, String), token: &str, words: &str) {
    let (status, detail) = answer;
    assert_eq!(status, StatusCode::UNAUTHORIZED, "{detail}");
    assert!(detail.contains(words), "{words:?} not in {detail:?}");
    assert!(!detail.contains(token), "the token is echoed: {detail}");
}

#[test]
fn oidc_tokens_from_a_discovered_issuer_edit_and_read_as_their_roles_allow() {
    let keys_dir = tempfile::tempdir().unwrap();
    let rsa = Key::new(keys_dir.path(), "rsa1", Algorithm::RS256);
    let ec = Key::new(keys_dir.path(), "ec1", Algorithm::ES256);
    let issuer = Issuer::start(&[&rsa, &ec]);
    let iss = issuer.url.clone();
    let dir = data_dir();
    let s = serve(
        dir.path(),
        &[
            "--oidc-issuer",
            &iss,
            "--oidc-audience",
            AUDIENCE,
            "--private-reads",
        ],
    );
    assert!(s.log().contains("(2 keys"), "{}", s.log());
    assert_eq!(issuer.fetches(), 1, "the key set is fetched once at start");
    let c = client();

    // Valid RS256 and ES256 tokens with write:* edit.
    for key in [&rsa, &ec] {
        let token = key.sign(&claims(&iss, "alice", &["write:*"]));
        let (status, detail) = edit(&c, &s, "w", Some(&token));
        assert_eq!(status, StatusCode::OK, "{:?}: {detail}", key.alg);
    }
    assert!(
        s.log().contains("user=alice"),
        "edits are logged by user:\n{}",
        s.log()
    );

    // read:w reads (reads are private here) but cannot edit.
    let reader = ec.sign(&claims(&iss, "rita", &["read:w"]));
    assert_eq!(read(&c, &s, "w", Some(&reader)).0, StatusCode::OK);
    let (status, detail) = edit(&c, &s, "w", Some(&reader));
    assert_eq!(status, StatusCode::FORBIDDEN, "{detail}");
    assert!(detail.contains("rita"), "{detail}");
    refused(read(&c, &s, "w", None), "-", "bearer token");

    // write:other cannot edit w (nor read it).
    let other = rsa.sign(&claims(&iss, "oscar", &["write:other", "admin"]));
    let (status, detail) = edit(&c, &s, "w", Some(&other));
    assert_eq!(status, StatusCode::FORBIDDEN, "{detail}");
    assert!(detail.contains("\"w\""), "{detail}");
    assert_eq!(read(&c, &s, "w", Some(&other)).0, StatusCode::FORBIDDEN);

    // Expired, another audience, another issuer: 401s saying which.
    let mut expired = claims(&iss, "alice", &["write:*"]);
    expired["exp"] = json!(now() - 3600);
    let token = rsa.sign(&expired);
    refused(edit(&c, &s, "w", Some(&token)), &token, "expired at");
    let mut audience = claims(&iss, "alice", &["write:*"]);
    audience["aud"] = json!("someone-else");
    let token = ec.sign(&audience);
    refused(
        edit(&c, &s, "w", Some(&token)),
        &token,
        "audience is \"someone-else\"",
    );
    let token = rsa.sign(&claims("https://elsewhere.example", "alice", &["write:*"]));
    refused(
        edit(&c, &s, "w", Some(&token)),
        &token,
        "issuer is \"https://elsewhere.example\"",
    );
    // Not yet valid.
    let mut early = claims(&iss, "alice", &["write:*"]);
    early["nbf"] = json!(now() + 3600);
    let token = rsa.sign(&early);
    refused(edit(&c, &s, "w", Some(&token)), &token, "not valid before");

    // Signed by another key that claims the kid of the issuer's: the signature fails.
    let forger = Key::new(keys_dir.path(), "rsa1", Algorithm::RS256);
    let token = forger.sign(&claims(&iss, "mallory", &["write:*"]));
    refused(
        edit(&c, &s, "w", Some(&token)),
        &token,
        "signature does not verify",
    );
    // A token-file-shaped bearer is still just an unknown token.
    refused(
        edit(&c, &s, "w", Some("0123456789abcdef0123")),
        "0123456789abcdef0123",
        "unknown token",
    );
    assert_eq!(issuer.fetches(), 1, "known kids need no fetch");

    // Rotation: the issuer adds a key; the first token naming it refreshes the set once.
    let rotated = Key::new(keys_dir.path(), "rsa2", Algorithm::RS256);
    issuer.publish(&[&rotated, &ec]);
    let token = rotated.sign(&claims(&iss, "alice", &["write:w"]));
    let (status, detail) = edit(&c, &s, "w", Some(&token));
    assert_eq!(status, StatusCode::OK, "{detail}");
    assert_eq!(issuer.fetches(), 2, "one refresh for the new kid");
    assert_eq!(edit(&c, &s, "w", Some(&token)).0, StatusCode::OK);

    // A flood of made-up kids within the refresh interval fetches nothing more.
    for i in 0..20 {
        let fake = Key {
            kid: format!("made-up-{i}"),
            alg: Algorithm::RS256,
            private: rotated.private.clone(),
            jwk: Value::Null,
        };
        let token = fake.sign(&claims(&iss, "mallory", &["write:*"]));
        refused(
            edit(&c, &s, "w", Some(&token)),
            &token,
            "is not among the issuer's keys",
        );
    }
    assert_eq!(
        issuer.fetches(),
        2,
        "made-up kids must not hammer the issuer"
    );
    let log = s.log();
    assert!(log.contains("refreshed the issuer's keys"), "{log}");
    assert!(!log.contains(&token), "a token is in the log");
}

#[test]
fn oidc_keys_from_a_file_need_no_network_and_jwt_users_are_rate_limited() {
    let keys_dir = tempfile::tempdir().unwrap();
    let rsa = Key::new(keys_dir.path(), "rsa1", Algorithm::RS256);
    let ec = Key::new(keys_dir.path(), "ec1", Algorithm::ES256);
    let jwks = keys_dir.path().join("jwks.json");
    std::fs::write(&jwks, json!({"keys": [rsa.jwk, ec.jwk]}).to_string()).unwrap();
    // Nothing listens there: any fetch would fail.
    let iss = "https://issuer.invalid/realms/site";
    let dir = data_dir();
    let s = serve(
        dir.path(),
        &[
            "--oidc-issuer",
            iss,
            "--oidc-audience",
            AUDIENCE,
            "--oidc-jwks",
            jwks.to_str().unwrap(),
            "--oidc-roles-claim",
            "realm_access.roles",
            "--edit-rate",
            "1",
        ],
    );
    let c = client();
    let mut mine = claims(iss, "alice", &[]);
    mine["realm_access"] = json!({"roles": ["write:w", "offline_access"]});
    let token = rsa.sign(&mine);
    let (status, detail) = edit(&c, &s, "w", Some(&token));
    assert_eq!(status, StatusCode::OK, "{detail}");
    // The same user with another token (and algorithm) shares the bucket: 429.
    let again = ec.sign(&mine);
    let (status, detail) = edit(&c, &s, "w", Some(&again));
    assert_eq!(status, StatusCode::TOO_MANY_REQUESTS, "{detail}");
    // Another user has a bucket of their own.
    let mut bob = claims(iss, "bob", &[]);
    bob["realm_access"] = json!({"roles": ["write:*"]});
    assert_eq!(edit(&c, &s, "w", Some(&ec.sign(&bob))).0, StatusCode::OK);
    // An unknown kid is refused at once: a file is never refetched.
    let stranger = Key::new(keys_dir.path(), "rsa9", Algorithm::RS256);
    let token = stranger.sign(&mine);
    refused(
        edit(&c, &s, "w", Some(&token)),
        &token,
        "\"rsa9\" is not among the issuer's keys",
    );
    // Reads are public here: no token needed.
    assert_eq!(read(&c, &s, "w", None).0, StatusCode::OK);
}

/// `GET /v1/auth` tells a page how to sign in, with `--private-reads` too (before it has a
/// token), and who a token is once it has one.
#[test]
fn the_page_learns_how_to_sign_in_and_who_it_is() {
    let keys_dir = tempfile::tempdir().unwrap();
    let rsa = Key::new(keys_dir.path(), "rsa1", Algorithm::RS256);
    let jwks = keys_dir.path().join("jwks.json");
    std::fs::write(&jwks, json!({"keys": [rsa.jwk]}).to_string()).unwrap();
    let iss = "https://issuer.invalid/realms/site";
    let dir = data_dir();
    let s = serve(
        dir.path(),
        &[
            "--oidc-issuer",
            iss,
            "--oidc-audience",
            AUDIENCE,
            "--oidc-client-id",
            "isovox-web",
            "--oidc-jwks",
            jwks.to_str().unwrap(),
            "--private-reads",
        ],
    );
    let c = client();
    let auth = |token: Option<&str>| {
        let (status, body) = send(c.get(s.url("/v1/auth")), token);
        (
            status,
            serde_json::from_str::<Value>(&body).unwrap_or(Value::Null),
        )
    };
    let (status, anonymous) = auth(None);
    assert_eq!(status, StatusCode::OK, "{anonymous}");
    assert_eq!(
        anonymous,
        json!({"user": null, "write": false, "admin": false, "private_reads": true,
               "oidc": {"issuer": iss, "client_id": "isovox-web", "audience": AUDIENCE}})
    );
    // Only /v1/auth is open: the volumes stay private.
    assert_eq!(read(&c, &s, "w", None).0, StatusCode::UNAUTHORIZED);

    let reader = rsa.sign(&claims(iss, "rita", &["read:w"]));
    let (status, rita) = auth(Some(&reader));
    assert_eq!(status, StatusCode::OK, "{rita}");
    assert_eq!(
        (&rita["user"], &rita["write"]),
        (&json!("rita"), &json!(false))
    );
    let writer = rsa.sign(&claims(iss, "alice", &["write:*", "admin"]));
    let (_, alice) = auth(Some(&writer));
    assert_eq!(
        (&alice["user"], &alice["write"], &alice["admin"]),
        (&json!("alice"), &json!(true), &json!(true))
    );
    // A token the server refuses is a 401, as anywhere.
    assert_eq!(
        send(c.get(s.url("/v1/auth")), Some("not-a-token")).0,
        StatusCode::UNAUTHORIZED
    );
}
