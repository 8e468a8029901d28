//! Two tenants through the real transports (issue 12): API keys of tenants `alpha` and `beta`
//! against one server. Over HTTP and gRPC neither can see, stream, download, cancel or delete
//! the other's jobs, uploads or Operations; their idempotency keys are their own; quotas are
//! enforced per tenant and named.

mod service_http_support;

use serde_json::Value;
use service_http_support::{read_sse, slow_obj, small_obj};
use std::time::Duration;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic::Code;
use tonic_types::StatusExt;
use willow_service::api::auth::{new_key, Auth, AuthConfig, AuthMode};
use willow_service::api::grpc::pb::google::longrunning as lro;
use willow_service::api::grpc::pb::willow::v1;
use willow_service::api::server::{AppOptions, ServeOptions};
use willow_service::jobs::{Config, Jobs, TenantQuotas};

struct Server {
    base: String,
    client: reqwest::Client,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: Option<tokio::task::JoinHandle<std::io::Result<()>>>,
    _dir: tempfile::TempDir,
}

/// Bearer keys of the two tenants.
struct Keys {
    alpha: String,
    beta: String,
}

async fn start(quotas: TenantQuotas) -> (Server, Keys) {
    let dir = tempfile::tempdir().expect("temp dir");
    let (alpha, alpha_line) = new_key("alpha", "ci").expect("key");
    let (beta, beta_line) = new_key("beta", "ci").expect("key");
    let file = dir.path().join("keys");
    std::fs::write(&file, format!("{alpha_line}\n{beta_line}\n")).expect("key file");
    let auth = Auth::new(&AuthConfig {
        mode: AuthMode {
            keys: true,
            jwt: false,
        },
        keys_file: Some(file),
        ..AuthConfig::default()
    })
    .expect("auth");
    let mut config = Config::new(dir.path().join("data"));
    config.workers = 1;
    config.queue_capacity = 16;
    config.quotas = quotas;
    let (jobs, core) = Jobs::start(config).await.expect("start");
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let base = format!("http://{}", listener.local_addr().expect("addr"));
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let options = ServeOptions {
        app: AppOptions {
            auth,
            ..Default::default()
        },
        ..Default::default()
    };
    let task = tokio::spawn(willow_service::api::server::serve_with(
        listener,
        jobs,
        core,
        async move {
            let _ = rx.await;
        },
        Duration::from_secs(2),
        options,
    ));
    let server = Server {
        base,
        client: reqwest::Client::new(),
        stop: Some(tx),
        task: Some(task),
        _dir: dir,
    };
    (server, Keys { alpha, beta })
}

impl Server {
    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    async fn call(
        &self,
        method: reqwest::Method,
        path: &str,
        key: &str,
        body: Option<(String, Option<&str>)>,
    ) -> (u16, Value) {
        let mut req = self.client.request(method, self.url(path)).bearer_auth(key);
        if let Some((body, idem)) = body {
            req = req.header("content-type", "model/obj").body(body);
            if let Some(k) = idem {
                req = req.header("idempotency-key", k);
            }
        }
        let res = req.send().await.expect("request");
        let status = res.status().as_u16();
        (status, res.json().await.unwrap_or(Value::Null))
    }

    async fn submit(&self, key: &str, mesh: String, query: &str, idem: Option<&str>) -> Value {
        let (status, v) = self
            .call(
                reqwest::Method::POST,
                &format!(
                    "/v1/jobs?{}",
                    service_http_support::conformal_unless_named(query)
                ),
                key,
                Some((mesh, idem)),
            )
            .await;
        assert_eq!(status, 202, "{v}");
        v
    }

    async fn wait_terminal(&self, key: &str, id: &str) -> Value {
        for _ in 0..2400 {
            let (status, v) = self
                .call(reqwest::Method::GET, &format!("/v1/jobs/{id}"), key, None)
                .await;
            assert_eq!(status, 200, "{v}");
            if matches!(
                v["state"].as_str(),
                Some("succeeded" | "failed" | "cancelled")
            ) {
                return v;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        panic!("job {id} did not finish");
    }

    async fn stop(mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        if let Some(t) = self.task.take() {
            let _ = tokio::time::timeout(Duration::from_secs(20), t).await;
        }
    }
}

fn assert_not_found(status: u16, v: &Value, what: &str) {
    assert_eq!(status, 404, "{what}: {v}");
    assert_eq!(v["code"], "not_found", "{what}: {v}");
}

/// HTTP: every route on the other tenant's job is 404 `not_found`, exactly as for a job that
/// does not exist; keys are per tenant; the owner's calls still work afterwards.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn http_tenants_cannot_reach_each_others_jobs() {
    let (server, keys) = start(TenantQuotas::default()).await;
    let a = server
        .submit(&keys.alpha, small_obj(), "steps=2", Some("same-key"))
        .await;
    let id = a["id"].as_str().expect("id").to_string();
    server.wait_terminal(&keys.alpha, &id).await;

    use reqwest::Method;
    let b = &keys.beta;
    for (method, path) in [
        (Method::GET, format!("/v1/jobs/{id}")),
        (Method::GET, format!("/v1/jobs/{id}/events")),
        (Method::GET, format!("/v1/jobs/{id}/frames")),
        (Method::GET, format!("/v1/jobs/{id}/frames/0")),
        (Method::GET, format!("/v1/jobs/{id}/result")),
        (Method::POST, format!("/v1/jobs/{id}/cancel")),
        (Method::POST, format!("/v1/jobs/{id}/stream-token")),
        (Method::DELETE, format!("/v1/jobs/{id}")),
    ] {
        let (status, v) = server.call(method.clone(), &path, b, None).await;
        assert_not_found(status, &v, &format!("{method} {path}"));
        // The same answer as for an id nobody has.
        let unknown = path.replace(&id, "00000000-0000-4000-8000-000000000000");
        let (s2, v2) = server.call(method.clone(), &unknown, b, None).await;
        assert_eq!((s2, &v2["code"]), (status, &v["code"]), "{unknown}");
    }
    let (status, list) = server.call(Method::GET, "/v1/jobs", b, None).await;
    assert_eq!(status, 200);
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(0), "{list}");

    // B's stream token for its own job does not open A's.
    let mine = server.submit(b, small_obj(), "steps=1", None).await;
    let mine = mine["id"].as_str().expect("id").to_string();
    let (status, token) = server
        .call(
            Method::POST,
            &format!("/v1/jobs/{mine}/stream-token"),
            b,
            None,
        )
        .await;
    assert_eq!(status, 200, "{token}");
    let token = token["token"].as_str().expect("token");
    let res = server
        .client
        .get(server.url(&format!("/v1/jobs/{id}/events?access_token={token}")))
        .send()
        .await
        .expect("GET");
    assert_eq!(res.status(), 401, "a token for one job opens no other");

    // Idempotency keys: B's `same-key` makes B's own job.
    let b_same = server
        .submit(b, small_obj(), "steps=2", Some("same-key"))
        .await;
    assert_ne!(b_same["id"], a["id"]);
    let a_again = server
        .submit(&keys.alpha, small_obj(), "steps=2", Some("same-key"))
        .await;
    assert_eq!(a_again["id"], a["id"], "A's repeat finds A's job");

    // A still has everything, and streams it.
    let res = server
        .client
        .get(server.url(&format!("/v1/jobs/{id}/events")))
        .bearer_auth(&keys.alpha)
        .send()
        .await
        .expect("events");
    assert_eq!(res.status(), 200);
    let events = read_sse(res, Duration::from_secs(60)).await;
    assert!(events.iter().any(|e| e.event == "done"), "{events:?}");
    let (status, _) = server
        .call(
            Method::GET,
            &format!("/v1/jobs/{id}/result"),
            &keys.alpha,
            None,
        )
        .await;
    assert_eq!(status, 200);
    let (status, _) = server
        .call(Method::DELETE, &format!("/v1/jobs/{id}"), &keys.alpha, None)
        .await;
    assert_eq!(status, 204);
    server.stop().await;
}

/// HTTP: list page tokens are the tenant's own (issue 25 item 7). Alpha's token is refused
/// for beta (400, field `page_token`), and so is an edited one; it carries no global
/// sequence (beta's jobs submitted between alpha's pages change nothing in alpha's tokens'
/// positions); and alpha's pages, one job each, list all its jobs once, newest first, while
/// beta submits in between.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn http_page_tokens_are_the_tenants_own() {
    let (server, keys) = start(TenantQuotas::default()).await;
    let mut alpha_jobs = Vec::new();
    for _ in 0..4 {
        let v = server
            .submit(&keys.alpha, small_obj(), "steps=1", None)
            .await;
        alpha_jobs.push(v["id"].as_str().expect("id").to_string());
        server
            .submit(&keys.beta, small_obj(), "steps=1", None)
            .await;
        // Distinct creation times, so that "newest first" is the reverse of submission.
        tokio::time::sleep(Duration::from_millis(3)).await;
    }
    let list = |key: String, token: Option<String>| {
        let server = &server;
        async move {
            let path = match token {
                Some(t) => format!("/v1/jobs?page_size=1&page_token={t}"),
                None => "/v1/jobs?page_size=1".to_string(),
            };
            server.call(reqwest::Method::GET, &path, &key, None).await
        }
    };
    let (status, first) = list(keys.alpha.clone(), None).await;
    assert_eq!(status, 200, "{first}");
    let token = first["next_page_token"]
        .as_str()
        .expect("a next page")
        .to_string();
    // What it holds is alpha's own: the creation time and id of the page's last job.
    let last = &first["jobs"][0];
    let body = token.rsplit_once('.').map(|(b, _)| b).expect("sealed");
    use base64::Engine as _;
    let held = base64::engine::general_purpose::URL_SAFE_NO_PAD
        .decode(body)
        .map(|b| String::from_utf8_lossy(&b).into_owned())
        .expect("base64url");
    let (at, id) = held
        .strip_prefix("at:")
        .and_then(|r| r.split_once(':'))
        .unwrap_or_else(|| panic!("`at:T:ID`: {held}"));
    let at: u64 = at.parse().expect("unix ms");
    assert_eq!(
        (willow_service::jobs::rfc3339(at).as_str(), id),
        (
            last["created_time"].as_str().expect("created_time"),
            last["id"].as_str().expect("id")
        ),
        "the token holds the last job's creation time and id, nothing global"
    );

    // Beta cannot use alpha's token, nor an edited one.
    let edited = format!(
        "{}{}",
        &token[..token.len() - 2],
        if token.ends_with("AA") { "BB" } else { "AA" }
    );
    for (key, t) in [(&keys.beta, &token), (&keys.alpha, &edited)] {
        let (status, p) = list(key.clone(), Some(t.clone())).await;
        assert_eq!(status, 400, "{t}: {p}");
        assert_eq!(p["code"], "invalid_parameter", "{p}");
        assert_eq!(p["field"], "page_token", "{p}");
    }

    // Alpha pages through its jobs while beta keeps submitting: each of alpha's jobs once,
    // newest first (the reverse of submission), and nothing of beta's.
    let mut seen = Vec::new();
    let mut page = first;
    loop {
        for j in page["jobs"].as_array().expect("jobs") {
            seen.push(j["id"].as_str().expect("id").to_string());
        }
        let Some(t) = page["next_page_token"].as_str().map(str::to_string) else {
            break;
        };
        server
            .submit(&keys.beta, small_obj(), "steps=1", None)
            .await;
        let (status, next) = list(keys.alpha.clone(), Some(t)).await;
        assert_eq!(status, 200, "{next}");
        page = next;
    }
    let newest_first: Vec<String> = alpha_jobs.iter().rev().cloned().collect();
    assert_eq!(seen, newest_first, "alpha's jobs, each once, newest first");
    server.stop().await;
}

/// HTTP: the quota is named and counts one tenant only.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn http_quota_is_named_and_per_tenant() {
    let (server, keys) = start(TenantQuotas {
        server_max_stored_bytes: 0,
        max_live_jobs: 2,
        ..TenantQuotas::default()
    })
    .await;
    let mut ids = Vec::new();
    for _ in 0..2 {
        let v = server
            .submit(
                &keys.alpha,
                slow_obj(),
                "steps=5000&until_converged=false",
                None,
            )
            .await;
        ids.push(v["id"].as_str().expect("id").to_string());
    }
    let res = server
        .client
        .post(server.url("/v1/jobs?steps=1"))
        .bearer_auth(&keys.alpha)
        .header("content-type", "model/obj")
        .body(small_obj())
        .send()
        .await
        .expect("POST");
    assert_eq!(res.status(), 429);
    assert!(res.headers().contains_key("retry-after"));
    let p: Value = res.json().await.expect("problem");
    assert_eq!(p["code"], "quota_exceeded", "{p}");
    assert_eq!(p["quota"], "live_jobs", "{p}");
    assert_eq!(p["limit"], 2, "{p}");
    // B is not held back.
    server
        .submit(&keys.beta, small_obj(), "steps=1", None)
        .await;
    for id in ids {
        let (status, _) = server
            .call(
                reqwest::Method::POST,
                &format!("/v1/jobs/{id}/cancel"),
                &keys.alpha,
                None,
            )
            .await;
        assert_eq!(status, 202);
    }
    server.stop().await;
}

/// Adds the tenant's key to every call.
#[derive(Clone)]
struct Bearer(tonic::metadata::MetadataValue<tonic::metadata::Ascii>);

impl tonic::service::Interceptor for Bearer {
    fn call(&mut self, mut req: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        req.metadata_mut().insert("authorization", self.0.clone());
        Ok(req)
    }
}

type Fairing = v1::fairing_client::FairingClient<InterceptedService<Channel, Bearer>>;
type Operations = lro::operations_client::OperationsClient<InterceptedService<Channel, Bearer>>;

async fn clients(server: &Server, key: &str) -> (Fairing, Operations) {
    let channel = Channel::from_shared(server.base.clone())
        .expect("uri")
        .connect()
        .await
        .expect("h2c");
    let bearer = Bearer(format!("Bearer {key}").parse().expect("ascii"));
    (
        v1::fairing_client::FairingClient::with_interceptor(channel.clone(), bearer.clone()),
        lro::operations_client::OperationsClient::with_interceptor(channel, bearer),
    )
}

fn uuid() -> String {
    uuid::Uuid::new_v4().to_string()
}

fn create_request(mesh: v1::create_job_request::Mesh, request_id: &str) -> v1::CreateJobRequest {
    v1::CreateJobRequest {
        mesh: Some(mesh),
        params: Some(v1::JobParams {
            // The conformal flow: the default method leaves the clean test mesh alone at once.
            method: v1::Method::Conformal as i32,
            steps: Some(2),
            ..Default::default()
        }),
        request_id: request_id.to_string(),
    }
}

fn inline() -> v1::create_job_request::Mesh {
    v1::create_job_request::Mesh::InlineMesh(v1::InlineMesh {
        format: v1::MeshFormat::Obj as i32,
        data: small_obj().into_bytes().into(),
    })
}

/// gRPC: Fairing and Operations calls on the other tenant's job, and its uploads, are
/// NOT_FOUND; request ids are per tenant; the quota is RESOURCE_EXHAUSTED with its name.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_tenants_cannot_reach_each_others_jobs_uploads_or_operations() {
    let (server, keys) = start(TenantQuotas {
        server_max_stored_bytes: 0,
        max_live_jobs: 3,
        ..TenantQuotas::default()
    })
    .await;
    let (mut fa, mut oa) = clients(&server, &keys.alpha).await;
    let (mut fb, mut ob) = clients(&server, &keys.beta).await;
    let request_id = uuid();
    let op = fa
        .create_job(create_request(inline(), &request_id))
        .await
        .expect("A creates")
        .into_inner();
    let name = op.name.clone();
    let done = oa
        .wait_operation(lro::WaitOperationRequest {
            name: name.clone(),
            timeout: Some(prost_types::Duration {
                seconds: 60,
                nanos: 0,
            }),
        })
        .await
        .expect("wait")
        .into_inner();
    assert!(done.done, "{done:?}");

    let not_found = |r: Result<(), tonic::Status>, what: &str| match r {
        Err(s) => assert_eq!(s.code(), Code::NotFound, "{what}: {s:?}"),
        Ok(()) => panic!("{what}: B reached A's job"),
    };
    not_found(
        fb.get_job(v1::GetJobRequest { name: name.clone() })
            .await
            .map(|_| ()),
        "GetJob",
    );
    not_found(
        fb.cancel_job(v1::CancelJobRequest { name: name.clone() })
            .await
            .map(|_| ()),
        "CancelJob",
    );
    not_found(
        fb.delete_job(v1::DeleteJobRequest { name: name.clone() })
            .await
            .map(|_| ()),
        "DeleteJob",
    );
    not_found(
        fb.stream_frames(v1::StreamFramesRequest {
            name: name.clone(),
            from_step: 0,
        })
        .await
        .map(|_| ()),
        "StreamFrames",
    );
    not_found(
        fb.download_result(v1::DownloadResultRequest {
            name: name.clone(),
            format: 0,
        })
        .await
        .map(|_| ()),
        "DownloadResult",
    );
    not_found(
        ob.get_operation(lro::GetOperationRequest { name: name.clone() })
            .await
            .map(|_| ()),
        "GetOperation",
    );
    not_found(
        ob.wait_operation(lro::WaitOperationRequest {
            name: name.clone(),
            timeout: None,
        })
        .await
        .map(|_| ()),
        "WaitOperation",
    );
    not_found(
        ob.cancel_operation(lro::CancelOperationRequest { name: name.clone() })
            .await
            .map(|_| ()),
        "CancelOperation",
    );
    not_found(
        ob.delete_operation(lro::DeleteOperationRequest { name: name.clone() })
            .await
            .map(|_| ()),
        "DeleteOperation",
    );
    let listed = ob
        .list_operations(lro::ListOperationsRequest::default())
        .await
        .expect("list")
        .into_inner();
    assert!(listed.operations.is_empty(), "{listed:?}");
    let listed = fb
        .list_jobs(v1::ListJobsRequest::default())
        .await
        .expect("list")
        .into_inner();
    assert!(listed.jobs.is_empty(), "{listed:?}");

    // Uploads: A's upload name is nothing to B.
    let upload = fa
        .upload_mesh(futures::stream::iter(vec![
            v1::UploadMeshChunk {
                part: Some(v1::upload_mesh_chunk::Part::Header(v1::UploadHeader {
                    format: v1::MeshFormat::Obj as i32,
                    size_bytes: small_obj().len() as u64,
                })),
            },
            v1::UploadMeshChunk {
                part: Some(v1::upload_mesh_chunk::Part::Data(
                    small_obj().into_bytes().into(),
                )),
            },
        ]))
        .await
        .expect("A uploads")
        .into_inner();
    let stored = v1::create_job_request::Mesh::Upload(upload.name.clone());
    let refused = fb
        .create_job(create_request(stored.clone(), &uuid()))
        .await
        .expect_err("B cannot use A's upload");
    assert_eq!(refused.code(), Code::NotFound, "{refused:?}");
    fa.create_job(create_request(stored, &uuid()))
        .await
        .expect("A uses its upload");

    // Request ids: B's copy of A's id creates B's own job.
    let b_op = fb
        .create_job(create_request(inline(), &request_id))
        .await
        .expect("B creates")
        .into_inner();
    assert_ne!(b_op.name, name);
    let a_again = fa
        .create_job(create_request(inline(), &request_id))
        .await
        .expect("A repeats")
        .into_inner();
    assert_eq!(a_again.name, name);

    // A's live jobs: slow ones up to the quota of 3, then RESOURCE_EXHAUSTED naming it.
    let slow = || {
        v1::create_job_request::Mesh::InlineMesh(v1::InlineMesh {
            format: v1::MeshFormat::Obj as i32,
            data: slow_obj().into_bytes().into(),
        })
    };
    let mut refusal = None;
    let mut long = Vec::new();
    for _ in 0..5 {
        let mut req = create_request(slow(), &uuid());
        if let Some(p) = req.params.as_mut() {
            p.steps = Some(5000);
            p.until_converged = Some(false);
            // Few kept frames: the live-jobs quota is the one tested, not stored bytes.
            p.frame_interval = Some(1000);
        }
        match fa.create_job(req).await {
            Ok(op) => long.push(op.into_inner().name),
            Err(s) => {
                refusal = Some(s);
                break;
            }
        }
    }
    let refusal = refusal.expect("the live_jobs quota refuses");
    assert_eq!(refusal.code(), Code::ResourceExhausted, "{refusal:?}");
    let details = refusal.get_error_details();
    let quota = details.quota_failure().expect("QuotaFailure detail");
    assert_eq!(quota.violations[0].subject, "tenant_quota:live_jobs");
    assert_eq!(
        details.error_info().map(|i| i.reason.as_str()),
        Some("QUOTA_EXCEEDED")
    );
    assert!(details.retry_info().is_some(), "RetryInfo says when");
    for name in long {
        let _ = oa
            .cancel_operation(lro::CancelOperationRequest { name })
            .await;
    }
    server.stop().await;
}
