#!/usr/bin/env python3
"""Checks of docker/ and deploy/ for scripts/lint-deploy.sh (run with its venv's python).

  lint-deploy.py k8s VERSIONS NAME=RENDERED.yaml...   rendered overlays: schema + rules
  lint-deploy.py compose CONFIG.json PROMETHEUS.yml   `docker compose config` output: rules
  lint-deploy.py selftest VERSIONS RENDERED.yaml CONFIG.json PROMETHEUS.yml
                                                      broken copies of those must fail

Kubernetes objects are validated with kubernetes-validate (the API's OpenAPI schemas, strict:
unknown fields are errors) against each version in VERSIONS (comma-separated). A kind without a
schema there is an error, except KEDA's ScaledObject, a CRD, whose fields are checked here
(check_scaled_object). Then the rules a schema cannot express: the hardening every pod must
have, probes, resources, labels, the drain fitting in terminationGracePeriodSeconds, the backend
and role flags agreeing with the objects around them, references between objects resolving.
Prints what it checked; exits 1 with every problem listed.
"""

import copy
import functools
import json
import re
import sys

import yaml
import kubernetes_validate
from kubernetes_validate import utils as kv_utils

# The same multi-megabyte definitions file is read for every object: read each file once.
kv_utils.schema_contents = functools.lru_cache(maxsize=None)(kv_utils.schema_contents)

# What the service does on SIGTERM after --grace-secs: the HTTP server waits up to this long
# (src/api/server.rs HTTP_DRAIN), and the kill must come later still, by this margin.
HTTP_DRAIN_SECS = 10
MIN_MARGIN_SECS = 5
# The JetStream names the NATS backend uses; KEDA must watch these.
JOBS_STREAM = "WILLOW_JOBS"
JOBS_CONSUMER = "willow-workers"
# A flow step on a 1M-triangle mesh takes ~4 GB: a pod that runs flows needs at least this.
FLOW_MEMORY = 4 * 1024**3
UID = 65532

WORKLOADS = ("Deployment", "StatefulSet")


class Problems:
    def __init__(self):
        self.items = []

    def add(self, where, what):
        self.items.append(f"{where}: {what}")


def kn(doc):
    meta = doc.get("metadata") or {}
    ns = meta.get("namespace")
    return f"{doc.get('kind')}/{meta.get('name')}" + (f" (ns {ns})" if ns else "")


def quantity(q):
    """Kubernetes quantity -> number (bytes for memory, cores for CPU)."""
    units = {"Ki": 2**10, "Mi": 2**20, "Gi": 2**30, "Ti": 2**40,
             "k": 1e3, "M": 1e6, "G": 1e9, "T": 1e12, "m": 1e-3}
    m = re.fullmatch(r"([0-9.]+)([A-Za-z]*)", str(q))
    if not m or (m.group(2) and m.group(2) not in units):
        raise ValueError(f"not a quantity: {q!r}")
    return float(m.group(1)) * units.get(m.group(2), 1)


def flags(args):
    """`serve --a b --c=d` -> {'--a': 'b', '--c': 'd'} (willow's flags all take a value)."""
    out, i = {}, 1
    while i < len(args):
        a = str(args[i])
        if a.startswith("--") and "=" in a:
            k, v = a.split("=", 1)
            out[k] = v
            i += 1
        elif a.startswith("--") and i + 1 < len(args):
            out[a] = str(args[i + 1])
            i += 2
        else:
            out[a] = None
            i += 1
    return out


def duration_secs(s):
    """Compose durations as `docker compose config` prints them: 1m0s, 60s, 1m30s."""
    total, rest = 0.0, str(s)
    for num, unit in re.findall(r"([0-9.]+)(h|ms|m|s|us|ns)", rest):
        total += float(num) * {"h": 3600, "m": 60, "s": 1, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}[unit]
    return total


def image_repository(image):
    """`registry:5000/team/willow:1.0@sha256:...` -> `registry:5000/team/willow`."""
    name = image.split("@")[0]
    head, _, last = name.rpartition("/")
    return (head + "/" if head else "") + last.split(":")[0]


def is_willow_image(image):
    return image_repository(image).rsplit("/", 1)[-1] == "willow"


def image_problem(image):
    """None when `image` is pinned, else why not. willow:latest is allowed: kustomize `images:`
    or WILLOW_IMAGE replace it (base/kustomization.yaml)."""
    if is_willow_image(image):
        return None
    if "@sha256:" in image:
        return None
    last = image.split("/")[-1]
    if ":" not in last:
        return f"image {image!r} has no tag (means latest): pin a version"
    if last.rsplit(":", 1)[1] == "latest":
        return f"image {image!r} uses the latest tag: pin a version"
    return None


# ---------------------------------------------------------------------------------------------
# KEDA ScaledObject (keda.sh/v1alpha1): no schema in kubernetes-validate, so its fields here.

SCALED_OBJECT_SPEC = {"scaleTargetRef", "pollingInterval", "cooldownPeriod", "initialCooldownPeriod",
                      "idleReplicaCount", "minReplicaCount", "maxReplicaCount", "fallback",
                      "advanced", "triggers"}
NATS_JETSTREAM_METADATA = {"natsServerMonitoringEndpoint", "account", "stream", "consumer",
                           "lagThreshold", "activationLagThreshold", "useHttps"}


def check_scaled_object(doc, docs, versions, p):
    where = kn(doc)
    spec = doc.get("spec")
    if not isinstance(spec, dict):
        p.add(where, "no spec")
        return
    for k in set(spec) - SCALED_OBJECT_SPEC:
        p.add(where, f"unknown field spec.{k}")
    for k in ("pollingInterval", "cooldownPeriod", "initialCooldownPeriod", "idleReplicaCount",
              "minReplicaCount", "maxReplicaCount"):
        if k in spec and (not isinstance(spec[k], int) or isinstance(spec[k], bool) or spec[k] < 0):
            p.add(where, f"spec.{k} must be a non-negative integer, is {spec[k]!r}")
    lo, hi = spec.get("minReplicaCount", 0), spec.get("maxReplicaCount", 100)
    if isinstance(lo, int) and isinstance(hi, int) and lo > hi:
        p.add(where, f"minReplicaCount {lo} > maxReplicaCount {hi}")

    ref = spec.get("scaleTargetRef") or {}
    unknown = set(ref) - {"name", "kind", "apiVersion", "envSourceContainerName"}
    if unknown:
        p.add(where, f"unknown fields in scaleTargetRef: {sorted(unknown)}")
    kind = ref.get("kind", "Deployment")
    if ref.get("apiVersion", "apps/v1") != "apps/v1" or kind not in WORKLOADS:
        p.add(where, f"scaleTargetRef must be an apps/v1 Deployment or StatefulSet, is {ref}")
    target = find(docs, kind, ref.get("name"), doc["metadata"].get("namespace"))
    if target is None:
        p.add(where, f"scaleTargetRef {kind}/{ref.get('name')} is not in this overlay")

    fallback = spec.get("fallback")
    if fallback is not None:
        if set(fallback) - {"failureThreshold", "replicas", "behavior"}:
            p.add(where, "unknown fields in fallback")
        if not isinstance(fallback.get("failureThreshold"), int) or fallback["failureThreshold"] < 1:
            p.add(where, "fallback.failureThreshold must be an integer >= 1")
        if not isinstance(fallback.get("replicas"), int) or fallback["replicas"] < 0:
            p.add(where, "fallback.replicas must be a non-negative integer")

    advanced = spec.get("advanced") or {}
    if set(advanced) - {"restoreToOriginalReplicaCount", "horizontalPodAutoscalerConfig", "scalingModifiers"}:
        p.add(where, "unknown fields in spec.advanced")
    hpa_config = advanced.get("horizontalPodAutoscalerConfig") or {}
    if set(hpa_config) - {"name", "behavior"}:
        p.add(where, "unknown fields in spec.advanced.horizontalPodAutoscalerConfig")
    if "behavior" in hpa_config:
        # KEDA passes it to the HorizontalPodAutoscaler it creates: validate it as one.
        hpa = {"apiVersion": "autoscaling/v2", "kind": "HorizontalPodAutoscaler",
               "metadata": {"name": "keda-hpa"},
               "spec": {"scaleTargetRef": {"apiVersion": "apps/v1", "kind": "Deployment", "name": "x"},
                        "maxReplicas": 1, "behavior": hpa_config["behavior"]}}
        for v in versions:
            try:
                kubernetes_validate.validate(hpa, v, strict=True)
            except kubernetes_validate.ValidationError as e:
                p.add(where, f"advanced.horizontalPodAutoscalerConfig.behavior ({v}): {e.message}")

    triggers = spec.get("triggers")
    if not isinstance(triggers, list) or not triggers:
        p.add(where, "spec.triggers must be a non-empty list")
        return
    for i, trig in enumerate(triggers):
        tw = f"{where} triggers[{i}]"
        meta = trig.get("metadata")
        if not isinstance(meta, dict):
            p.add(tw, "no metadata")
            continue
        # The CRD types metadata as map[string]string: a bare number is refused by the API.
        for k, v in meta.items():
            if not isinstance(v, str):
                p.add(tw, f"metadata.{k} must be a string (quote it), is {v!r}")
        if trig.get("type") != "nats-jetstream":
            p.add(tw, f"trigger type {trig.get('type')!r}: this check knows only nats-jetstream")
            continue
        for k in set(meta) - NATS_JETSTREAM_METADATA:
            p.add(tw, f"unknown nats-jetstream metadata {k}")
        for k in ("natsServerMonitoringEndpoint", "account", "stream", "consumer"):
            if not meta.get(k):
                p.add(tw, f"nats-jetstream needs metadata.{k}")
        if meta.get("stream") != JOBS_STREAM:
            p.add(tw, f"stream is {meta.get('stream')!r}; the NATS backend's job stream is {JOBS_STREAM}")
        if meta.get("consumer") != JOBS_CONSUMER:
            p.add(tw, f"consumer is {meta.get('consumer')!r}; the workers' durable consumer is {JOBS_CONSUMER}")
        for k in ("lagThreshold", "activationLagThreshold"):
            if k in meta and not re.fullmatch(r"[0-9]+", str(meta[k])):
                p.add(tw, f"{k} must be a whole number, is {meta[k]!r}")
        if "useHttps" in meta and str(meta["useHttps"]) not in ("true", "false"):
            p.add(tw, "useHttps must be \"true\" or \"false\"")
        # host:port of a Service of this overlay, named with this namespace (KEDA resolves it
        # from its own namespace).
        endpoint = str(meta.get("natsServerMonitoringEndpoint", ""))
        m = re.fullmatch(r"([a-z0-9-]+)\.([a-z0-9-]+)\.svc(?:\.cluster\.local)?:([0-9]+)", endpoint)
        if not m:
            p.add(tw, f"natsServerMonitoringEndpoint {endpoint!r} is not SERVICE.NAMESPACE.svc:PORT "
                      "(no scheme: KEDA adds it)")
            continue
        svc_name, ns, port = m.group(1), m.group(2), int(m.group(3))
        if ns != doc["metadata"].get("namespace"):
            p.add(tw, f"natsServerMonitoringEndpoint names namespace {ns!r}, the overlay deploys to "
                      f"{doc['metadata'].get('namespace')!r}")
        svc = find(docs, "Service", svc_name, ns)
        if svc is None:
            p.add(tw, f"natsServerMonitoringEndpoint: no Service {svc_name} in namespace {ns} here")
        elif port not in [sp.get("port") for sp in svc["spec"].get("ports", [])]:
            p.add(tw, f"natsServerMonitoringEndpoint: Service {svc_name} has no port {port}")


CUSTOM_CHECKS = {("keda.sh/v1alpha1", "ScaledObject"): check_scaled_object}


# ---------------------------------------------------------------------------------------------
# Rendered overlays.

def find(docs, kind, name, namespace=None):
    for d in docs:
        if d.get("kind") == kind and d["metadata"].get("name") == name and \
                (namespace is None or d["metadata"].get("namespace") == namespace):
            return d
    return None


def selects(selector, labels):
    return bool(selector) and all(labels.get(k) == v for k, v in selector.items())


def pod_labels(docs):
    return [(d, d["spec"]["template"]["metadata"].get("labels") or {})
            for d in docs if d.get("kind") in WORKLOADS]


def check_schema(docs, versions, p, notes):
    for doc in docs:
        key = (doc.get("apiVersion"), doc.get("kind"))
        for v in versions:
            try:
                kubernetes_validate.validate(doc, v, strict=True)
            except kubernetes_validate.SchemaNotFoundError:
                if key not in CUSTOM_CHECKS:
                    p.add(kn(doc), f"no schema for {key[0]} {key[1]} in Kubernetes {v} and no check "
                                   "of it in scripts/lint-deploy.py: add one rather than skip it")
                    break
                # Checked once, below, whatever the version.
            except kubernetes_validate.ValidationError as e:
                path = ".".join(str(x) for x in e.absolute_path) or "(top)"
                p.add(kn(doc), f"Kubernetes {v} schema: {path}: {e.message}")
        if key in CUSTOM_CHECKS:
            CUSTOM_CHECKS[key](doc, docs, versions, p)
            notes.append(f"{kn(doc)}: {key[0]} CRD, no API schema; fields checked by lint-deploy.py")


def check_labels(doc, p):
    where = kn(doc)
    labels = doc["metadata"].get("labels") or {}
    wanted = ["app.kubernetes.io/part-of"]
    if doc.get("kind") != "Namespace":
        wanted.append("app.kubernetes.io/name")
    if doc.get("kind") not in ("Namespace", "ServiceAccount"):
        wanted.append("app.kubernetes.io/component")
    for k in wanted:
        if k not in labels:
            p.add(where, f"no label {k}")


def check_workload(doc, docs, p):
    where = kn(doc)
    spec = doc["spec"]
    template = spec["template"]
    tlabels = template["metadata"].get("labels") or {}
    sel = (spec.get("selector") or {}).get("matchLabels") or {}
    if not selects(sel, tlabels):
        p.add(where, f"selector {sel} does not match the pod template's labels")
    for k in ("app.kubernetes.io/name", "app.kubernetes.io/component", "app.kubernetes.io/part-of"):
        if k not in tlabels:
            p.add(where, f"pod template has no label {k}")
    pod = template["spec"]
    psc = pod.get("securityContext") or {}
    if psc.get("runAsNonRoot") is not True:
        p.add(where, "pod securityContext.runAsNonRoot must be true")
    if (psc.get("seccompProfile") or {}).get("type") != "RuntimeDefault":
        p.add(where, "pod securityContext.seccompProfile.type must be RuntimeDefault")
    if pod.get("automountServiceAccountToken") is not False:
        p.add(where, "automountServiceAccountToken must be false (nothing here calls the API)")
    volumes = {v["name"]: v for v in pod.get("volumes", [])}
    claim_templates = {c["metadata"]["name"] for c in spec.get("volumeClaimTemplates", [])}
    for c in pod.get("initContainers", []) + pod.get("containers", []):
        cw = f"{where} container {c['name']}"
        problem = image_problem(c.get("image", ""))
        if problem:
            p.add(cw, problem)
        sc = c.get("securityContext") or {}
        if sc.get("allowPrivilegeEscalation") is not False:
            p.add(cw, "securityContext.allowPrivilegeEscalation must be false")
        if sc.get("readOnlyRootFilesystem") is not True:
            p.add(cw, "securityContext.readOnlyRootFilesystem must be true")
        if "ALL" not in ((sc.get("capabilities") or {}).get("drop") or []):
            p.add(cw, "securityContext.capabilities.drop must contain ALL")
        if sc.get("privileged"):
            p.add(cw, "must not be privileged")
        uid = sc.get("runAsUser", psc.get("runAsUser"))
        if not isinstance(uid, int) or uid == 0:
            p.add(cw, f"runAsUser must be a numeric non-root UID, is {uid!r}")
        res = c.get("resources") or {}
        for part in ("requests", "limits"):
            for r in ("cpu", "memory"):
                if r not in (res.get(part) or {}):
                    p.add(cw, f"resources.{part}.{r} missing")
        for probe in ("startupProbe", "livenessProbe", "readinessProbe"):
            if probe not in c:
                p.add(cw, f"no {probe}")
        for m in c.get("volumeMounts", []):
            if m["name"] not in volumes and m["name"] not in claim_templates:
                p.add(cw, f"volumeMount {m['name']} has no volume")
        if is_willow_image(c.get("image", "")):
            check_willow_container(doc, c, volumes, docs, p)


def probe_path(c, probe):
    return ((c.get(probe) or {}).get("httpGet") or {}).get("path")


def check_willow_container(doc, c, volumes, docs, p):
    where = f"{kn(doc)} container {c['name']}"
    args = [str(a) for a in (c.get("args") or [])]
    if c.get("command") or not args or args[0] != "serve":
        p.add(where, "must run the image's entrypoint with `serve ...` as args")
        return
    f = flags(args)
    pod = doc["spec"]["template"]["spec"]

    ports = {cp.get("name"): cp.get("containerPort") for cp in c.get("ports", [])}
    addr = f.get("--addr", "127.0.0.1:8080")
    if not addr.startswith("0.0.0.0:"):
        p.add(where, f"--addr {addr} is not reachable from outside the pod: use 0.0.0.0:PORT")
    elif int(addr.rsplit(":", 1)[1]) not in ports.values():
        p.add(where, f"--addr {addr}: no containerPort {addr.rsplit(':', 1)[1]}")
    for probe, path in (("startupProbe", "/healthz"), ("livenessProbe", "/healthz"),
                        ("readinessProbe", "/readyz")):
        if probe_path(c, probe) != path:
            p.add(where, f"{probe} must GET {path}, gets {probe_path(c, probe)!r}")

    data_dir = f.get("--data-dir", "./willow-data")
    mount = next((m for m in c.get("volumeMounts", []) if m.get("mountPath") == data_dir), None)
    if mount is None:
        p.add(where, f"--data-dir {data_dir} is not a mounted volume (the root filesystem is read-only)")
        data_volume = {}
    else:
        data_volume = volumes.get(mount["name"], {})

    # The drain must end before the kubelet kills: preStop, then --grace-secs, then the HTTP
    # server's own drain.
    grace = float(f.get("--grace-secs", 30))
    pre_stop = (((c.get("lifecycle") or {}).get("preStop") or {}).get("sleep") or {}).get("seconds", 0)
    tgps = pod.get("terminationGracePeriodSeconds", 30)
    need = pre_stop + grace + HTTP_DRAIN_SECS + MIN_MARGIN_SECS
    if tgps < need:
        p.add(where, f"terminationGracePeriodSeconds {tgps} < preStop {pre_stop} + --grace-secs {grace:g} "
                     f"+ {HTTP_DRAIN_SECS} s HTTP drain + {MIN_MARGIN_SECS} s margin = {need:g}")

    backend = f.get("--backend", "embedded")
    role = f.get("--role", "all")
    if role not in ("api", "worker", "all"):
        p.add(where, f"--role {role!r} is not api, worker or all")
    memory_limit = quantity(((c.get("resources") or {}).get("limits") or {}).get("memory", "0"))
    if role in ("worker", "all") and memory_limit < FLOW_MEMORY:
        p.add(where, f"--role {role} runs flows (~4 GB at 1M triangles): memory limit "
                     f"{memory_limit / 2**30:.1f} GiB is too small")
    autoscalers = [d for d in docs if d.get("kind") in ("HorizontalPodAutoscaler", "ScaledObject")
                   and (d["spec"].get("scaleTargetRef") or {}).get("name") == doc["metadata"]["name"]]

    if backend == "embedded":
        # One process owns the SQLite database on one volume.
        if role != "all":
            p.add(where, f"--backend embedded runs in one process: --role must be all, is {role}")
        if doc["spec"].get("replicas") != 1:
            p.add(where, f"--backend embedded needs replicas: 1, has {doc['spec'].get('replicas')!r}")
        if doc.get("kind") == "Deployment" and (doc["spec"].get("strategy") or {}).get("type") != "Recreate":
            p.add(where, "--backend embedded needs strategy Recreate (never two pods on one database)")
        if autoscalers:
            p.add(where, f"--backend embedded cannot scale out, yet {kn(autoscalers[0])} targets it")
        if "persistentVolumeClaim" not in data_volume:
            p.add(where, "--backend embedded keeps its jobs in --data-dir: it must be a persistent volume claim")
        elif find(docs, "PersistentVolumeClaim", data_volume["persistentVolumeClaim"].get("claimName")) is None:
            p.add(where, f"claim {data_volume['persistentVolumeClaim'].get('claimName')} is not in this overlay")
    elif backend.startswith("nats://"):
        m = re.fullmatch(r"nats://([a-z0-9-]+)(?:\.([a-z0-9-]+)\.svc(?:\.cluster\.local)?)?:([0-9]+)", backend)
        if not m:
            p.add(where, f"--backend {backend}: expected nats://SERVICE:PORT")
        else:
            ns = m.group(2) or doc["metadata"].get("namespace")
            svc = find(docs, "Service", m.group(1), ns)
            if svc is None:
                p.add(where, f"--backend {backend}: no Service {m.group(1)} in namespace {ns} here")
            elif int(m.group(3)) not in [sp.get("port") for sp in svc["spec"].get("ports", [])]:
                p.add(where, f"--backend {backend}: Service {m.group(1)} has no port {m.group(3)}")
        if role == "all":
            p.add(where, "--backend nats: give each Deployment --role api or --role worker")
        if "emptyDir" not in data_volume:
            p.add(where, "--backend nats keeps nothing durable locally: --data-dir should be an emptyDir")
        if role == "worker" and not any(d.get("kind") == "ScaledObject" for d in autoscalers):
            p.add(where, "workers on NATS should be scaled by a KEDA ScaledObject on the job queue")
    else:
        p.add(where, f"--backend {backend!r}: neither embedded nor nats://HOST:PORT")


def check_references(docs, p):
    workloads = pod_labels(docs)
    for d in docs:
        kind = d.get("kind")
        if kind == "Service":
            sel = d["spec"].get("selector") or {}
            matched = [(w, l) for w, l in workloads if selects(sel, l)]
            if not matched:
                p.add(kn(d), f"selector {sel} matches no pod template here")
            for sp in d["spec"].get("ports", []):
                tp = sp.get("targetPort", sp.get("port"))
                for w, _ in matched:
                    names = {cp.get("name") for c in w["spec"]["template"]["spec"]["containers"]
                             for cp in c.get("ports", [])}
                    numbers = {cp.get("containerPort") for c in w["spec"]["template"]["spec"]["containers"]
                               for cp in c.get("ports", [])}
                    if tp not in names and tp not in numbers:
                        p.add(kn(d), f"targetPort {tp!r} is not a port of {kn(w)}")
        elif kind == "PodDisruptionBudget":
            sel = (d["spec"].get("selector") or {}).get("matchLabels") or {}
            if not any(selects(sel, l) for _, l in workloads):
                p.add(kn(d), f"selector {sel} matches no pod template here")
        elif kind == "HorizontalPodAutoscaler":
            ref = d["spec"]["scaleTargetRef"]
            if find(docs, ref["kind"], ref["name"], d["metadata"].get("namespace")) is None:
                p.add(kn(d), f"scaleTargetRef {ref['kind']}/{ref['name']} is not in this overlay")
        elif kind == "StatefulSet":
            if find(docs, "Service", d["spec"].get("serviceName"), d["metadata"].get("namespace")) is None:
                p.add(kn(d), f"serviceName {d['spec'].get('serviceName')} is not a Service here")
        if kind in WORKLOADS:
            for v in d["spec"]["template"]["spec"].get("volumes", []):
                if "configMap" in v and find(docs, "ConfigMap", v["configMap"]["name"]) is None:
                    p.add(kn(d), f"volume {v['name']}: ConfigMap {v['configMap']['name']} is not here")
            sa = d["spec"]["template"]["spec"].get("serviceAccountName")
            if sa and find(docs, "ServiceAccount", sa) is None:
                p.add(kn(d), f"serviceAccountName {sa} is not here")


def check_overlay(name, docs, versions, p, notes, rules=True):
    check_schema(docs, versions, p, notes)
    if not rules:
        return
    namespaces = {d["metadata"].get("namespace") for d in docs if d.get("kind") != "Namespace"}
    if len(namespaces) != 1 or None in namespaces:
        p.add(name, f"every object should be in one namespace, found {sorted(map(str, namespaces))}")
    for d in docs:
        check_labels(d, p)
        if d.get("kind") in WORKLOADS:
            check_workload(d, docs, p)
    check_references(docs, p)
    if not any(d.get("kind") in WORKLOADS and any(is_willow_image(c.get("image", ""))
               for c in d["spec"]["template"]["spec"]["containers"]) for d in docs):
        p.add(name, "no willow workload rendered")


def load_render(path):
    with open(path) as fh:
        return [d for d in yaml.safe_load_all(fh) if d]


def cmd_k8s(versions, specs):
    p, notes, total = Problems(), [], 0
    for spec in specs:
        name, path = spec.split("=", 1)
        rules = not name.endswith(":schema-only")
        name = name.split(":")[0]
        docs = load_render(path)
        total += len(docs)
        before = len(p.items)
        check_overlay(name, docs, versions, p, notes, rules)
        kinds = ", ".join(sorted({d["kind"] for d in docs}))
        what = "strict schema" + (" + rules" if rules else " only (not deployable on its own)")
        status = "ok" if len(p.items) == before else f"{len(p.items) - before} problem(s)"
        print(f"  {name}: {len(docs)} objects ({kinds}); {what} against Kubernetes "
              f"{', '.join(versions)}: {status}")
    for n in sorted(set(notes)):
        print(f"  note: {n}")
    return report(p)


# ---------------------------------------------------------------------------------------------
# docker/compose.yaml, as `docker compose config --format json` resolved it.

COMPOSE_SERVICES = {"nats": None, "api-1": "api", "api-2": "api", "worker-1": "worker",
                    "worker-2": "worker", "prometheus": None}
API_HOST_PORTS = {"api-1": "8081", "api-2": "8082"}


def check_compose(cfg, prom, p):
    services = cfg.get("services") or {}
    missing = set(COMPOSE_SERVICES) - set(services)
    if missing:
        p.add("compose", f"missing services: {sorted(missing)}")
    for name, svc in services.items():
        problem = image_problem(svc.get("image", ""))
        if problem:
            p.add(f"compose {name}", problem)
    nats = services.get("nats") or {}
    if nats and not any(s in " ".join(map(str, (nats.get("command") or []))) for s in ("--config", "-js")):
        p.add("compose nats", "JetStream is not enabled (-js or a --config with a jetstream block)")

    targets = set()
    for job in (prom or {}).get("scrape_configs") or []:
        if job.get("metrics_path", "/metrics") != "/metrics":
            continue
        for sc in job.get("static_configs") or []:
            targets.update(sc.get("targets") or [])

    for name, role in COMPOSE_SERVICES.items():
        svc = services.get(name)
        if role is None or svc is None:
            continue
        where = f"compose {name}"
        if not is_willow_image(svc.get("image", "")):
            p.add(where, f"image {svc.get('image')!r} is not willow")
        if str(svc.get("user")) != f"{UID}:{UID}":
            p.add(where, f"user must be \"{UID}:{UID}\", is {svc.get('user')!r}")
        if svc.get("read_only") is not True:
            p.add(where, "read_only must be true")
        if "ALL" not in (svc.get("cap_drop") or []):
            p.add(where, "cap_drop must contain ALL")
        cmd = [str(a) for a in (svc.get("command") or [])]
        if not cmd or cmd[0] != "serve":
            p.add(where, "command must be `serve ...`")
            continue
        f = flags(cmd)
        data_dir = f.get("--data-dir")
        if not any(str(t).split(":")[0] == data_dir for t in (svc.get("tmpfs") or [])):
            p.add(where, f"--data-dir {data_dir} must be a tmpfs (read-only root filesystem)")
        if f.get("--role") != role:
            p.add(where, f"--role must be {role}, is {f.get('--role')!r}")
        backend = f.get("--backend", "embedded")
        m = re.fullmatch(r"nats://([a-z0-9-]+):([0-9]+)", backend)
        if not m or m.group(1) not in services:
            p.add(where, f"--backend {backend!r} must be nats://SERVICE:PORT of a service here")
        elif "nats" not in (svc.get("depends_on") or {}):
            p.add(where, "must depend on nats")
        grace = float(f.get("--grace-secs", 30))
        stop = duration_secs(svc.get("stop_grace_period", "10s"))
        if stop < grace + HTTP_DRAIN_SECS + MIN_MARGIN_SECS:
            p.add(where, f"stop_grace_period {stop:g} s < --grace-secs {grace:g} + {HTTP_DRAIN_SECS} s "
                         f"HTTP drain + {MIN_MARGIN_SECS} s margin")
        port = f.get("--addr", "127.0.0.1:8080").rsplit(":", 1)[1]
        if not f.get("--addr", "").startswith("0.0.0.0:"):
            p.add(where, "--addr must listen on 0.0.0.0 inside the container")
        if f"{name}:{port}" not in targets:
            p.add(where, f"docker/prometheus.yml does not scrape {name}:{port}/metrics")
        if name in API_HOST_PORTS:
            published = {str(pt.get("published")) for pt in svc.get("ports") or []
                         if str(pt.get("target")) == port}
            if API_HOST_PORTS[name] not in published:
                p.add(where, f"must publish container port {port} on host port {API_HOST_PORTS[name]}")


def cmd_compose(config_path, prom_path):
    with open(config_path) as fh:
        cfg = json.load(fh)
    with open(prom_path) as fh:
        prom = yaml.safe_load(fh)
    p = Problems()
    check_compose(cfg, prom, p)
    targets = sorted(t for job in prom.get("scrape_configs", []) for sc in job.get("static_configs", [])
                     for t in sc.get("targets", []))
    status = "ok" if not p.items else f"{len(p.items)} problem(s)"
    print(f"  compose: services {', '.join(sorted(cfg.get('services', {})))}; "
          f"prometheus.yml scrapes {', '.join(targets)}: {status}")
    return report(p)


# ---------------------------------------------------------------------------------------------
# Self-test: each of these broken copies must be refused, or a check has gone blind.

def k8s_mutations():
    def obj(docs, kind, name):
        d = find(docs, kind, name)
        assert d is not None, f"self-test fixture: no {kind}/{name} in the render"
        return d

    def worker(docs):
        return obj(docs, "Deployment", "willow-worker")["spec"]["template"]["spec"]

    def so(docs):
        return obj(docs, "ScaledObject", "willow-worker")["spec"]

    def set_arg(docs, deployment, flag, value):
        args = obj(docs, "Deployment", deployment)["spec"]["template"]["spec"]["containers"][0]["args"]
        args[args.index(flag) + 1] = value

    return [
        ("schema: replicas is a string", 'spec.replicas', lambda d: obj(d, "StatefulSet", "nats")["spec"].update(replicas="one")),
        ("strict schema: unknown container field", 'memoryLimit', lambda d: worker(d)["containers"][0].update(memoryLimit="6Gi")),
        ("unknown kind without a schema or a check", 'no schema for monitoring.coreos.com/v1 ServiceMonitor', lambda d: d.append(
            {"apiVersion": "monitoring.coreos.com/v1", "kind": "ServiceMonitor",
             "metadata": {"name": "willow", "namespace": "willow"}, "spec": {}})),
        ("KEDA: wrong consumer", "consumer is 'workers'", lambda d: so(d)["triggers"][0]["metadata"].update(consumer="workers")),
        ("KEDA: unquoted lagThreshold", 'lagThreshold must be a string', lambda d: so(d)["triggers"][0]["metadata"].update(lagThreshold=1)),
        ("KEDA: endpoint in another namespace", "names namespace 'default'", lambda d: so(d)["triggers"][0]["metadata"].update(
            natsServerMonitoringEndpoint="nats.default.svc:8222")),
        ("KEDA: unknown spec field", 'unknown field spec.maxReplicas', lambda d: so(d).update(maxReplicas=10)),
        ("KEDA: target not rendered", 'scaleTargetRef Deployment/willow-workers', lambda d: so(d)["scaleTargetRef"].update(name="willow-workers")),
        ("drain longer than terminationGracePeriodSeconds", 'terminationGracePeriodSeconds 30 <', lambda d: worker(d).update(terminationGracePeriodSeconds=30)),
        ("writable root filesystem", 'readOnlyRootFilesystem must be true', lambda d: worker(d)["containers"][0]["securityContext"].update(readOnlyRootFilesystem=False)),
        ("capabilities not dropped", 'capabilities.drop must contain ALL', lambda d: worker(d)["containers"][0]["securityContext"].pop("capabilities")),
        ("no readiness probe", 'no readinessProbe', lambda d: worker(d)["containers"][0].pop("readinessProbe")),
        ("readiness on /healthz", 'readinessProbe must GET /readyz', lambda d: worker(d)["containers"][0]["readinessProbe"]["httpGet"].update(path="/healthz")),
        ("no memory limit", 'resources.limits.memory missing', lambda d: worker(d)["containers"][0]["resources"]["limits"].pop("memory")),
        ("worker memory below one flow", 'is too small', lambda d: worker(d)["containers"][0]["resources"]["limits"].update(memory="1Gi")),
        ("NATS image on latest", 'uses the latest tag', lambda d: obj(d, "StatefulSet", "nats")["spec"]["template"]["spec"]["containers"][0].update(image="nats:latest")),
        ("backend names a missing Service", 'no Service nats-client', lambda d: set_arg(d, "willow-api", "--backend", "nats://nats-client:4222")),
        ("role all on NATS", '--role api or --role worker', lambda d: set_arg(d, "willow-worker", "--role", "all")),
        ("embedded with many replicas", '--role must be all', lambda d: set_arg(d, "willow-api", "--backend", "embedded")),
        ("Service selects nothing", 'matches no pod template', lambda d: obj(d, "Service", "willow-api")["spec"]["selector"].update(
            {"app.kubernetes.io/component": "apis"})),
        ("selector not matching template", 'does not match the pod template', lambda d: obj(d, "Deployment", "willow-worker")["spec"]["selector"]["matchLabels"].update(
            {"app.kubernetes.io/component": "wrk"})),
        ("missing component label", 'no label app.kubernetes.io/component', lambda d: obj(d, "Service", "nats")["metadata"]["labels"].pop("app.kubernetes.io/component")),
    ]


def compose_mutations():
    def svc(cfg, name):
        return cfg["services"][name]

    def set_cmd(cfg, name, flag, value):
        cmd = svc(cfg, name)["command"]
        cmd[cmd.index(flag) + 1] = value

    return [
        ("a worker missing", "missing services: ['worker-2']", lambda c: c["services"].pop("worker-2")),
        ("root user", 'user must be "65532:65532"', lambda c: svc(c, "api-1").update(user="0:0")),
        ("writable root filesystem", "read_only must be true", lambda c: svc(c, "worker-1").update(read_only=False)),
        ("wrong role", '--role must be api', lambda c: set_cmd(c, "api-2", "--role", "worker")),
        ("backend on a host that is no service", 'nats://broker:4222', lambda c: set_cmd(c, "worker-1", "--backend", "nats://broker:4222")),
        ("stop grace shorter than the drain", 'stop_grace_period 30 s', lambda c: svc(c, "worker-2").update(stop_grace_period="30s")),
        ("NATS on latest", 'uses the latest tag', lambda c: svc(c, "nats").update(image="nats:latest")),
        ("api on another host port", 'host port 8082', lambda c: svc(c, "api-2")["ports"][0].update(published="9999")),
    ]


def expect_refused(what, expect, problems):
    """One self-test case: refused, and for the reason it was broken for."""
    hit = next((i for i in problems if expect in i), None)
    if hit:
        print(f"  refused as it should be: {what}: {hit}")
        return 0
    print(f"  NOT REFUSED for {expect!r}: {what}" + (f" (only: {problems})" if problems else ""))
    return 1


def cmd_selftest(versions, render_path, config_path, prom_path):
    docs = load_render(render_path)
    with open(config_path) as fh:
        cfg = json.load(fh)
    with open(prom_path) as fh:
        prom = yaml.safe_load(fh)
    p = Problems()
    check_overlay("selftest", copy.deepcopy(docs), versions, p, [])
    check_compose(copy.deepcopy(cfg), prom, p)
    if p.items:
        print("  the self-test's fixtures do not pass as they are:", *p.items, sep="\n    ")
        return 1
    failures = 0
    for what, expect, mutate in k8s_mutations():
        broken = copy.deepcopy(docs)
        mutate(broken)
        p = Problems()
        check_overlay("selftest", broken, versions, p, [])
        failures += expect_refused(what, expect, p.items)
    for what, expect, mutate in compose_mutations():
        broken = copy.deepcopy(cfg)
        mutate(broken)
        p = Problems()
        check_compose(broken, prom, p)
        failures += expect_refused(f"compose: {what}", expect, p.items)
    p = Problems()
    check_compose(cfg, {"scrape_configs": []}, p)
    failures += expect_refused("prometheus.yml scraping nothing", "does not scrape", p.items)
    return 1 if failures else 0


def report(p):
    for item in p.items:
        print(f"  ERROR {item}")
    return 1 if p.items else 0


def main(argv):
    if len(argv) >= 3 and argv[1] == "k8s":
        return cmd_k8s(argv[2].split(","), argv[3:])
    if len(argv) == 4 and argv[1] == "compose":
        return cmd_compose(argv[2], argv[3])
    if len(argv) == 6 and argv[1] == "selftest":
        return cmd_selftest(argv[2].split(","), argv[3], argv[4], argv[5])
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv))
