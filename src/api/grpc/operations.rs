//! `google.longrunning.Operations`: the same jobs seen as long-running operations (an
//! Operation's name is its job's name).

use std::time::Duration;

use tonic::{Request, Response, Status};

use super::convert::{
    duration_from_pb, grpc_timeout, operation, page_size, parse_name, parse_operation_filter,
};
use super::errors::{bad_request, caller, clip, job_error};
use super::pb::google::longrunning as lro;
use super::{GrpcApi, WAIT_DEADLINE_MARGIN};

/// Upper bound of one `WaitOperation` call. AIP-151 lets the server cap the wait; a bounded
/// long-poll keeps idle connections from piling up behind a load balancer's idle timeout.
const MAX_WAIT: Duration = Duration::from_secs(60);

#[tonic::async_trait]
impl lro::operations_server::Operations for GrpcApi {
    async fn list_operations(
        &self,
        request: Request<lro::ListOperationsRequest>,
    ) -> Result<Response<lro::ListOperationsResponse>, Status> {
        let caller = caller(&request)?;
        let request = request.into_inner();
        // The collection's name: "jobs" (ours), "operations" (what generic LRO clients send)
        // or empty. Anything else names a collection this server does not have.
        if !matches!(request.name.as_str(), "" | "jobs" | "operations") {
            return Err(bad_request(
                "name",
                format!("must be `jobs` (or empty), got `{}`", clip(&request.name)),
            ));
        }
        let state = parse_operation_filter(&request.filter)?;
        let page_size = page_size(request.page_size)?;
        let token = Some(request.page_token).filter(|t| !t.is_empty());
        let (jobs, next) = self
            .jobs
            .list(&caller, state, page_size, token)
            .await
            .map_err(|e| job_error(e, "page_token"))?;
        Ok(Response::new(lro::ListOperationsResponse {
            operations: jobs.iter().map(operation).collect(),
            next_page_token: next.unwrap_or_default(),
            ..Default::default()
        }))
    }

    async fn get_operation(
        &self,
        request: Request<lro::GetOperationRequest>,
    ) -> Result<Response<lro::Operation>, Status> {
        let caller = caller(&request)?;
        let id = parse_name("name", "jobs/", &request.get_ref().name)?;
        let status = self
            .jobs
            .get(&caller, &id)
            .await
            .map_err(|e| job_error(e, "name"))?;
        Ok(Response::new(operation(&status)))
    }

    async fn delete_operation(
        &self,
        request: Request<lro::DeleteOperationRequest>,
    ) -> Result<Response<()>, Status> {
        let caller = caller(&request)?;
        let id = parse_name("name", "jobs/", &request.get_ref().name)?;
        self.jobs
            .delete(&caller, &id)
            .await
            .map_err(|e| job_error(e, "name"))?;
        Ok(Response::new(()))
    }

    async fn cancel_operation(
        &self,
        request: Request<lro::CancelOperationRequest>,
    ) -> Result<Response<()>, Status> {
        let caller = caller(&request)?;
        let id = parse_name("name", "jobs/", &request.get_ref().name)?;
        self.jobs
            .cancel(&caller, &id)
            .await
            .map_err(|e| job_error(e, "name"))?;
        Ok(Response::new(()))
    }

    async fn wait_operation(
        &self,
        request: Request<lro::WaitOperationRequest>,
    ) -> Result<Response<lro::Operation>, Status> {
        let client_deadline = grpc_timeout(&request);
        let caller = caller(&request)?;
        let request = request.into_inner();
        let id = parse_name("name", "jobs/", &request.name)?;
        let asked = match request.timeout {
            Some(t) => Some(duration_from_pb("timeout", &t)?),
            None => None,
        };
        // AIP-151: the shorter of the request's timeout and the RPC deadline, capped by the
        // server.
        let wait = [
            asked,
            client_deadline.map(|d| d.saturating_sub(WAIT_DEADLINE_MARGIN)),
            Some(MAX_WAIT),
        ]
        .into_iter()
        .flatten()
        .min()
        .unwrap_or(MAX_WAIT);
        let status = self
            .jobs
            .wait(&caller, &id, wait)
            .await
            .map_err(|e| job_error(e, "name"))?;
        Ok(Response::new(operation(&status)))
    }
}
