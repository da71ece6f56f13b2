//! JWTs of an OpenID Connect issuer (`serve --oidc-issuer URL --oidc-audience AUD`), beside the
//! token file: who signed in, and with which roles (`docs/editing.md`, "Access control").
//!
//! Keys: the issuer's JWKS, found through `{issuer}/.well-known/openid-configuration`'s
//! `jwks_uri` (or a JWKS URL given directly, or a JWKS file for sites without network). The
//! key set is kept in memory; a token naming a key id (`kid`) the set lacks refreshes it, at most
//! once per [`OidcConfig::refresh_interval`] however many made-up kids arrive, and concurrent
//! requests wait for the one refresh in flight rather than start their own. A file is read once,
//! at start. Fetches run on a blocking thread with reqwest's blocking client (bounded time and
//! size), never on a connection's event loop.
//!
//! Validation (jsonwebtoken, RustCrypto backend): RS256 or ES256 signature by a key of the set
//! whose type and `alg` match the token's header; `iss` equal to the issuer; `aud` naming the
//! audience; `exp`, and `nbf` when present, with [`LEEWAY_SECS`] of clock skew. A token that
//! fails is a 401 whose detail says which check failed; the token itself is never echoed or
//! logged. The user and roles are read from the verified claims ([`principal_from_claims`]).

use super::auth::{principal_from_claims, Principal};
use super::ApiError;
use jsonwebtoken::errors::ErrorKind;
use jsonwebtoken::jwk::{AlgorithmParameters, EllipticCurve, Jwk, KeyAlgorithm, PublicKeyUse};
use jsonwebtoken::{Algorithm, DecodingKey, Validation};
use serde_json::Value;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

/// Clock skew allowed on `exp` and `nbf`, in seconds.
pub const LEEWAY_SECS: u64 = 30;

/// The claim roles are read from unless `--oidc-roles-claim` says otherwise.
pub const DEFAULT_ROLES_CLAIM: &str = "isovox_roles";

/// Least time between two refreshes of the key set for unknown kids, unless configured.
pub const DEFAULT_REFRESH_INTERVAL: Duration = Duration::from_secs(60);

/// Largest discovery document or key set read.
const MAX_DOCUMENT_BYTES: u64 = 1 << 20;

/// How long one fetch (discovery or key set) may take.
const FETCH_TIMEOUT: Duration = Duration::from_secs(10);

/// Where the issuer's keys come from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum KeySource {
    /// The `jwks_uri` of `{issuer}/.well-known/openid-configuration`.
    Discover,
    /// This JWKS URL, without discovery.
    Url(String),
    /// A JWKS file, read once at start: no network at all.
    File(PathBuf),
}

/// How JWTs are checked.
#[derive(Debug, Clone)]
pub struct OidcConfig {
    /// The issuer, exactly as its tokens' `iss` (and its discovery document's `issuer`) spell it.
    pub issuer: String,
    /// What this server is called in the tokens' `aud` (the client id registered with the
    /// issuer).
    pub audience: String,
    /// The client id the web viewer signs in with at the issuer (authorization code with PKCE;
    /// `GET /v1/auth` tells the page): `--oidc-client-id`, else the audience.
    pub client_id: String,
    /// The claim holding the roles: a top-level claim by its exact name, else a dotted path
    /// (`realm_access.roles`).
    pub roles_claim: String,
    /// Where the keys come from.
    pub keys: KeySource,
    /// Least time between two refreshes of the key set for tokens naming unknown kids.
    pub refresh_interval: Duration,
}

impl OidcConfig {
    /// A configuration with the default roles claim, discovery, and refresh interval.
    pub fn new(issuer: &str, audience: &str) -> OidcConfig {
        OidcConfig {
            issuer: issuer.to_string(),
            audience: audience.to_string(),
            client_id: audience.to_string(),
            roles_claim: DEFAULT_ROLES_CLAIM.to_string(),
            keys: KeySource::Discover,
            refresh_interval: DEFAULT_REFRESH_INTERVAL,
        }
    }
}

/// One usable key of the set.
#[derive(Clone)]
struct Key {
    kid: Option<String>,
    alg: Algorithm,
    key: DecodingKey,
}

/// The keys of a JWKS that can verify RS256 or ES256 signatures.
#[derive(Clone, Default)]
struct KeySet {
    keys: Vec<Key>,
}

impl KeySet {
    /// Reads a JWKS document (`{"keys": [...]}`). Keys for encryption, of other types or
    /// algorithms (HMAC, EdDSA, P-384) or that do not decode are left out, as is a provider's
    /// key of a kind jsonwebtoken does not know: one odd key must not lose the others.
    ///
    /// # Errors
    /// Not JSON, no `keys` array, or no usable key in it.
    fn parse(text: &str) -> Result<KeySet, String> {
        let doc: Value =
            serde_json::from_str(text).map_err(|e| format!("the key set is not JSON: {e}"))?;
        let entries = doc
            .get("keys")
            .and_then(Value::as_array)
            .ok_or("the key set has no \"keys\" array")?;
        let keys: Vec<Key> = entries.iter().filter_map(usable_key).collect();
        if keys.is_empty() {
            return Err(format!(
                "none of the key set's {} keys is an RS256 or ES256 signing key",
                entries.len()
            ));
        }
        Ok(KeySet { keys })
    }

    /// The key that verifies a token of `alg` naming `kid`.
    ///
    /// `Ok(None)`: no key has that kid (a refresh may bring it). A token without a kid takes the
    /// one key of its algorithm when the set has exactly one.
    ///
    /// # Errors
    /// The kid's key is for another algorithm, or the token names no kid and the set has
    /// several keys for its algorithm.
    fn find(&self, kid: Option<&str>, alg: Algorithm) -> Result<Option<DecodingKey>, String> {
        let Some(kid) = kid else {
            let mut of_alg = self.keys.iter().filter(|k| k.alg == alg);
            return match (of_alg.next(), of_alg.next()) {
                (Some(k), None) => Ok(Some(k.key.clone())),
                (None, _) => Ok(None),
                (Some(_), Some(_)) => Err(format!(
                    "the token names no key (kid) and the issuer has several {alg:?} keys"
                )),
            };
        };
        let mut named = self
            .keys
            .iter()
            .filter(|k| k.kid.as_deref() == Some(kid))
            .peekable();
        if named.peek().is_none() {
            return Ok(None);
        }
        match named.find(|k| k.alg == alg) {
            Some(k) => Ok(Some(k.key.clone())),
            None => Err(format!(
                "the token is signed with {alg:?} but the issuer's key {kid:?} is not an {alg:?} key"
            )),
        }
    }
}

/// A JWK that can verify RS256 or ES256 signatures, else `None`.
fn usable_key(entry: &Value) -> Option<Key> {
    let jwk: Jwk = serde_json::from_value(entry.clone()).ok()?;
    if matches!(&jwk.common.public_key_use, Some(u) if *u != PublicKeyUse::Signature) {
        return None;
    }
    let alg = match &jwk.algorithm {
        AlgorithmParameters::RSA(_) => Algorithm::RS256,
        AlgorithmParameters::EllipticCurve(p) if p.curve == EllipticCurve::P256 => Algorithm::ES256,
        _ => return None,
    };
    let stated = match alg {
        Algorithm::RS256 => KeyAlgorithm::RS256,
        _ => KeyAlgorithm::ES256,
    };
    if jwk.common.key_algorithm.is_some_and(|a| a != stated) {
        return None;
    }
    Some(Key {
        kid: jwk.common.key_id.clone(),
        alg,
        key: DecodingKey::from_jwk(&jwk).ok()?,
    })
}

/// The issuer's keys and how tokens are checked against them.
pub struct Oidc {
    config: OidcConfig,
    /// Shared with the refresh's blocking thread, which stores what it fetched even if the
    /// request that started it is gone by then.
    keys: Arc<RwLock<Arc<KeySet>>>,
    /// When the set was last refreshed for an unknown kid; the lock also makes concurrent
    /// refreshes one.
    refreshed: tokio::sync::Mutex<Option<Instant>>,
    /// Fetches of the key set made (the initial one included).
    fetches: AtomicU64,
}

impl std::fmt::Debug for Oidc {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Oidc")
            .field("config", &self.config)
            .field("keys", &self.key_count())
            .finish_non_exhaustive()
    }
}

impl Oidc {
    /// Checks tokens as `config` says. A key file is read now; keys from the network are
    /// fetched by [`Oidc::load_blocking`] at start, or by the first token that needs them.
    ///
    /// # Errors
    /// The key file cannot be read or holds no usable key.
    pub fn new(config: OidcConfig) -> Result<Oidc, String> {
        let keys = match &config.keys {
            KeySource::File(path) => read_key_file(path)?,
            KeySource::Discover | KeySource::Url(_) => KeySet::default(),
        };
        Ok(Oidc {
            config,
            keys: Arc::new(RwLock::new(Arc::new(keys))),
            refreshed: tokio::sync::Mutex::new(None),
            fetches: AtomicU64::new(0),
        })
    }

    /// How tokens are checked.
    pub fn config(&self) -> &OidcConfig {
        &self.config
    }

    /// Fetches the key set now, blocking (at start, outside the async runtime); returns how
    /// many usable keys it holds. Does not count as a refresh: the first unknown kid may still
    /// refresh at once.
    ///
    /// # Errors
    /// The issuer or its key set cannot be fetched or read.
    pub fn load_blocking(&self) -> Result<usize, String> {
        let set = self.fetch()?;
        let n = set.keys.len();
        self.store(set);
        Ok(n)
    }

    /// How many usable keys are held.
    pub fn key_count(&self) -> usize {
        self.current().keys.len()
    }

    /// How many times the key set was fetched from the network.
    pub fn fetches(&self) -> u64 {
        self.fetches.load(Ordering::Relaxed)
    }

    fn current(&self) -> Arc<KeySet> {
        self.keys.read().unwrap_or_else(|p| p.into_inner()).clone()
    }

    fn store(&self, set: KeySet) {
        store(&self.keys, set);
    }

    /// The user a JWT names, with the grants of its roles, once it verifies.
    ///
    /// # Errors
    /// 401 saying which check failed (never echoing the token).
    pub async fn verify(&self, token: &str) -> Result<Principal, ApiError> {
        let header = jsonwebtoken::decode_header(token).map_err(|_| {
            unauthorized("the token's header does not decode, or names an algorithm other than RS256 and ES256")
        })?;
        let alg = header.alg;
        if !matches!(alg, Algorithm::RS256 | Algorithm::ES256) {
            return Err(unauthorized(&format!(
                "the token is signed with {alg:?}; this server takes RS256 and ES256"
            )));
        }
        let kid = header.kid.as_deref();
        let key = self.key_for(kid, alg).await?;
        let mut validation = Validation::new(alg);
        validation.leeway = LEEWAY_SECS;
        validation.validate_nbf = true;
        validation.set_issuer(&[&self.config.issuer]);
        validation.set_audience(&[&self.config.audience]);
        validation.set_required_spec_claims(&["exp", "iss", "aud"]);
        match jsonwebtoken::decode::<Value>(token, &key, &validation) {
            Ok(data) => principal_from_claims(&data.claims, &self.config.roles_claim)
                .map_err(|e| unauthorized(&e)),
            Err(e) => Err(unauthorized(&self.explain(e.kind(), token, kid))),
        }
    }

    /// Why a token whose signature was checked (or not) failed, in words.
    fn explain(&self, kind: &ErrorKind, token: &str, kid: Option<&str>) -> String {
        // Only claims errors read the claims, and jsonwebtoken checks the signature before the
        // claims: what is quoted here was signed by the issuer.
        let claim = |name: &str| {
            jsonwebtoken::dangerous::insecure_decode_claims::<Value>(token)
                .ok()
                .and_then(|c| c.get(name).cloned())
        };
        match kind {
            ErrorKind::ExpiredSignature => {
                let exp = claim("exp").and_then(|v| v.as_u64()).unwrap_or(0);
                let ago = jsonwebtoken::get_current_timestamp().saturating_sub(exp);
                format!(
                    "the token expired at {} ({ago} s ago; {LEEWAY_SECS} s of clock skew are allowed)",
                    rfc3339(exp)
                )
            }
            ErrorKind::ImmatureSignature => {
                let nbf = claim("nbf").and_then(|v| v.as_u64()).unwrap_or(0);
                format!("the token is not valid before {}", rfc3339(nbf))
            }
            ErrorKind::InvalidAudience => format!(
                "the token's audience is {}, this server is {:?}",
                quoted(claim("aud")),
                self.config.audience
            ),
            ErrorKind::InvalidIssuer => format!(
                "the token's issuer is {}, this server trusts {:?}",
                quoted(claim("iss")),
                self.config.issuer
            ),
            ErrorKind::MissingRequiredClaim(c) => format!("the token has no {c:?} claim"),
            ErrorKind::InvalidClaimFormat(c) => format!("the token's {c:?} claim is malformed"),
            ErrorKind::InvalidSignature => match kid {
                Some(kid) => {
                    format!("the token's signature does not verify with the issuer's key {kid:?}")
                }
                None => "the token's signature does not verify with the issuer's key".into(),
            },
            ErrorKind::InvalidAlgorithm
            | ErrorKind::InvalidEcdsaKey
            | ErrorKind::InvalidRsaKey(_) => {
                "the token's algorithm does not match the issuer's key".into()
            }
            _ => "the token is not a well-formed JWT".into(),
        }
    }

    /// The key for a token of `alg` naming `kid`, refreshing the key set once if it lacks the
    /// kid and the last refresh is older than the refresh interval.
    async fn key_for(&self, kid: Option<&str>, alg: Algorithm) -> Result<DecodingKey, ApiError> {
        let unknown = || match kid {
            Some(kid) => format!("the token's key {kid:?} is not among the issuer's keys"),
            None => format!("the issuer has no {alg:?} key"),
        };
        if let Some(key) = self
            .current()
            .find(kid, alg)
            .map_err(|e| unauthorized(&e))?
        {
            return Ok(key);
        }
        if matches!(self.config.keys, KeySource::File(_)) {
            return Err(unauthorized(&unknown()));
        }
        let mut refreshed = self.refreshed.lock().await;
        // Another request may have refreshed while this one waited.
        if let Some(key) = self
            .current()
            .find(kid, alg)
            .map_err(|e| unauthorized(&e))?
        {
            return Ok(key);
        }
        if let Some(at) = *refreshed {
            if at.elapsed() < self.config.refresh_interval {
                return Err(unauthorized(&format!(
                    "{} (they were fetched {} s ago)",
                    unknown(),
                    at.elapsed().as_secs()
                )));
            }
        }
        *refreshed = Some(Instant::now());
        let (config, keys) = (self.config.clone(), self.keys.clone());
        self.fetches.fetch_add(1, Ordering::Relaxed);
        let fetched = tokio::task::spawn_blocking(move || {
            let set = fetch_keys(&config)?;
            let n = set.keys.len();
            store(&keys, set);
            Ok::<usize, String>(n)
        })
        .await
        .map_err(|e| ApiError::Internal(format!("the key set fetch failed: {e}")))?;
        match fetched {
            Ok(n) => tracing::info!(
                issuer = %self.config.issuer,
                keys = n,
                "refreshed the issuer's keys for a token naming an unknown key"
            ),
            Err(e) => {
                tracing::warn!(issuer = %self.config.issuer, "cannot refresh the issuer's keys: {e}");
                return Err(unauthorized(&format!(
                    "{}, and the issuer's keys could not be fetched again; retry later",
                    unknown()
                )));
            }
        }
        drop(refreshed);
        self.current()
            .find(kid, alg)
            .map_err(|e| unauthorized(&e))?
            .ok_or_else(|| unauthorized(&unknown()))
    }

    /// The key set from the issuer, counted.
    fn fetch(&self) -> Result<KeySet, String> {
        self.fetches.fetch_add(1, Ordering::Relaxed);
        fetch_keys(&self.config)
    }
}

fn store(keys: &RwLock<Arc<KeySet>>, set: KeySet) {
    *keys.write().unwrap_or_else(|p| p.into_inner()) = Arc::new(set);
}

fn unauthorized(detail: &str) -> ApiError {
    ApiError::Unauthorized(detail.to_string())
}

/// A claim's value for a message, as JSON, cut short if long (it came from the caller).
fn quoted(value: Option<Value>) -> String {
    let Some(value) = value else {
        return "missing".into();
    };
    let text = value.to_string();
    match text.char_indices().nth(200) {
        Some((at, _)) => format!("{}...", &text[..at]),
        None => text,
    }
}

/// Seconds since 1970 as `YYYY-MM-DDTHH:MM:SSZ`.
fn rfc3339(secs: u64) -> String {
    let days = (secs / 86_400) as i64;
    let rem = secs % 86_400;
    // Howard Hinnant's civil_from_days.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}Z",
        rem / 3600,
        rem / 60 % 60,
        rem % 60
    )
}

/// Reads a JWKS file.
fn read_key_file(path: &std::path::Path) -> Result<KeySet, String> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("cannot read the key set {}: {e}", path.display()))?;
    KeySet::parse(&text).map_err(|e| format!("{}: {e}", path.display()))
}

/// The issuer's discovery document URL.
pub fn discovery_url(issuer: &str) -> String {
    format!(
        "{}/.well-known/openid-configuration",
        issuer.trim_end_matches('/')
    )
}

/// The key set as `config` says where it is (blocking).
fn fetch_keys(config: &OidcConfig) -> Result<KeySet, String> {
    let url = match &config.keys {
        KeySource::File(path) => return read_key_file(path),
        KeySource::Url(url) => url.clone(),
        KeySource::Discover => {
            let client = client()?;
            let found = discovery_url(&config.issuer);
            let doc: Value = serde_json::from_str(&get(&client, &found)?)
                .map_err(|e| format!("{found}: not JSON: {e}"))?;
            if doc.get("issuer").and_then(Value::as_str) != Some(config.issuer.as_str()) {
                tracing::warn!(
                    configured = %config.issuer,
                    discovered = ?doc.get("issuer"),
                    "the discovery document names another issuer; tokens must name the configured one"
                );
            }
            doc.get("jwks_uri")
                .and_then(Value::as_str)
                .ok_or_else(|| format!("{found} names no jwks_uri"))?
                .to_string()
        }
    };
    let text = get(&client()?, &url)?;
    KeySet::parse(&text).map_err(|e| format!("{url}: {e}"))
}

fn client() -> Result<reqwest::blocking::Client, String> {
    crate::client_tls::install_provider();
    reqwest::blocking::Client::builder()
        .timeout(FETCH_TIMEOUT)
        .build()
        .map_err(|e| format!("cannot build an HTTP client: {e}"))
}

/// The body of `GET url`, at most [`MAX_DOCUMENT_BYTES`].
fn get(client: &reqwest::blocking::Client, url: &str) -> Result<String, String> {
    use std::io::Read;
    let response = client
        .get(url)
        .header(reqwest::header::ACCEPT, "application/json")
        .send()
        .map_err(|e| format!("GET {url}: {}", crate::store::error_chain(&e)))?;
    if !response.status().is_success() {
        return Err(format!("GET {url}: {}", response.status()));
    }
    let mut body = String::new();
    response
        .take(MAX_DOCUMENT_BYTES + 1)
        .read_to_string(&mut body)
        .map_err(|e| format!("GET {url}: {e}"))?;
    if body.len() as u64 > MAX_DOCUMENT_BYTES {
        return Err(format!("GET {url}: larger than {MAX_DOCUMENT_BYTES} bytes"));
    }
    Ok(body)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_read_as_utc() {
        assert_eq!(rfc3339(0), "1970-01-01T00:00:00Z");
        assert_eq!(rfc3339(951_782_400), "2000-02-29T00:00:00Z");
        assert_eq!(rfc3339(1_798_761_599), "2026-12-31T23:59:59Z");
    }

    #[test]
    fn key_sets_keep_only_signing_keys_they_can_use() {
        let rsa = r#"{"kty":"RSA","kid":"r","n":"sXchDaQebHnPiGvyDOAT4saGEUetSyo9MKLOoWFsueri23bOdgWp4Dy1WlUzewbgBHod5pcM9H95GQRV3JDXboIRROSBigeC5yjU1hGzHHyXss8UDprecbAYxknTcQkhslANGRUZmdTOQ5qTRsLAt6BTYuyvVRdhS8exSZEy_c4gs_7svlJJQ4H9_NxsiIoLwAEk7-Q3UXERGYw_75IDrGA84-lA_-Ct4eTlXHBIY2EaV7t7LjJaynVJCpkv4LKjTTAumiGUIuQhrNhZLuF_RJLqHpM2kgWFLU7-VTdL1VbC2tejvcI2BlMkEpk1BzBZI0KQB0GaDWFLN-aEAw3vRw","e":"AQAB"}"#;
        let ec = r#"{"kty":"EC","crv":"P-256","kid":"e","use":"sig","x":"MKBCTNIcKUSDii11ySs3526iDZ8AiTo7Tu6KPAqv7D4","y":"4Etl6SRW2YiLUrN5vfvVHuhp7x8PxltmWWlbbM4IFyM"}"#;
        let enc = r#"{"kty":"EC","crv":"P-256","kid":"x","use":"enc","x":"MKBCTNIcKUSDii11ySs3526iDZ8AiTo7Tu6KPAqv7D4","y":"4Etl6SRW2YiLUrN5vfvVHuhp7x8PxltmWWlbbM4IFyM"}"#;
        let hmac = r#"{"kty":"oct","kid":"h","k":"c2VjcmV0"}"#;
        let odd = r#"{"kty":"weird","kid":"w"}"#;
        let set = KeySet::parse(&format!(r#"{{"keys":[{rsa},{ec},{enc},{hmac},{odd}]}}"#)).unwrap();
        assert_eq!(set.keys.len(), 2);
        assert!(set.find(Some("r"), Algorithm::RS256).unwrap().is_some());
        assert!(set.find(Some("e"), Algorithm::ES256).unwrap().is_some());
        // A kid of another type is refused, not tried; an unknown kid may be refreshed.
        assert!(set.find(Some("r"), Algorithm::ES256).is_err());
        assert!(set.find(Some("x"), Algorithm::ES256).unwrap().is_none());
        // Without a kid: the one key of the algorithm.
        assert!(set.find(None, Algorithm::RS256).unwrap().is_some());
        assert!(KeySet::parse(&format!(r#"{{"keys":[{hmac}]}}"#)).is_err());
        assert!(KeySet::parse("{}").is_err());
    }
}
