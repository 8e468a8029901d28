"""Willow's gRPC API seen by a client nobody here wrote: Python grpcio.

The stubs are generated from ../../proto at start-up by grpcio-tools (nothing generated is
checked in); the google.longrunning / google.rpc modules, the health client and the
reflection client come from their PyPI packages (pinned in requirements.txt).

Run by tests/service_grpc_python.rs against the real `willow serve` binary started with
`--workers 1 --queue-capacity 1`:

    .venv/bin/python tests/python/client_test.py --addr 127.0.0.1:PORT \
        --small-obj S.obj --small-glb S.glb --large-obj L.obj --slow-obj W.obj

Prints one line per check and a closing "N passed, N failed"; exits non-zero on failure.
"""

import argparse
import math
import os
import struct
import sys
import tempfile
import time
import traceback
import uuid

import grpc
from grpc_tools import protoc

HERE = os.path.dirname(os.path.abspath(__file__))
PROTO_ROOT = os.path.normpath(os.path.join(HERE, "..", "..", "proto"))

# Generous bound for any single wait on a loaded 2-core machine.
PATIENCE_S = 180


def generate_stubs():
    """Compile proto/willow/v1/*.proto to Python in a temp dir and import it.

    Only Willow's files are generated; their google/* imports resolve (at compile time) to the
    vendored files in proto/ and (at run time) to googleapis-common-protos, which is built from
    the same sources.
    """
    out = tempfile.mkdtemp(prefix="willow-pb-")
    protos = sorted(
        os.path.join(PROTO_ROOT, "willow", "v1", f)
        for f in os.listdir(os.path.join(PROTO_ROOT, "willow", "v1"))
        if f.endswith(".proto")
    )
    well_known = os.path.join(os.path.dirname(protoc.__file__), "_proto")
    args = [
        "grpc_tools.protoc",
        f"-I{PROTO_ROOT}",
        f"-I{well_known}",
        f"--python_out={out}",
        f"--grpc_python_out={out}",
        *protos,
    ]
    if protoc.main(args) != 0:
        raise SystemExit(f"protoc failed on {protos}")
    sys.path.insert(0, out)


generate_stubs()

from google.longrunning import operations_pb2, operations_pb2_grpc  # noqa: E402
from google.rpc import code_pb2, error_details_pb2, status_pb2  # noqa: E402
from grpc_health.v1 import health_pb2, health_pb2_grpc  # noqa: E402
from google.protobuf import empty_pb2  # noqa: E402
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import (  # noqa: E402
    ProtoReflectionDescriptorDatabase,
)
from willow.v1 import fairing_pb2 as pb  # noqa: E402
from willow.v1 import fairing_pb2_grpc as pb_grpc  # noqa: E402

CHUNK = 1 << 20


def upload(stub, fmt, data, chunk=CHUNK):
    def messages():
        yield pb.UploadMeshChunk(header=pb.UploadHeader(format=fmt, size_bytes=len(data)))
        for i in range(0, len(data), chunk):
            yield pb.UploadMeshChunk(data=data[i : i + chunk])

    return stub.UploadMesh(messages(), timeout=PATIENCE_S)


def details(err):
    """The google.rpc.Status carried in `grpc-status-details-bin`, with its details unpacked."""
    for key, value in err.trailing_metadata() or ():
        if key == "grpc-status-details-bin":
            status = status_pb2.Status.FromString(value)
            out = {}
            for any_msg in status.details:
                for cls in (
                    error_details_pb2.BadRequest,
                    error_details_pb2.RetryInfo,
                    error_details_pb2.ErrorInfo,
                    error_details_pb2.QuotaFailure,
                    error_details_pb2.ResourceInfo,
                    error_details_pb2.PreconditionFailure,
                ):
                    if any_msg.Is(cls.DESCRIPTOR):
                        msg = cls()
                        any_msg.Unpack(msg)
                        out[cls.__name__] = msg
            return status, out
    raise AssertionError(f"no status details on {err.code()}: {err.details()}")


def expect_error(fn, code):
    try:
        fn()
    except grpc.RpcError as err:
        assert err.code() == code, f"expected {code}, got {err.code()}: {err.details()}"
        return err
    raise AssertionError(f"expected {code}, the call succeeded")


def bad_fields(err):
    _, d = details(err)
    return [v.field for v in d["BadRequest"].field_violations]


def job_from_any(any_msg):
    job = pb.Job()
    assert any_msg.Unpack(job), any_msg.type_url
    return job


class Suite:
    def __init__(self, args):
        self.args = args
        target = args.addr
        options = [("grpc.max_receive_message_length", 64 << 20)]
        self.channel = grpc.insecure_channel(target, options=options)
        grpc.channel_ready_future(self.channel).result(timeout=30)
        self.fairing = pb_grpc.FairingStub(self.channel)
        self.ops = operations_pb2_grpc.OperationsStub(self.channel)
        self.health = health_pb2_grpc.HealthStub(self.channel)
        self.small_obj = open(args.small_obj, "rb").read()
        self.small_glb = open(args.small_glb, "rb").read()
        self.large_obj = open(args.large_obj, "rb").read()
        self.slow_obj = open(args.slow_obj, "rb").read()

    def create_inline(self, data, fmt=pb.MESH_FORMAT_OBJ, request_id="", **params):
        return self.fairing.CreateJob(
            pb.CreateJobRequest(
                inline_mesh=pb.InlineMesh(format=fmt, data=data),
                params=pb.JobParams(**params),
                request_id=request_id,
            ),
            timeout=PATIENCE_S,
        )

    # -- checks, run in this order (the server has one worker and a queue of one) -------------

    def test_health_serving(self):
        reply = self.health.Check(health_pb2.HealthCheckRequest(service=""), timeout=10)
        assert reply.status == health_pb2.HealthCheckResponse.SERVING, reply
        reply = self.health.Check(
            health_pb2.HealthCheckRequest(service="willow.v1.Fairing"), timeout=10
        )
        assert reply.status == health_pb2.HealthCheckResponse.SERVING, reply

    def test_reflection_lists_services(self):
        db = ProtoReflectionDescriptorDatabase(self.channel)
        services = set(db.get_services())
        for want in (
            "willow.v1.Fairing",
            "google.longrunning.Operations",
            "grpc.health.v1.Health",
        ):
            assert want in services, f"{want} not in {sorted(services)}"
        # The descriptors themselves come through reflection too.
        from google.protobuf.descriptor_pool import DescriptorPool

        pool = DescriptorPool(db)
        fairing = pool.FindServiceByName("willow.v1.Fairing")
        methods = {m.name for m in fairing.methods}
        assert {"UploadMesh", "CreateJob", "StreamFrames", "CancelJob"} <= methods, methods

    def test_upload_large_obj_in_chunks(self):
        assert len(self.large_obj) > 4 << 20, len(self.large_obj)
        up = upload(self.fairing, pb.MESH_FORMAT_OBJ, self.large_obj)
        assert up.name.startswith("uploads/"), up.name
        assert up.size_bytes == len(self.large_obj)
        assert up.format == pb.MESH_FORMAT_OBJ

    def test_glb_job_frames_resume_and_operations(self):
        up = upload(self.fairing, pb.MESH_FORMAT_GLB, self.small_glb, chunk=4096)
        request_id = str(uuid.uuid4())
        request = pb.CreateJobRequest(
            upload=up.name,
            params=pb.JobParams(
                method=pb.METHOD_MCF, steps=5, tau=0.1, frame_interval=2, include_positions=True
            ),
            request_id=request_id,
        )
        op = self.fairing.CreateJob(request, timeout=PATIENCE_S)
        again = self.fairing.CreateJob(request, timeout=PATIENCE_S)
        assert again.name == op.name, "same request_id, same operation (AIP-155)"
        meta = job_from_any(op.metadata)
        assert meta.name == op.name and meta.total_steps == 5

        steps, position_bytes, last = [], [], None
        for msg in self.fairing.StreamFrames(
            pb.StreamFramesRequest(name=op.name, from_step=0), timeout=PATIENCE_S
        ):
            if msg.HasField("frame"):
                f = msg.frame
                steps.append(f.step)
                keyframe = f.step % 2 == 0 or f.step == 5
                assert f.HasField("positions") == keyframe, f"step {f.step}"
                if keyframe:
                    n = len(f.positions) // 12
                    xyz = struct.unpack(f"<{3 * n}f", f.positions)
                    assert len(f.positions) == 12 * n and n > 0
                    position_bytes.append(len(f.positions))
                    assert all(abs(c) < 10 for c in xyz)
                assert f.metrics.step == f.step and f.metrics.area > 0
            else:
                last = msg.job
        assert steps == list(range(0, 6)), steps
        assert last is not None and last.state == pb.Job.SUCCEEDED, last
        # 12 bytes (3 little-endian f32) per vertex of the uploaded file, on steps 0, 2, 4, 5.
        assert position_bytes == [12 * last.vertex_count] * 4, (position_bytes, last.vertex_count)

        resumed = [
            m.frame.step
            for m in self.fairing.StreamFrames(
                pb.StreamFramesRequest(name=op.name, from_step=3), timeout=PATIENCE_S
            )
            if m.HasField("frame")
        ]
        assert resumed == [3, 4, 5], resumed

        done = self.ops.WaitOperation(
            operations_pb2.WaitOperationRequest(name=op.name), timeout=PATIENCE_S
        )
        assert done.done and done.HasField("response"), done
        assert job_from_any(done.response).state == pb.Job.SUCCEEDED
        got = self.ops.GetOperation(operations_pb2.GetOperationRequest(name=op.name), timeout=30)
        assert got.done and job_from_any(got.metadata).step == 5
        job = self.fairing.GetJob(pb.GetJobRequest(name=op.name), timeout=30)
        assert job.state == pb.Job.SUCCEEDED and job.latest.step == 5

        data = b"".join(
            c.data
            for c in self.fairing.DownloadResult(
                pb.DownloadResultRequest(name=op.name, format=pb.MESH_FORMAT_GLB),
                timeout=PATIENCE_S,
            )
        )
        assert data[:4] == b"glTF", data[:16]

        other = pb.CreateJobRequest()
        other.CopyFrom(request)
        other.params.steps = 6
        err = expect_error(
            lambda: self.fairing.CreateJob(other, timeout=PATIENCE_S),
            grpc.StatusCode.ALREADY_EXISTS,
        )
        assert bad_fields(err) == ["request_id"]

    def test_poll_obj_job_to_done(self):
        # The flow options of JobParams 8-11, set the way a Python client sets messages.
        op = self.create_inline(
            self.small_obj,
            method=pb.METHOD_CONFORMAL,
            steps=3,
            mobius_balancing=True,
            filter=pb.SpectralFilter(sigma=0.01, k=2),
            boundary=pb.Boundary(cmc=empty_pb2.Empty()),
        )
        meta = job_from_any(op.metadata)
        assert meta.params.mobius_balancing and meta.params.exactness, meta.params
        assert meta.params.filter.k == 2 and meta.params.boundary.WhichOneof("condition") == "cmc"
        deadline = time.monotonic() + PATIENCE_S
        while True:
            got = self.ops.GetOperation(operations_pb2.GetOperationRequest(name=op.name), timeout=30)
            if got.done:
                break
            assert time.monotonic() < deadline, "job did not finish"
            time.sleep(0.05)
        job = self.fairing.GetJob(pb.GetJobRequest(name=op.name), timeout=30)
        assert job.state == pb.Job.SUCCEEDED, job
        assert job.input_format == pb.MESH_FORMAT_OBJ
        assert abs(job.params.filter.sigma - 0.01) < 1e-15, job.params

    def test_fair_curve(self):
        # r = 1 + 0.2 sin 5t, 200 points: the flow rounds it and keeps its length.
        n = 200
        xy = []
        for i in range(n):
            t = 2 * math.pi * i / n
            r = 1 + 0.2 * math.sin(5 * t)
            xy += [r * math.cos(t), r * math.sin(t)]

        def length(v):
            return sum(
                math.hypot(v[2 * ((i + 1) % n)] - v[2 * i], v[2 * ((i + 1) % n) + 1] - v[2 * i + 1])
                for i in range(n)
            )

        out = self.fairing.FairCurve(
            pb.FairCurveRequest(curve=pb.Curve(xy=xy, closed=True), steps=6), timeout=60
        )
        assert len(out.curve.xy) == 2 * n and out.curve.closed
        first, last = out.metrics[0], out.metrics[-1]
        assert last.step == 6 and first.curvature_std_over_mean > 0.5, first
        assert last.curvature_std_over_mean < 1e-2 * first.curvature_std_over_mean, last
        assert abs(length(out.curve.xy) / length(xy) - 1) < 1e-3
        err = expect_error(
            lambda: self.fairing.FairCurve(
                pb.FairCurveRequest(curve=pb.Curve(xy=xy[:-1], closed=True)), timeout=10
            ),
            grpc.StatusCode.INVALID_ARGUMENT,
        )
        assert bad_fields(err) == ["curve.xy"], bad_fields(err)

    def test_bad_inputs(self):
        err = expect_error(
            lambda: self.create_inline(b"v 0 0 0\nf 1 2 3\n", steps=1),
            grpc.StatusCode.INVALID_ARGUMENT,
        )
        assert bad_fields(err) == ["inline_mesh.data"], bad_fields(err)
        err = expect_error(
            lambda: self.create_inline(self.small_obj, steps=0),
            grpc.StatusCode.INVALID_ARGUMENT,
        )
        assert bad_fields(err) == ["params.steps"], bad_fields(err)
        err = expect_error(
            lambda: self.create_inline(self.small_obj, steps=1, tau=-1.0),
            grpc.StatusCode.INVALID_ARGUMENT,
        )
        assert bad_fields(err) == ["params.tau"], bad_fields(err)
        err = expect_error(
            lambda: self.create_inline(self.small_obj, steps=1, method=99),
            grpc.StatusCode.INVALID_ARGUMENT,
        )
        assert bad_fields(err) == ["params.method"], bad_fields(err)
        err = expect_error(
            lambda: self.create_inline(self.small_obj, request_id="not-a-uuid"),
            grpc.StatusCode.INVALID_ARGUMENT,
        )
        assert bad_fields(err) == ["request_id"], bad_fields(err)
        err = expect_error(
            lambda: self.fairing.GetJob(pb.GetJobRequest(name="nope"), timeout=10),
            grpc.StatusCode.INVALID_ARGUMENT,
        )
        assert bad_fields(err) == ["name"]
        err = expect_error(
            lambda: self.ops.GetOperation(
                operations_pb2.GetOperationRequest(name=f"jobs/{uuid.uuid4()}"), timeout=10
            ),
            grpc.StatusCode.NOT_FOUND,
        )
        assert "ResourceInfo" in details(err)[1]
        # An upload stream that starts with data instead of the header.
        err = expect_error(
            lambda: self.fairing.UploadMesh(iter([pb.UploadMeshChunk(data=b"v 0 0 0")]), timeout=10),
            grpc.StatusCode.INVALID_ARGUMENT,
        )
        assert bad_fields(err) == ["header"]
        status, _ = details(err)
        assert status.code == code_pb2.INVALID_ARGUMENT

    def test_queue_full_and_cancel(self):
        running = self.create_inline(
            self.slow_obj, method=pb.METHOD_CONFORMAL, steps=5000,
            until_converged=False,
        )
        deadline = time.monotonic() + PATIENCE_S
        while self.fairing.GetJob(pb.GetJobRequest(name=running.name), timeout=10).step < 1:
            assert time.monotonic() < deadline, "the slow job never started"
            time.sleep(0.05)
        queued = self.create_inline(self.small_obj, method=pb.METHOD_MCF, steps=1)
        err = expect_error(
            lambda: self.create_inline(self.small_obj, method=pb.METHOD_MCF, steps=1),
            grpc.StatusCode.RESOURCE_EXHAUSTED,
        )
        _, d = details(err)
        assert d["RetryInfo"].retry_delay.seconds >= 1, d
        assert d["ErrorInfo"].reason == "QUEUE_FULL", d

        self.ops.CancelOperation(operations_pb2.CancelOperationRequest(name=queued.name), timeout=10)
        job = self.fairing.GetJob(pb.GetJobRequest(name=queued.name), timeout=10)
        assert job.state == pb.Job.CANCELLED, job

        self.fairing.CancelJob(pb.CancelJobRequest(name=running.name), timeout=10)
        done = self.ops.WaitOperation(
            operations_pb2.WaitOperationRequest(name=running.name), timeout=PATIENCE_S
        )
        assert done.done and done.error.code == code_pb2.CANCELLED, done
        err = expect_error(
            lambda: self.fairing.CancelJob(pb.CancelJobRequest(name=running.name), timeout=10),
            grpc.StatusCode.FAILED_PRECONDITION,
        )
        assert "PreconditionFailure" in details(err)[1]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--addr", required=True, help="host:port of `willow serve`")
    parser.add_argument("--small-obj", required=True)
    parser.add_argument("--small-glb", required=True)
    parser.add_argument("--large-obj", required=True)
    parser.add_argument("--slow-obj", required=True)
    args = parser.parse_args()

    suite = Suite(args)
    checks = [name for name in Suite.__dict__ if name.startswith("test_")]
    passed = failed = 0
    for name in checks:
        started = time.monotonic()
        try:
            getattr(suite, name)()
        except Exception:  # report every check, not just the first failure
            failed += 1
            print(f"FAIL {name}", flush=True)
            traceback.print_exc()
        else:
            passed += 1
            print(f"ok   {name} ({time.monotonic() - started:.2f}s)", flush=True)
    print(f"{passed} passed, {failed} failed", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
