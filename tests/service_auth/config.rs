//! Configuration, the CLI, and logs that never hold a token.

use super::*;

// Configuration, CLI, logs

/// The loopback rule as `willow serve` applies it: no auth on a non-loopback address is refused
/// unless explicitly allowed.
#[test]
fn non_loopback_without_auth_is_refused() {
    let args = AuthArgs::default();
    let e =
        AuthConfig::from_args(&args, "0.0.0.0:8080".parse().expect("addr")).expect_err("refused");
    assert!(e.contains("--insecure-allow-unauthenticated"), "{e}");
    assert!(AuthConfig::from_args(&args, "127.0.0.1:8080".parse().expect("addr")).is_ok());
    let allowed = AuthArgs {
        insecure_allow_unauthenticated: true,
        ..AuthArgs::default()
    };
    assert!(AuthConfig::from_args(&allowed, "0.0.0.0:8080".parse().expect("addr")).is_ok());

    let out = std::process::Command::new(env!("CARGO_BIN_EXE_willow"))
        .args(["serve", "--addr", "0.0.0.0:0", "--data-dir"])
        .arg(std::env::temp_dir().join("willow-auth-never-created"))
        .output()
        .expect("run willow");
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("--insecure-allow-unauthenticated"),
        "{stderr}"
    );
}

/// `--insecure-allow-unauthenticated` alone or as `=true` (deployment files use that form:
/// their linters read `--flag=value`); it never takes the next argument as its value.
#[test]
fn insecure_flag_forms() {
    use clap::Parser;
    #[derive(Parser)]
    struct T {
        #[command(flatten)]
        auth: AuthArgs,
        #[arg(long)]
        data_dir: Option<String>,
    }
    let t = T::try_parse_from(["t", "--insecure-allow-unauthenticated", "--data-dir", "/d"])
        .expect("bare flag");
    assert!(t.auth.insecure_allow_unauthenticated);
    assert_eq!(t.data_dir.as_deref(), Some("/d"));
    let t = T::try_parse_from(["t", "--insecure-allow-unauthenticated=true"]).expect("=true");
    assert!(t.auth.insecure_allow_unauthenticated);
    let t = T::try_parse_from(["t"]).expect("default");
    assert!(!t.auth.insecure_allow_unauthenticated);
    assert_eq!(t.auth.auth, "none");
    assert!(T::try_parse_from(["t", "--insecure-allow-unauthenticated=maybe"]).is_err());
}

/// `willow keys new` prints a key and a line whose hash is the key's.
#[test]
fn keys_new_cli() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_willow"))
        .args(["keys", "new", "--tenant", "acme", "--name", "ci"])
        .output()
        .expect("run willow");
    assert!(out.status.success());
    let stdout = String::from_utf8_lossy(&out.stdout);
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(lines.len(), 2, "{stdout}");
    assert!(lines[0].starts_with("wlw_"));
    assert!(lines[1].starts_with("acme ci sha256:"));
    assert!(!lines[1].contains(lines[0]));
    let bad = std::process::Command::new(env!("CARGO_BIN_EXE_willow"))
        .args(["keys", "new", "--tenant", "no spaces", "--name", "ci"])
        .output()
        .expect("run willow");
    assert!(!bad.status.success());
}

/// Keys, JWTs and stream tokens, good and bad, in headers and queries: none reaches the log
/// (every level, span fields included), while the refusals and requests are logged.
#[tokio::test]
async fn tokens_never_reach_the_log() {
    let capture = Capture::default();
    let subscriber = tracing_subscriber::fmt()
        .with_writer(capture.clone())
        .with_max_level(tracing::Level::TRACE)
        .json()
        .with_current_span(true)
        .with_span_list(true)
        .finish();
    // tracing-core caches each callsite's interest process-wide, and while at most one
    // dispatcher is alive it asks only the registering thread's default: a sibling test (no
    // subscriber) reaching `request refused` first would cache "never" for every thread. With
    // a second live dispatcher every registration asks all of them, this capture included.
    let _second = tracing::Dispatch::new(tracing_subscriber::registry());
    // A current-thread runtime: the server's tasks run on this thread, under this subscriber.
    let _guard = tracing::subscriber::set_default(subscriber);

    let (key, line) = willow_service::api::auth::new_key("acme", "ci").expect("key");
    let keys = key_file(std::slice::from_ref(&line));
    let server = Server::start(keys_and_jwt(&keys.file)).await;
    let auth = bearer(&key);
    let bad_key = "wlw_secret-bad-key-0123456789";
    let jwt = hs256(&claims(|_| {}));
    let expired = hs256(&claims(|c| c["exp"] = json!(now() - 3600)));
    let a = create_job(&server, &auth).await;
    let body: Value = mint(&server, &a, Some(&auth))
        .await
        .json()
        .await
        .expect("json");
    let token = body["token"].as_str().expect("token").to_string();
    server.submit(Some(&bearer(bad_key))).await;
    server.submit(Some(&bearer(&expired))).await;
    server.get("/v1/jobs", Some(&bearer(&jwt))).await;
    let res = server
        .get(&format!("/v1/jobs/{a}/events?access_token={token}"), None)
        .await;
    read_sse(res, PATIENCE).await;
    server
        .get(&format!("/v1/jobs?access_token={token}"), None)
        .await;
    server
        .get(&format!("/v1/nope?access_token={token}"), Some(&auth))
        .await;
    server.stop().await;

    let log = String::from_utf8_lossy(&capture.0.lock().expect("log").clone()).to_string();
    assert!(log.contains("request refused"), "nothing captured: {log}");
    let hash = line.rsplit(':').next().expect("hash");
    for secret in [
        key.as_str(),
        bad_key,
        jwt.as_str(),
        expired.as_str(),
        token.as_str(),
        hash,
    ] {
        assert!(!log.contains(secret), "a secret reached the log");
    }
    assert!(!log.contains("access_token"), "the query reached the log");
    assert!(!log.to_ascii_lowercase().contains("authorization"));
}
