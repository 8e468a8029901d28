//! JWT bearer tokens: HS256, RS256 or ES256, with `exp`/`nbf`, issuer and audience checked.

use super::{JwtConfig, Refusal};
use crate::jobs::Caller;

pub(super) struct JwtVerifier {
    key: jsonwebtoken::DecodingKey,
    validation: jsonwebtoken::Validation,
    tenant_claim: String,
}

impl JwtVerifier {
    pub(super) fn new(c: &JwtConfig) -> Result<JwtVerifier, String> {
        use jsonwebtoken::{Algorithm, DecodingKey, Validation};
        let key = match c.algorithm {
            Algorithm::RS256 => DecodingKey::from_rsa_pem(&c.key)
                .map_err(|e| format!("--jwt-key-file is not an RSA public key in PEM: {e}"))?,
            Algorithm::ES256 => DecodingKey::from_ec_pem(&c.key)
                .map_err(|e| format!("--jwt-key-file is not an EC public key in PEM: {e}"))?,
            _ => {
                if c.key.len() < 32 {
                    return Err(
                        "the HS256 secret in --jwt-key-file must be at least 32 bytes".into(),
                    );
                }
                DecodingKey::from_secret(&c.key)
            }
        };
        let mut validation = Validation::new(c.algorithm);
        validation.leeway = c.leeway_secs;
        validation.validate_exp = true;
        validation.validate_nbf = true;
        validation.set_issuer(&[c.issuer.as_str()]);
        validation.set_audience(&[c.audience.as_str()]);
        validation.set_required_spec_claims(&["exp", "iss", "aud", "sub"]);
        Ok(JwtVerifier {
            key,
            validation,
            tenant_claim: c.tenant_claim.clone(),
        })
    }

    pub(super) fn verify(&self, token: &str) -> Result<Caller, Refusal> {
        use jsonwebtoken::errors::ErrorKind;
        let data = jsonwebtoken::decode::<serde_json::Map<String, serde_json::Value>>(
            token,
            &self.key,
            &self.validation,
        )
        .map_err(|e| {
            let (reason, detail) = match e.kind() {
                ErrorKind::ExpiredSignature => ("expired_token", "the token has expired".into()),
                ErrorKind::ImmatureSignature => {
                    ("invalid_token", "the token is not valid yet (nbf)".into())
                }
                ErrorKind::InvalidAudience => (
                    "invalid_token",
                    "the token's audience (aud) is not this service".into(),
                ),
                ErrorKind::InvalidIssuer => (
                    "invalid_token",
                    "the token's issuer (iss) is not accepted".into(),
                ),
                ErrorKind::InvalidSignature => (
                    "invalid_token",
                    "the token's signature does not verify".into(),
                ),
                ErrorKind::InvalidAlgorithm => (
                    "invalid_token",
                    "the token is signed with another algorithm than the server accepts".into(),
                ),
                ErrorKind::MissingRequiredClaim(c) => (
                    "invalid_token",
                    format!("the token has no `{}` claim", crate::api::problem::clip(c)),
                ),
                _ => ("invalid_token", "the token is not a valid JWT".into()),
            };
            Refusal::invalid(reason, detail)
        })?;
        let claims = data.claims;
        let tenant = claims
            .get(&self.tenant_claim)
            .and_then(|v| v.as_str())
            .ok_or_else(|| {
                Refusal::invalid(
                    "invalid_token",
                    format!(
                        "the token has no string `{}` claim naming the tenant",
                        self.tenant_claim
                    ),
                )
            })?;
        let subject = claims.get("sub").and_then(|v| v.as_str()).unwrap_or("");
        Caller::new(tenant, subject)
            .map_err(|e| Refusal::invalid("invalid_token", format!("the token's tenant: {e}")))
    }
}
