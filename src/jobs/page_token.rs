//! Page tokens of job listings, sealed with an HMAC over the tenant and the backend's own
//! cursor, so a token names no global sequence and another tenant's or an edited one is
//! refused (issue 25, item 7).

/// The key of page tokens' HMAC: derived from the server secret (`--webhook-secret-file`)
/// when there is one, so that nodes sharing it accept each other's tokens and nobody else can
/// make one. Without it the key is fixed and public: tokens are then still bound to their
/// tenant and checked against edits, but a tenant who knows this source can forge one for
/// itself, which positions only its own listing (a token holds nothing else).
pub(crate) fn page_token_key(server_secret: Option<&[u8]>) -> ring::hmac::Key {
    const LABEL: &[u8] = b"willow page tokens v2";
    let material = match server_secret {
        Some(secret) => {
            let k = ring::hmac::Key::new(ring::hmac::HMAC_SHA256, secret);
            ring::hmac::sign(&k, LABEL).as_ref().to_vec()
        }
        None => LABEL.to_vec(),
    };
    ring::hmac::Key::new(ring::hmac::HMAC_SHA256, &material)
}

/// What a page token's HMAC covers: the tenant and the backend's token, length-prefixed so
/// that no two (tenant, token) pairs give the same bytes.
fn page_token_message(tenant: &str, token: &str) -> Vec<u8> {
    let mut m = Vec::with_capacity(16 + tenant.len() + token.len());
    m.extend_from_slice(&(tenant.len() as u64).to_be_bytes());
    m.extend_from_slice(tenant.as_bytes());
    m.extend_from_slice(token.as_bytes());
    m
}

/// `{token}.{mac}`: the backend's page token (base64url, no `.`) and the base64url
/// HMAC-SHA256 of it and `tenant` under `key`.
pub(super) fn seal_page_token(key: &ring::hmac::Key, tenant: &str, token: &str) -> String {
    use base64::Engine as _;
    let mac = ring::hmac::sign(key, &page_token_message(tenant, token));
    format!(
        "{token}.{}",
        base64::engine::general_purpose::URL_SAFE_NO_PAD.encode(mac.as_ref())
    )
}

/// The backend's token inside a sealed one, if `tenant` was given it by a server with `key`.
pub(super) fn unseal_page_token(
    key: &ring::hmac::Key,
    tenant: &str,
    sealed: &str,
) -> Option<String> {
    use base64::Engine as _;
    let (token, mac) = sealed.rsplit_once('.')?;
    let mac = base64::engine::general_purpose::URL_SAFE_NO_PAD
        .decode(mac)
        .ok()?;
    // `verify` compares in constant time.
    ring::hmac::verify(key, &page_token_message(tenant, token), &mac).ok()?;
    (!token.is_empty()).then(|| token.to_string())
}

#[cfg(test)]
mod page_token_tests {
    use super::*;

    /// A sealed token opens for the tenant it was given to, under the key that sealed it, and
    /// for nobody else; any edit is refused.
    #[test]
    fn page_tokens_are_bound_to_their_tenant_key_and_text() {
        let key = page_token_key(None);
        let token = "YXQ6MTc5NTc0MzkxMDAwMDpqXzE"; // base64url of a backend's `at:T:ID`
        let sealed = seal_page_token(&key, "alpha", token);
        assert_eq!(
            unseal_page_token(&key, "alpha", &sealed).as_deref(),
            Some(token)
        );
        // Another tenant's listing: refused.
        assert_eq!(unseal_page_token(&key, "beta", &sealed), None);
        // Tenants whose ids run into the token's text do not collide (length prefix).
        let shifted = seal_page_token(&key, "alph", &format!("a{token}"));
        assert_ne!(
            shifted.rsplit_once('.').map(|(_, m)| m),
            sealed.rsplit_once('.').map(|(_, m)| m)
        );
        // Every single-character edit of the token or its MAC: refused.
        for i in 0..sealed.len() {
            let mut edited: Vec<u8> = sealed.clone().into_bytes();
            edited[i] = if edited[i] == b'A' { b'B' } else { b'A' };
            let edited = String::from_utf8(edited).expect("ascii");
            assert_eq!(unseal_page_token(&key, "alpha", &edited), None, "{edited}");
        }
        for bad in ["", ".", "abc", "a.b", &format!("{token}.")] {
            assert_eq!(unseal_page_token(&key, "alpha", bad), None, "{bad}");
        }
        // A server with a secret makes tokens only it (and nodes sharing the secret) opens.
        let secret = page_token_key(Some(b"a server secret of 32 bytes, say"));
        let other = page_token_key(Some(b"another server's secret, 32 byte"));
        let sealed = seal_page_token(&secret, "alpha", token);
        assert_eq!(
            unseal_page_token(&secret, "alpha", &sealed).as_deref(),
            Some(token)
        );
        assert_eq!(unseal_page_token(&other, "alpha", &sealed), None);
        assert_eq!(unseal_page_token(&key, "alpha", &sealed), None);
    }
}
