// Signing in at the server's OpenID Connect provider from the page: the authorization code
// flow with PKCE (RFC 7636), a public client, no secret and no server round trip. The server
// tells the issuer and the client id (`GET /v1/auth`'s `oidc`, from `isovox serve
// --oidc-issuer --oidc-audience [--oidc-client-id]`); the page sends the person to the issuer's
// authorization endpoint with a random verifier's S256 challenge, and when it comes back with a
// code, trades code and verifier for tokens at the token endpoint and keeps the JWT the server
// accepts (the one whose `aud` names the server's audience) as the session's token.

const PENDING_KEY = "isovox-oidc-pending";

export interface OidcSettings {
  issuer: string;
  client_id: string;
  audience: string;
}

interface Discovery {
  authorization_endpoint: string;
  token_endpoint: string;
}

function base64url(bytes: Uint8Array): string {
  let s = "";
  for (const b of bytes) s += String.fromCharCode(b);
  return btoa(s).replace(/\+/g, "-").replace(/\//g, "_").replace(/=+$/, "");
}

/** A random string of 43 base64url characters (32 bytes): a verifier or a state. */
export function randomString(): string {
  return base64url(crypto.getRandomValues(new Uint8Array(32)));
}

/** The S256 challenge of a verifier: base64url(SHA-256(verifier)). */
export async function challengeOf(verifier: string): Promise<string> {
  const digest = await crypto.subtle.digest("SHA-256", new TextEncoder().encode(verifier));
  return base64url(new Uint8Array(digest));
}

/** The page's address without the query parameters the provider adds (the redirect URI). */
export function redirectUri(location: { origin: string; pathname: string }): string {
  return location.origin + location.pathname;
}

/** The authorization request's URL. */
export function authorizationUrl(
  endpoint: string,
  clientId: string,
  redirect: string,
  state: string,
  challenge: string,
): string {
  const u = new URL(endpoint);
  u.searchParams.set("response_type", "code");
  u.searchParams.set("client_id", clientId);
  u.searchParams.set("redirect_uri", redirect);
  u.searchParams.set("scope", "openid profile");
  u.searchParams.set("state", state);
  u.searchParams.set("code_challenge", challenge);
  u.searchParams.set("code_challenge_method", "S256");
  return u.toString();
}

/** A JWT's claims, read without checking anything (the server checks). */
export function claimsOf(jwt: string): Record<string, unknown> | null {
  const part = jwt.split(".")[1];
  if (!part) return null;
  try {
    const b64 = part.replace(/-/g, "+").replace(/_/g, "/");
    const bytes = Uint8Array.from(atob(b64 + "=".repeat((4 - (b64.length % 4)) % 4)), (c) => c.charCodeAt(0));
    return JSON.parse(new TextDecoder().decode(bytes)) as Record<string, unknown>;
  } catch {
    return null;
  }
}

/** Of the tokens the provider gave, the one the server takes: `aud` naming `audience`. */
export function pickToken(
  tokens: { access_token?: string; id_token?: string },
  audience: string,
): string | null {
  for (const t of [tokens.access_token, tokens.id_token]) {
    if (!t) continue;
    const aud = claimsOf(t)?.["aud"];
    if (aud === audience || (Array.isArray(aud) && aud.includes(audience))) return t;
  }
  return null;
}

async function discover(issuer: string): Promise<Discovery> {
  const r = await fetch(`${issuer.replace(/\/$/, "")}/.well-known/openid-configuration`);
  if (!r.ok) throw new Error(`the provider's discovery document answered ${r.status}`);
  return (await r.json()) as Discovery;
}

/** Sends the person to the provider's login; the page comes back with a code. */
export async function beginSignIn(settings: OidcSettings): Promise<void> {
  const d = await discover(settings.issuer);
  const verifier = randomString();
  const state = randomString();
  sessionStorage.setItem(PENDING_KEY, JSON.stringify({ verifier, state, search: location.search }));
  const redirect = redirectUri(location);
  location.assign(authorizationUrl(d.authorization_endpoint, settings.client_id, redirect, state, await challengeOf(verifier)));
}

/**
 * When the page is the provider's redirect back (`?code=&state=`): trades the code for tokens
 * and answers the one the server takes, and puts the page's own query back in the address.
 * Null when the page is not a redirect back.
 */
export async function finishSignIn(settings: OidcSettings): Promise<string | null> {
  const params = new URLSearchParams(location.search);
  const code = params.get("code");
  const pendingJson = sessionStorage.getItem(PENDING_KEY);
  if ((!code && !params.get("error")) || !pendingJson) return null;
  sessionStorage.removeItem(PENDING_KEY);
  const pending = JSON.parse(pendingJson) as { verifier: string; state: string; search: string };
  history.replaceState(null, "", location.pathname + pending.search);
  if (params.get("error")) {
    throw new Error(`the provider refused: ${params.get("error_description") ?? params.get("error")}`);
  }
  if (params.get("state") !== pending.state) throw new Error("the sign-in answer does not match the request (state)");
  const d = await discover(settings.issuer);
  const r = await fetch(d.token_endpoint, {
    method: "POST",
    headers: { "content-type": "application/x-www-form-urlencoded" },
    body: new URLSearchParams({
      grant_type: "authorization_code",
      code: code ?? "",
      redirect_uri: redirectUri(location),
      client_id: settings.client_id,
      code_verifier: pending.verifier,
    }),
  });
  if (!r.ok) throw new Error(`the provider's token endpoint answered ${r.status}`);
  const token = pickToken((await r.json()) as { access_token?: string; id_token?: string }, settings.audience);
  if (!token) throw new Error(`the provider gave no token for the audience ${settings.audience}`);
  return token;
}
