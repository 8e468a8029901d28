//! Flags and configuration of authentication: `--auth`, the key file, JWT, and the rule
//! that a network address needs authentication.

use super::API_KEYS_ENV;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

/// The authentication flags of `willow serve` (flattened into its `ServeArgs`).
#[derive(Debug, Clone, clap::Args)]
pub struct AuthArgs {
    /// Who may call: `none` (everyone is the anonymous caller; loopback only unless
    /// --insecure-allow-unauthenticated), `keys` (API keys), `jwt` (JSON Web Tokens) or
    /// `keys,jwt`.
    #[arg(long, default_value = "none")]
    pub auth: String,
    /// Serve a non-loopback --addr with `--auth none`: anyone who can reach the port can
    /// submit, read and delete jobs. Only behind something that authenticates for us.
    /// (`--insecure-allow-unauthenticated=true` works too, for argument lists that expect
    /// `--flag=value`.)
    #[arg(long, num_args = 0..=1, require_equals = true, default_missing_value = "true",
          action = clap::ArgAction::Set, default_value_t = false)]
    pub insecure_allow_unauthenticated: bool,
    /// API key file: lines `<tenant> <name> sha256:<hex>` (`#` starts a comment), as
    /// `willow keys new` prints them. Re-read when it changes and on SIGHUP. The variable
    /// WILLOW_API_KEYS may hold more lines.
    #[arg(long)]
    pub api_keys_file: Option<PathBuf>,
    /// Seconds between checks of --api-keys-file for changes.
    #[arg(long, default_value_t = 5.0)]
    pub api_keys_poll_secs: f64,
    /// JWT signature algorithm: HS256, RS256 or ES256.
    #[arg(long)]
    pub jwt_algorithm: Option<String>,
    /// JWT verification key: the shared secret (HS256; the file's bytes, a final newline
    /// dropped) or the PEM public key (RS256, ES256). Re-read when it changes and on SIGHUP.
    #[arg(long)]
    pub jwt_key_file: Option<PathBuf>,
    /// Required `iss` of JWTs.
    #[arg(long)]
    pub jwt_issuer: Option<String>,
    /// Required `aud` of JWTs.
    #[arg(long)]
    pub jwt_audience: Option<String>,
    /// The JWT claim naming the caller's tenant.
    #[arg(long, default_value = "tenant")]
    pub jwt_tenant_claim: String,
    /// Clock skew allowed on JWT `exp` and `nbf`, in seconds.
    #[arg(long, default_value_t = 30)]
    pub jwt_leeway_secs: u64,
    /// Secret (at least 32 bytes) signing stream tokens. Give every node of a multi-node
    /// deployment the same file, or a token minted on one node is refused by the others;
    /// without it each process draws a random secret (tokens die with the process).
    #[arg(long)]
    pub stream_token_secret_file: Option<PathBuf>,
    /// Lifetime of a stream token in seconds.
    #[arg(long, default_value_t = 300)]
    pub stream_token_ttl_secs: u64,
    /// Require credentials on /metrics too.
    #[arg(long)]
    pub protect_metrics: bool,
}

impl Default for AuthArgs {
    fn default() -> Self {
        AuthArgs {
            auth: "none".into(),
            insecure_allow_unauthenticated: false,
            api_keys_file: None,
            api_keys_poll_secs: 5.0,
            jwt_algorithm: None,
            jwt_key_file: None,
            jwt_issuer: None,
            jwt_audience: None,
            jwt_tenant_claim: "tenant".into(),
            jwt_leeway_secs: 30,
            stream_token_secret_file: None,
            stream_token_ttl_secs: 300,
            protect_metrics: false,
        }
    }
}

/// Which credentials `--auth` accepts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct AuthMode {
    pub keys: bool,
    pub jwt: bool,
}

impl AuthMode {
    /// `none`, `keys`, `jwt`, `keys,jwt` (or `jwt,keys`).
    pub fn parse(s: &str) -> Result<AuthMode, String> {
        let mut mode = AuthMode::default();
        if s.trim() == "none" {
            return Ok(mode);
        }
        for part in s.split(',') {
            match part.trim() {
                "keys" => mode.keys = true,
                "jwt" => mode.jwt = true,
                _ => {
                    return Err(format!(
                        "--auth must be `none`, `keys`, `jwt` or `keys,jwt`, got `{}`",
                        crate::api::problem::clip(s)
                    ))
                }
            }
        }
        Ok(mode)
    }

    pub fn enabled(self) -> bool {
        self.keys || self.jwt
    }
}

/// JWT verification settings.
#[derive(Debug, Clone)]
pub struct JwtConfig {
    pub algorithm: jsonwebtoken::Algorithm,
    /// HS256: the secret; RS256/ES256: the PEM public key.
    pub key: Vec<u8>,
    pub issuer: String,
    pub audience: String,
    pub tenant_claim: String,
    pub leeway_secs: u64,
    /// Where `key` was read from: re-read when its content changes (every
    /// `--api-keys-poll-secs`) and on SIGHUP, so the identity provider's key can rotate
    /// without a restart; a file that does not hold a valid key keeps the old one. `None`:
    /// `key` is fixed.
    pub key_file: Option<PathBuf>,
}

/// The JWT key in `path`: the HS256 secret without a final newline, or the PEM as it is.
pub(super) fn read_jwt_key(
    path: &std::path::Path,
    algorithm: jsonwebtoken::Algorithm,
) -> Result<Vec<u8>, String> {
    let mut key = std::fs::read(path)
        .map_err(|e| format!("cannot read --jwt-key-file {}: {e}", path.display()))?;
    if algorithm == jsonwebtoken::Algorithm::HS256 {
        strip_final_newline(&mut key);
    }
    Ok(key)
}

/// Everything [`Auth::new`](super::Auth::new) needs, validated; built from the flags by [`AuthConfig::from_args`]
/// or directly (tests).
#[derive(Debug, Clone, Default)]
pub struct AuthConfig {
    pub mode: AuthMode,
    pub keys_file: Option<PathBuf>,
    /// Key lines from [`API_KEYS_ENV`].
    pub keys_env: Option<String>,
    pub keys_poll: Duration,
    pub jwt: Option<JwtConfig>,
    /// `None`: a random secret for this process.
    pub stream_secret: Option<Vec<u8>>,
    pub stream_ttl: Duration,
    pub protect_metrics: bool,
}

impl AuthConfig {
    /// The configuration the flags describe for a server on `addr`; refuses a non-loopback
    /// address without authentication unless `--insecure-allow-unauthenticated`.
    pub fn from_args(args: &AuthArgs, addr: SocketAddr) -> Result<AuthConfig, String> {
        let mode = AuthMode::parse(&args.auth)?;
        check_bind(addr, mode, args.insecure_allow_unauthenticated)?;
        let keys_env = std::env::var(API_KEYS_ENV).ok();
        if !mode.keys && (args.api_keys_file.is_some() || keys_env.is_some()) {
            return Err(format!(
                "--api-keys-file or {API_KEYS_ENV} is set but --auth does not include `keys`"
            ));
        }
        if mode.keys && args.api_keys_file.is_none() && keys_env.is_none() {
            return Err(format!(
                "--auth keys needs --api-keys-file or the {API_KEYS_ENV} variable"
            ));
        }
        if !(args.api_keys_poll_secs.is_finite() && args.api_keys_poll_secs >= 0.1) {
            return Err("--api-keys-poll-secs must be at least 0.1".into());
        }
        let jwt_flags = args.jwt_algorithm.is_some()
            || args.jwt_key_file.is_some()
            || args.jwt_issuer.is_some()
            || args.jwt_audience.is_some();
        if !mode.jwt && jwt_flags {
            return Err("--jwt-* flags are set but --auth does not include `jwt`".into());
        }
        let jwt = if mode.jwt {
            let need = |v: &Option<String>, flag: &str| {
                v.clone()
                    .filter(|s| !s.is_empty())
                    .ok_or_else(|| format!("--auth jwt needs {flag}"))
            };
            let algorithm = parse_algorithm(&need(&args.jwt_algorithm, "--jwt-algorithm")?)?;
            let path = args
                .jwt_key_file
                .as_ref()
                .ok_or("--auth jwt needs --jwt-key-file")?;
            Some(JwtConfig {
                algorithm,
                key: read_jwt_key(path, algorithm)?,
                key_file: Some(path.clone()),
                issuer: need(&args.jwt_issuer, "--jwt-issuer")?,
                audience: need(&args.jwt_audience, "--jwt-audience")?,
                tenant_claim: args.jwt_tenant_claim.clone(),
                leeway_secs: args.jwt_leeway_secs,
            })
        } else {
            None
        };
        if args.protect_metrics && !mode.enabled() {
            return Err("--protect-metrics needs --auth keys or jwt".into());
        }
        let stream_secret = match &args.stream_token_secret_file {
            None => None,
            Some(path) => {
                let mut s = std::fs::read(path).map_err(|e| {
                    format!(
                        "cannot read --stream-token-secret-file {}: {e}",
                        path.display()
                    )
                })?;
                strip_final_newline(&mut s);
                Some(s)
            }
        };
        if args.stream_token_ttl_secs == 0 {
            return Err("--stream-token-ttl-secs must be at least 1".into());
        }
        Ok(AuthConfig {
            mode,
            keys_file: args.api_keys_file.clone(),
            keys_env,
            keys_poll: Duration::from_secs_f64(args.api_keys_poll_secs),
            jwt,
            stream_secret,
            stream_ttl: Duration::from_secs(args.stream_token_ttl_secs),
            protect_metrics: args.protect_metrics,
        })
    }
}

/// The loopback rule: without authentication, only a loopback address, unless explicitly
/// allowed.
pub fn check_bind(addr: SocketAddr, mode: AuthMode, allow_insecure: bool) -> Result<(), String> {
    if mode.enabled() || allow_insecure || addr.ip().is_loopback() {
        return Ok(());
    }
    Err(format!(
        "refusing to serve {addr} without authentication: anyone who can reach it could submit, \
         read and delete jobs. Use --auth keys or --auth jwt, bind a loopback address, or pass \
         --insecure-allow-unauthenticated if something in front of willow authenticates"
    ))
}

pub(super) fn parse_algorithm(s: &str) -> Result<jsonwebtoken::Algorithm, String> {
    match s.to_ascii_uppercase().as_str() {
        "HS256" => Ok(jsonwebtoken::Algorithm::HS256),
        "RS256" => Ok(jsonwebtoken::Algorithm::RS256),
        "ES256" => Ok(jsonwebtoken::Algorithm::ES256),
        _ => Err(format!(
            "--jwt-algorithm must be HS256, RS256 or ES256, got `{}`",
            crate::api::problem::clip(s)
        )),
    }
}

pub(super) fn strip_final_newline(b: &mut Vec<u8>) {
    if b.last() == Some(&b'\n') {
        b.pop();
        if b.last() == Some(&b'\r') {
            b.pop();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn modes_parse() {
        assert_eq!(AuthMode::parse("none"), Ok(AuthMode::default()));
        assert_eq!(
            AuthMode::parse("keys,jwt"),
            Ok(AuthMode {
                keys: true,
                jwt: true
            })
        );
        assert!(AuthMode::parse("basic").is_err());
        assert!(AuthMode::parse("").is_err());
    }

    #[test]
    fn loopback_rule() {
        let none = AuthMode::default();
        let keys = AuthMode {
            keys: true,
            jwt: false,
        };
        let lo: SocketAddr = "127.0.0.1:8080".parse().unwrap();
        let lo6: SocketAddr = "[::1]:8080".parse().unwrap();
        let any: SocketAddr = "0.0.0.0:8080".parse().unwrap();
        assert!(check_bind(lo, none, false).is_ok());
        assert!(check_bind(lo6, none, false).is_ok());
        let e = check_bind(any, none, false).unwrap_err();
        assert!(e.contains("--insecure-allow-unauthenticated"), "{e}");
        assert!(check_bind(any, none, true).is_ok());
        assert!(check_bind(any, keys, false).is_ok());
    }

    #[test]
    fn from_args_refuses_network_without_auth() {
        let args = AuthArgs::default();
        let e = AuthConfig::from_args(&args, "0.0.0.0:80".parse().unwrap()).unwrap_err();
        assert!(e.contains("--insecure-allow-unauthenticated"), "{e}");
        let jwt = AuthArgs {
            auth: "jwt".into(),
            jwt_algorithm: Some("HS256".into()),
            ..AuthArgs::default()
        };
        let e = AuthConfig::from_args(&jwt, "127.0.0.1:80".parse().unwrap()).unwrap_err();
        assert!(e.contains("--jwt-key-file"), "{e}");
    }
}
