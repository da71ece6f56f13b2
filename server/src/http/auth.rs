//! Who a request speaks for, what they may do, and per-user edit rates.
//!
//! Two sources name a [`Principal`] (a user and their [`Grant`]s): the token file below, and,
//! with `--oidc-issuer`, JWTs signed by an OpenID Connect issuer (`oidc.rs`). A bearer that
//! looks like a JWT (three base64url parts joined by dots) goes to the issuer's keys when OIDC
//! is configured; any other bearer is looked up in the token file. [`authorize`] is the one
//! check both go through, so handlers see the same identity whichever signed it.
//!
//! A token file has one token per line, `NAME TOKEN [SCOPE [VOLUMES]]`: NAME is the user the
//! token speaks for; SCOPE is `write` (the default) or `read`; VOLUMES is `*` (every volume, the
//! default) or a comma-separated list of the volumes the token may use. `#` starts a comment.
//! Secrets are compared in constant time and never printed: a [`Token`]'s `Debug` shows its
//! name, scope and volumes only, and logs name the token, not its secret.

use super::{ApiError, AppState, ServerConfig};
use axum::extract::{Request, State};
use axum::http::{header, HeaderMap};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use std::collections::HashMap;
use std::path::Path;
use std::sync::Mutex;
use std::time::Instant;

/// What a token may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Scope {
    /// May read (with `--private-reads`).
    Read,
    /// May read and write.
    Write,
}

/// Which volumes a token may use.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum VolumeAccess {
    /// Every volume (`*`).
    All,
    /// Only these, by name.
    Only(Vec<String>),
}

impl VolumeAccess {
    /// Reads a token file's VOLUMES field: `*`, or names separated by commas.
    ///
    /// # Errors
    /// An empty name (`a,,b`, a trailing comma) or `*` among names.
    pub fn parse(field: &str) -> Result<VolumeAccess, String> {
        if field == "*" {
            return Ok(VolumeAccess::All);
        }
        let names: Vec<String> = field.split(',').map(str::to_string).collect();
        if let Some(bad) = names.iter().find(|n| n.is_empty() || n.as_str() == "*") {
            return Err(format!(
                "volumes {field:?}: {} (expected * or NAME[,NAME...])",
                if bad.is_empty() {
                    "an empty name"
                } else {
                    "* among names"
                }
            ));
        }
        Ok(VolumeAccess::Only(names))
    }

    /// Whether the volume `name` is among them.
    pub fn allows(&self, name: &str) -> bool {
        match self {
            VolumeAccess::All => true,
            VolumeAccess::Only(names) => names.iter().any(|n| n == name),
        }
    }
}

/// One right: `scope` on `volumes`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Grant {
    /// What may be done.
    pub scope: Scope,
    /// To which volumes.
    pub volumes: VolumeAccess,
}

/// Who a request speaks for and what they may do, whichever source vouched for them (a token
/// of the token file, or a JWT).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Principal {
    /// The user: the token file's NAME, or the JWT's `preferred_username` (else `sub`). Logs,
    /// rate limits and the record of who did what use it.
    pub user: String,
    /// What they may do: a request is allowed when one grant covers it.
    pub grants: Vec<Grant>,
    /// The `admin` role: may undo and redo anyone's edit (a user undoes only their own).
    pub admin: bool,
}

impl Principal {
    /// Whether some grant gives at least `need` on `volume` (a route that names no volume:
    /// `None`, which asks for the scope on any volume).
    pub fn may(&self, need: Scope, volume: Option<&str>) -> bool {
        self.grants
            .iter()
            .any(|g| g.scope >= need && volume.is_none_or(|v| g.volumes.allows(v)))
    }

    /// [`Principal::may`] as an answer: a 403 that says what is missing.
    ///
    /// # Errors
    /// 403 when no grant covers `need` on `volume`.
    pub fn check(&self, need: Scope, volume: Option<&str>) -> Result<(), ApiError> {
        if self.may(need, volume) {
            return Ok(());
        }
        let user = &self.user;
        let what = match need {
            Scope::Read => "read",
            Scope::Write => "write",
        };
        // Say "read-only" when the user may read there: the one thing a read-only token lacks.
        if need == Scope::Write && self.may(Scope::Read, volume) {
            return Err(ApiError::Forbidden(match volume {
                Some(v) => format!("{user:?} may only read the volume {v:?}"),
                None => format!("{user:?} is read-only"),
            }));
        }
        Err(ApiError::Forbidden(match volume {
            Some(v) => format!("{user:?} may not {what} the volume {v:?}"),
            None => format!("{user:?} may not {what}"),
        }))
    }
}

/// The grants of a JWT's roles: `write:VOLUME` writes and reads VOLUME, `read:VOLUME` reads
/// it, `*` for VOLUME means every volume; `admin` (the second value) lets a writer undo anyone's
/// edits and grants nothing by itself. Other roles (a provider's own, such as `offline_access`) are ignored.
pub fn grants_from_roles<'a>(roles: impl IntoIterator<Item = &'a str>) -> (Vec<Grant>, bool) {
    let mut grants = Vec::new();
    let mut admin = false;
    for role in roles {
        if role == "admin" {
            admin = true;
            continue;
        }
        let Some((scope, volume)) = role.split_once(':') else {
            continue;
        };
        let scope = match scope {
            "write" => Scope::Write,
            "read" => Scope::Read,
            _ => continue,
        };
        let volumes = match volume {
            "" => continue,
            "*" => VolumeAccess::All,
            name => VolumeAccess::Only(vec![name.to_string()]),
        };
        grants.push(Grant { scope, volumes });
    }
    (grants, admin)
}

/// The user and grants of a verified JWT's claims: the user is `preferred_username`, else
/// `sub`; the roles are the claim `roles_claim` (a top-level claim by its exact name, which
/// may hold dots or slashes as Auth0's namespaced claims do, else a dotted path into nested
/// objects such as Keycloak's `realm_access.roles`), an array of strings or one string of
/// roles separated by spaces. No roles claim: a user with no grants.
///
/// # Errors
/// Neither `preferred_username` nor `sub` is a non-empty string.
pub fn principal_from_claims(
    claims: &serde_json::Value,
    roles_claim: &str,
) -> Result<Principal, String> {
    let user = ["preferred_username", "sub"]
        .iter()
        .find_map(|c| claims.get(c)?.as_str().filter(|s| !s.is_empty()))
        .ok_or("the token names no user (neither preferred_username nor sub)")?;
    let roles = claims.get(roles_claim).or_else(|| {
        roles_claim
            .split('.')
            .try_fold(claims, |value, key| value.get(key))
    });
    let roles: Vec<&str> = match roles {
        Some(serde_json::Value::Array(items)) => {
            items.iter().filter_map(serde_json::Value::as_str).collect()
        }
        Some(serde_json::Value::String(text)) => text.split_whitespace().collect(),
        _ => Vec::new(),
    };
    let (grants, admin) = grants_from_roles(roles);
    Ok(Principal {
        user: user.to_string(),
        grants,
        admin,
    })
}

/// One configured token.
#[derive(Clone)]
pub struct Token {
    /// The user it speaks for, for logs, rate limits and the record of who did what (never the
    /// secret).
    pub name: String,
    secret: String,
    /// What it may do.
    pub scope: Scope,
    /// Which volumes it may do it to.
    pub volumes: VolumeAccess,
    /// The `admin` scope: writes, and may undo anyone's edit.
    pub admin: bool,
}

impl Token {
    /// The user it speaks for and its one grant.
    pub fn principal(&self) -> Principal {
        Principal {
            user: self.name.clone(),
            grants: vec![Grant {
                scope: self.scope,
                volumes: self.volumes.clone(),
            }],
            admin: self.admin,
        }
    }
}

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Token")
            .field("name", &self.name)
            .field("scope", &self.scope)
            .field("volumes", &self.volumes)
            .finish_non_exhaustive()
    }
}

/// The server's tokens.
#[derive(Debug, Clone, Default)]
pub struct Tokens {
    tokens: Vec<Token>,
}

/// Shortest secret accepted: guessing one must be hopeless.
pub const MIN_SECRET_LEN: usize = 16;

impl Tokens {
    /// Parses a token file's text.
    ///
    /// # Errors
    /// A line that is not `NAME TOKEN [SCOPE [VOLUMES]]`, an unknown scope, a malformed volume
    /// list, a secret shorter than [`MIN_SECRET_LEN`], or a name or secret given twice (the
    /// message names the line, never the secret).
    pub fn parse(text: &str) -> Result<Tokens, String> {
        let mut tokens = Tokens::default();
        for (i, line) in text.lines().enumerate() {
            let line = line.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let fields: Vec<&str> = line.split_whitespace().collect();
            let (scope, admin) = match fields.get(2).copied() {
                None | Some("write") => (Scope::Write, false),
                Some("read") => (Scope::Read, false),
                Some("admin") => (Scope::Write, true),
                Some(other) => {
                    return Err(format!(
                        "line {}: scope {other:?} is not write, read or admin",
                        i + 1
                    ))
                }
            };
            if !(2..=4).contains(&fields.len()) {
                return Err(format!(
                    "line {}: expected NAME TOKEN [SCOPE [VOLUMES]]",
                    i + 1
                ));
            }
            let volumes = match fields.get(3) {
                None => VolumeAccess::All,
                Some(field) => {
                    VolumeAccess::parse(field).map_err(|e| format!("line {}: {e}", i + 1))?
                }
            };
            tokens
                .add_for(fields[0], fields[1], scope, volumes)
                .map_err(|e| format!("line {}: {e}", i + 1))?;
            if let Some(token) = tokens.tokens.last_mut() {
                token.admin = admin;
            }
        }
        Ok(tokens)
    }

    /// Reads a token file.
    ///
    /// # Errors
    /// The file cannot be read or does not parse.
    pub fn load(path: &Path) -> Result<Tokens, String> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("cannot read the token file {}: {e}", path.display()))?;
        Tokens::parse(&text).map_err(|e| format!("token file {}: {e}", path.display()))
    }

    /// Adds a token for every volume.
    ///
    /// # Errors
    /// A short secret, or a name or secret already present.
    pub fn add(&mut self, name: &str, secret: &str, scope: Scope) -> Result<(), String> {
        self.add_for(name, secret, scope, VolumeAccess::All)
    }

    /// Adds a token for `volumes`.
    ///
    /// # Errors
    /// A short secret, or a name or secret already present.
    pub fn add_for(
        &mut self,
        name: &str,
        secret: &str,
        scope: Scope,
        volumes: VolumeAccess,
    ) -> Result<(), String> {
        if secret.len() < MIN_SECRET_LEN {
            return Err(format!(
                "the token of {name:?} is shorter than {MIN_SECRET_LEN} characters"
            ));
        }
        if self.tokens.iter().any(|t| t.name == name) {
            return Err(format!("the name {name:?} is given twice"));
        }
        if self.find(secret).is_some() {
            return Err(format!("the token of {name:?} is given twice"));
        }
        self.tokens.push(Token {
            name: name.to_string(),
            secret: secret.to_string(),
            scope,
            volumes,
            admin: false,
        });
        Ok(())
    }

    /// How many tokens.
    pub fn len(&self) -> usize {
        self.tokens.len()
    }

    /// Whether there is none.
    pub fn is_empty(&self) -> bool {
        self.tokens.is_empty()
    }

    /// The token with this secret. Every configured secret is compared in full, so the time
    /// taken does not tell how much of a guess was right.
    fn find(&self, secret: &str) -> Option<&Token> {
        let mut found = None;
        for t in &self.tokens {
            if constant_time_eq(t.secret.as_bytes(), secret.as_bytes()) {
                found = Some(t);
            }
        }
        found
    }

    /// The user of the token file's token a request carries, if it has at least `need` on
    /// `volume` (a route that names no volume: `None`). JWTs are [`authorize`]'s.
    ///
    /// # Errors
    /// 401 without a bearer token or with an unknown one; 403 when its scope is short or it is
    /// limited to other volumes.
    pub fn authorize(
        &self,
        headers: &HeaderMap,
        need: Scope,
        volume: Option<&str>,
    ) -> Result<Principal, ApiError> {
        let principal = self.principal_of(bearer(headers)?)?;
        principal.check(need, volume)?;
        Ok(principal)
    }

    /// The user of the token whose secret is `secret`.
    ///
    /// # Errors
    /// 401 for a secret that is no configured token's.
    fn principal_of(&self, secret: &str) -> Result<Principal, ApiError> {
        self.find(secret)
            .map(Token::principal)
            .ok_or_else(|| ApiError::Unauthorized("unknown token".into()))
    }
}

/// The bearer token of the `Authorization` header.
///
/// # Errors
/// 401 without the header, or with another scheme.
fn bearer(headers: &HeaderMap) -> Result<&str, ApiError> {
    let Some(value) = headers.get(header::AUTHORIZATION) else {
        return Err(ApiError::Unauthorized(
            "this route needs a bearer token (Authorization: Bearer TOKEN)".into(),
        ));
    };
    value
        .to_str()
        .ok()
        .and_then(|v| {
            let (scheme, rest) = v.split_once(' ')?;
            scheme.eq_ignore_ascii_case("bearer").then(|| rest.trim())
        })
        .ok_or_else(|| {
            ApiError::Unauthorized("the Authorization header is not `Bearer TOKEN`".into())
        })
}

/// Whether `bearer` has a JWT's shape: three non-empty base64url parts joined by dots (a
/// token file's secrets are hex, or anything without two dots).
pub fn looks_like_jwt(bearer: &str) -> bool {
    let parts: Vec<&str> = bearer.split('.').collect();
    parts.len() == 3
        && parts.iter().all(|p| {
            !p.is_empty()
                && p.bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_')
        })
}

/// Who a request speaks for, if they may do `need` on `volume` (`None`: a route that names no
/// volume): a JWT's user when OIDC is configured and the bearer looks like one, else the token
/// file's.
///
/// # Errors
/// 401 without a bearer, for an unknown token, or a JWT that does not verify (the detail says
/// why: expired, another audience or issuer, a bad signature); 403 when the user may not.
pub async fn authorize(
    config: &ServerConfig,
    headers: &HeaderMap,
    need: Scope,
    volume: Option<&str>,
) -> Result<Principal, ApiError> {
    let bearer = bearer(headers)?;
    let principal = match &config.oidc {
        Some(oidc) if looks_like_jwt(bearer) => oidc.verify(bearer).await?,
        _ => config.tokens.principal_of(bearer)?,
    };
    principal.check(need, volume)?;
    Ok(principal)
}

/// Who a write request speaks for (a token of the token file, or a JWT), allowed to write to
/// the volume of its path: as the first extractor of a write route, it is checked before
/// anything else of the request is read (a caller without one learns nothing).
#[derive(Debug, Clone)]
pub struct WriteToken(pub Principal);

impl axum::extract::FromRequestParts<AppState> for WriteToken {
    type Rejection = ApiError;

    async fn from_request_parts(
        parts: &mut axum::http::request::Parts,
        state: &AppState,
    ) -> Result<Self, ApiError> {
        authorize_path(parts, state, Scope::Write)
            .await
            .map(WriteToken)
    }
}

/// [`authorize`] for `need` on the volume the request's path names.
async fn authorize_path(
    parts: &axum::http::request::Parts,
    state: &AppState,
    need: Scope,
) -> Result<Principal, ApiError> {
    let volume = volume_in_path(parts.uri.path());
    authorize(&state.config, &parts.headers, need, volume.as_deref()).await
}

/// Who a request speaks for, allowed to read the volume of its path: for routes that need a
/// user even when reads are open (presence names its sender). Checked before the body is read.
#[derive(Debug, Clone)]
pub struct ReadToken(pub Principal);

impl axum::extract::FromRequestParts<AppState> for ReadToken {
    type Rejection = ApiError;

    async fn from_request_parts(
        parts: &mut axum::http::request::Parts,
        state: &AppState,
    ) -> Result<Self, ApiError> {
        authorize_path(parts, state, Scope::Read)
            .await
            .map(ReadToken)
    }
}

/// With `--private-reads`: every `/v1` route needs a token (or JWT) that may read.
pub async fn require_token(
    State(state): State<AppState>,
    request: Request,
    next: Next,
) -> Response {
    // `/v1/auth` tells a page how to sign in: it cannot need a token itself.
    if request.uri().path().starts_with("/v1/") && request.uri().path() != "/v1/auth" {
        let volume = volume_in_path(request.uri().path());
        if let Err(e) = authorize(
            &state.config,
            request.headers(),
            Scope::Read,
            volume.as_deref(),
        )
        .await
        {
            return e.into_response();
        }
    }
    next.run(request).await
}

/// `GET /v1/auth`: who the bearer is (`user` null without one), what they may do, and how a
/// page signs in: `oidc` names the issuer and the viewer's client id when the server accepts
/// an issuer's JWTs (`--oidc-issuer`, `--oidc-client-id`), else null. Open to all, with
/// `--private-reads` too; a bearer the server refuses is a 401 as anywhere.
///
/// # Errors
/// 401 for a token or JWT that does not verify.
pub async fn whoami(
    State(state): State<AppState>,
    headers: HeaderMap,
) -> Result<axum::Json<serde_json::Value>, ApiError> {
    let principal = if headers.contains_key(header::AUTHORIZATION) {
        Some(authorize(&state.config, &headers, Scope::Read, None).await?)
    } else {
        None
    };
    let oidc = state.config.oidc.as_ref().map(|o| {
        serde_json::json!({"issuer": o.config().issuer, "client_id": o.config().client_id, "audience": o.config().audience})
    });
    Ok(axum::Json(serde_json::json!({
        "user": principal.as_ref().map(|p| p.user.clone()),
        "write": principal.as_ref().is_some_and(|p| p.may(Scope::Write, None)),
        "admin": principal.as_ref().is_some_and(|p| p.admin),
        "private_reads": state.config.private_reads,
        "oidc": oidc,
    })))
}

/// The volume a `/v1/volumes/{name}...` path names, percent-decoded as the router decodes it;
/// `None` for other paths (the list of volumes, uploads of meshes).
fn volume_in_path(path: &str) -> Option<std::borrow::Cow<'_, str>> {
    let rest = path.strip_prefix("/v1/volumes/")?;
    let segment = rest.split('/').next().filter(|s| !s.is_empty())?;
    Some(percent_encoding::percent_decode_str(segment).decode_utf8_lossy())
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    let mut diff = a.len() ^ b.len();
    for (i, &x) in a.iter().enumerate() {
        diff |= usize::from(x ^ b.get(i).copied().unwrap_or(!x));
    }
    diff == 0
}

/// A random secret: 32 hex digits from the operating system's generator.
///
/// # Errors
/// The generator cannot be read.
pub fn random_secret() -> std::io::Result<String> {
    use std::io::Read;
    let mut bytes = [0u8; 16];
    std::fs::File::open("/dev/urandom")?.read_exact(&mut bytes)?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// Edits per second per user: a token bucket per user name (a JWT's user and a token file's
/// NAME alike), `rate` tokens per second up to
/// a burst of `rate`.
#[derive(Debug)]
pub struct RateLimiter {
    rate: f64,
    buckets: Mutex<HashMap<String, (f64, Instant)>>,
}

impl RateLimiter {
    /// `rate` edits per second per token, bursts of `rate`.
    pub fn new(rate: f64) -> Self {
        RateLimiter {
            rate: rate.max(f64::MIN_POSITIVE),
            buckets: Mutex::default(),
        }
    }

    /// Takes one edit from `name`'s bucket.
    ///
    /// # Errors
    /// 429 with the seconds until the bucket holds an edit again.
    pub fn take(&self, name: &str) -> Result<(), ApiError> {
        let now = Instant::now();
        let mut buckets = self.buckets.lock().unwrap_or_else(|p| p.into_inner());
        let (level, at) = buckets.entry(name.to_string()).or_insert((self.rate, now));
        *level = (*level + now.duration_since(*at).as_secs_f64() * self.rate).min(self.rate);
        *at = now;
        if *level >= 1.0 {
            *level -= 1.0;
            return Ok(());
        }
        let wait = ((1.0 - *level) / self.rate).ceil().max(1.0);
        Err(ApiError::TooManyRequests(wait.min(u32::MAX as f64) as u32))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_names_scopes_and_comments() {
        let t = Tokens::parse(
            "# team\nalice 0123456789abcdef0123 write\n\nbob fedcba9876543210fedc # default scope\nviewer 00000000000000000000 read\n",
        )
        .unwrap();
        assert_eq!(t.len(), 3);
        let mut h = HeaderMap::new();
        h.insert(
            header::AUTHORIZATION,
            "Bearer 00000000000000000000".parse().unwrap(),
        );
        assert!(matches!(
            t.authorize(&h, Scope::Write, None),
            Err(ApiError::Forbidden(_))
        ));
        assert_eq!(t.authorize(&h, Scope::Read, None).unwrap().user, "viewer");
        h.insert(
            header::AUTHORIZATION,
            "bearer fedcba9876543210fedc".parse().unwrap(),
        );
        assert_eq!(t.authorize(&h, Scope::Write, None).unwrap().user, "bob");
        h.insert(
            header::AUTHORIZATION,
            "Bearer fedcba9876543210fed".parse().unwrap(),
        );
        assert!(matches!(
            t.authorize(&h, Scope::Read, None),
            Err(ApiError::Unauthorized(_))
        ));
    }

    #[test]
    fn rejects_bad_lines_without_echoing_secrets() {
        for bad in [
            "alice",
            "alice 0123456789abcdef0123 root",
            "alice short",
            "a 0123456789abcdef0123\na 1123456789abcdef0123",
            "a 0123456789abcdef0123\nb 0123456789abcdef0123",
            // VOLUMES is one field: a fifth is an error, as are empty names and a stray `*`.
            "a 0123456789abcdef0123 write w extra",
            "a 0123456789abcdef0123 write w,,x",
            "a 0123456789abcdef0123 write w,",
            "a 0123456789abcdef0123 write *,w",
        ] {
            let e = Tokens::parse(bad).unwrap_err();
            assert!(!e.contains("0123456789abcdef0123"), "{e}");
            assert!(e.starts_with("line "), "{e}");
        }
        let t = Tokens::parse("alice 0123456789abcdef0123").unwrap();
        assert!(!format!("{t:?}").contains("0123456789abcdef0123"));
    }

    #[test]
    fn the_admin_scope_writes_and_may_undo_anyones_edits() {
        let t = Tokens::parse(
            "alice 0123456789abcdef0123 admin
bob 1123456789abcdef0123
",
        )
        .unwrap();
        let alice = t.principal_of("0123456789abcdef0123").unwrap();
        assert!(alice.admin && alice.may(Scope::Write, Some("w")));
        let bob = t.principal_of("1123456789abcdef0123").unwrap();
        assert!(!bob.admin && bob.may(Scope::Write, Some("w")));
    }

    #[test]
    fn a_token_limited_to_volumes_may_use_those_only() {
        let t = Tokens::parse(
            "alice 0123456789abcdef0123 write demo,scan\nbob 1123456789abcdef0123 read *\ncarol 2123456789abcdef0123\n",
        )
        .unwrap();
        let bearer = |secret: &str| {
            let mut h = HeaderMap::new();
            h.insert(
                header::AUTHORIZATION,
                format!("Bearer {secret}").parse().unwrap(),
            );
            h
        };
        let alice = bearer("0123456789abcdef0123");
        for volume in ["demo", "scan"] {
            let token = t.authorize(&alice, Scope::Write, Some(volume)).unwrap();
            assert_eq!(token.user, "alice");
        }
        let refused = t.authorize(&alice, Scope::Read, Some("other"));
        assert!(
            matches!(&refused, Err(ApiError::Forbidden(m)) if m.contains("\"other\"")),
            "{refused:?}"
        );
        // A route that names no volume (the list, uploads) asks only for the scope.
        assert!(t.authorize(&alice, Scope::Write, None).is_ok());
        // `*` and an absent field both mean every volume.
        let bob = bearer("1123456789abcdef0123");
        assert!(t.authorize(&bob, Scope::Read, Some("other")).is_ok());
        let carol = bearer("2123456789abcdef0123");
        assert!(t.authorize(&carol, Scope::Write, Some("other")).is_ok());
        assert_eq!(
            VolumeAccess::parse("demo,scan"),
            Ok(VolumeAccess::Only(vec!["demo".into(), "scan".into()]))
        );
    }

    #[test]
    fn the_volume_of_a_path_is_decoded_as_the_router_decodes_it() {
        assert_eq!(
            volume_in_path("/v1/volumes/demo/edits").as_deref(),
            Some("demo")
        );
        assert_eq!(volume_in_path("/v1/volumes/demo").as_deref(), Some("demo"));
        assert_eq!(
            volume_in_path("/v1/volumes/d%65mo/bricks/0/0/0/0").as_deref(),
            Some("demo")
        );
        assert_eq!(volume_in_path("/v1/volumes"), None);
        assert_eq!(volume_in_path("/v1/volumes/"), None);
        assert_eq!(volume_in_path("/v1/meshes"), None);
    }

    #[test]
    fn roles_map_to_grants_per_volume() {
        let (grants, admin) = grants_from_roles([
            "write:demo",
            "read:*",
            "admin",
            "offline_access",
            "write:",
            "delete:demo",
            "read",
        ]);
        assert!(admin);
        assert_eq!(
            grants,
            vec![
                Grant {
                    scope: Scope::Write,
                    volumes: VolumeAccess::Only(vec!["demo".into()])
                },
                Grant {
                    scope: Scope::Read,
                    volumes: VolumeAccess::All
                },
            ]
        );
        let p = Principal {
            user: "u".into(),
            grants,
            admin,
        };
        // write:demo writes and reads demo; read:* reads everything, writes nothing else.
        assert!(p.may(Scope::Write, Some("demo")));
        assert!(p.may(Scope::Read, Some("demo")));
        assert!(p.may(Scope::Read, Some("other")));
        assert!(!p.may(Scope::Write, Some("other")));
        assert!(
            matches!(p.check(Scope::Write, Some("other")), Err(ApiError::Forbidden(m)) if m.contains("may only read the volume \"other\""))
        );
        // A route that names no volume asks for the scope on some volume.
        assert!(p.may(Scope::Write, None));
        // admin alone grants nothing (yet).
        let (grants, admin) = grants_from_roles(["admin"]);
        assert!(admin && grants.is_empty());
        let only_admin = Principal {
            user: "root".into(),
            grants,
            admin,
        };
        assert!(!only_admin.may(Scope::Read, None));
        assert!(matches!(
            only_admin.check(Scope::Write, Some("w")),
            Err(ApiError::Forbidden(m)) if m.contains("may not write the volume \"w\"")
        ));
        // write:other does not reach w.
        let (grants, _) = grants_from_roles(["write:other"]);
        let other = Principal {
            user: "o".into(),
            grants,
            admin: false,
        };
        assert!(!other.may(Scope::Read, Some("w")) && other.may(Scope::Write, Some("other")));
    }

    #[test]
    fn claims_name_the_user_and_their_roles() {
        use serde_json::json;
        let p = principal_from_claims(
            &json!({"sub": "1234", "preferred_username": "alice", "isovox_roles": ["read:demo", 7]}),
            "isovox_roles",
        )
        .unwrap();
        assert_eq!(p.user, "alice");
        assert!(p.may(Scope::Read, Some("demo")) && !p.may(Scope::Write, Some("demo")));
        // sub when there is no (or an empty) preferred_username.
        let p = principal_from_claims(
            &json!({"sub": "1234", "preferred_username": ""}),
            "isovox_roles",
        )
        .unwrap();
        assert_eq!(p.user, "1234");
        assert!(p.grants.is_empty() && !p.admin);
        assert!(
            principal_from_claims(&json!({"isovox_roles": ["admin"]}), "isovox_roles").is_err()
        );
        // A dotted path into nested claims (Keycloak's realm roles).
        let p = principal_from_claims(
            &json!({"sub": "k", "realm_access": {"roles": ["write:*", "uma_authorization"]}}),
            "realm_access.roles",
        )
        .unwrap();
        assert!(p.may(Scope::Write, Some("anything")));
        // A namespaced claim whose name holds dots is taken whole (Auth0's custom claims).
        let p = principal_from_claims(
            &json!({"sub": "a", "https://isovox.example/roles": ["admin", "write:w"]}),
            "https://isovox.example/roles",
        )
        .unwrap();
        assert!(p.admin && p.may(Scope::Write, Some("w")));
        // One string of roles separated by spaces, as some providers send scopes.
        let p =
            principal_from_claims(&json!({"sub": "s", "roles": "read:a read:b"}), "roles").unwrap();
        assert!(p.may(Scope::Read, Some("b")) && !p.may(Scope::Read, Some("c")));
    }

    #[test]
    fn jwts_are_told_from_token_file_secrets_by_their_shape() {
        assert!(looks_like_jwt(
            "eyJhbGciOiJSUzI1NiJ9.eyJzdWIiOiJhIn0.c2ln-_x"
        ));
        for not in [
            "0123456789abcdef0123",
            "a.b",
            "a..c",
            "a.b.c.d",
            "a.b.c=",
            ".b.c",
        ] {
            assert!(!looks_like_jwt(not), "{not}");
        }
    }

    #[test]
    fn a_token_of_the_file_is_a_principal_with_one_grant() {
        let t = Tokens::parse("alice 0123456789abcdef0123 read demo").unwrap();
        let p = t.principal_of("0123456789abcdef0123").unwrap();
        assert_eq!(p.user, "alice");
        assert!(p.may(Scope::Read, Some("demo")) && !p.may(Scope::Write, Some("demo")));
        assert!(!p.admin);
    }

    #[test]
    fn constant_time_eq_is_eq() {
        for (a, b) in [("", ""), ("a", "a"), ("a", "b"), ("ab", "a"), ("a", "ab")] {
            assert_eq!(constant_time_eq(a.as_bytes(), b.as_bytes()), a == b);
        }
    }

    #[test]
    fn rate_limiter_allows_a_burst_then_refuses() {
        let r = RateLimiter::new(3.0);
        for _ in 0..3 {
            r.take("a").unwrap();
        }
        assert!(matches!(r.take("a"), Err(ApiError::TooManyRequests(1))));
        // Buckets are per token.
        r.take("b").unwrap();
    }
}
