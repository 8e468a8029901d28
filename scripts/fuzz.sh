#!/usr/bin/env bash
# Fuzzing with cargo-fuzz (libFuzzer): the targets in fuzz/fuzz_targets/ feed arbitrary bytes
# to the parsers an upload or a request reaches.
#
#   obj          OBJ reader (Asset::read, Format::Obj), then the OBJ and GLB writers
#   gltf         glTF/GLB reader (Asset::read, Format::Gltf), then the writers
#   curve        curve readers (Curve::from_json, Curve::from_obj)
#   http_params  POST /v1/jobs parameters: query string or `params` JSON part -> JobSpec
#   grpc_upload  gRPC request decoding, UploadMesh chunk assembly, CreateJob -> JobSpec
#
# Usage:
#   scripts/fuzz.sh --smoke                  every target for WILLOW_FUZZ_SMOKE_SECS (default
#                                            20) seconds; fails on any crash, hang or leak of
#                                            memory past the limits (CI: scripts/test.sh)
#   scripts/fuzz.sh TARGET --runs N          a campaign: N executions of one target
#   scripts/fuzz.sh TARGET --secs S          a campaign bounded by time
#   scripts/fuzz.sh --build                  install and build only
# Extra arguments after `--` go to libFuzzer (e.g. `-- -jobs=2`).
#
# cargo-fuzz is installed pinned into target/fuzz-tools/ (idempotent, quick when installed).
# Targets are built with `--sanitizer none -O`: the code under test is safe Rust, so ASan
# finds little that a panic does not, while it makes the coverage build of this dependency
# tree several times slower and the runs about half as fast. What `-malloc_limit_mb` would
# check without a sanitizer runtime is checked by the targets' own allocator
# (fuzz/src/lib.rs: any single allocation above WILLOW_FUZZ_MALLOC_LIMIT_MB, default 1024,
# is a crash); -rss_limit_mb=2048 and -timeout=10 catch the rest. The only toolchain here is
# stable, so RUSTC_BOOTSTRAP=1 lets cargo-fuzz pass its -Z flags.
#
# Seed corpora are made at run time from the repository's test files (crates/willow/tests/data) into
# target/fuzz-work/seeds/ (glTF, gRPC and HTTP seeds by the make-seeds binary of fuzz/);
# what a run finds goes to target/fuzz-work/corpus/TARGET/ and crashes to
# target/fuzz-work/artifacts/TARGET/. None of it is committed.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

cargo_fuzz_version=0.13.1
targets=(obj gltf curve http_params grpc_upload)
tools="$root/target/fuzz-tools"
work="$root/target/fuzz-work"
build_dir="${CARGO_TARGET_DIR:-$root/target}/fuzz"
triple="$(rustc -vV | sed -n 's/^host: //p')"
bin="$build_dir/$triple/release"

mode=""
target=""
runs=""
secs=""
extra=()
while [[ $# -gt 0 ]]; do
    case "$1" in
        --smoke) mode=smoke ;;
        --build) mode=build ;;
        --runs) runs="$2"; shift ;;
        --secs) secs="$2"; shift ;;
        --) shift; extra=("$@"); break ;;
        -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d'; exit 0 ;;
        *)
            if [[ " ${targets[*]} " == *" $1 "* ]]; then
                mode=campaign; target="$1"
            else
                echo "fuzz.sh: unknown argument or target '$1' (targets: ${targets[*]})" >&2
                exit 2
            fi
            ;;
    esac
    shift
done
if [[ -z "$mode" ]]; then
    echo "usage: scripts/fuzz.sh --smoke | --build | TARGET (--runs N | --secs S) [-- LIBFUZZER_ARGS]" >&2
    exit 2
fi

# cargo-fuzz, pinned.
if ! "$tools/bin/cargo-fuzz" --version 2>/dev/null | grep -qx "cargo-fuzz $cargo_fuzz_version"; then
    echo "fuzz.sh: installing cargo-fuzz $cargo_fuzz_version into $tools"
    cargo install --locked --quiet --root "$tools" "cargo-fuzz@$cargo_fuzz_version"
fi

# Every target and the seed maker, in one cargo invocation (one coverage build of the library).
echo "fuzz.sh: building the fuzz targets"
RUSTC_BOOTSTRAP=1 "$tools/bin/cargo-fuzz" build --fuzz-dir fuzz -O --sanitizer none \
    --target-dir "$build_dir"
[[ "$mode" == build ]] && exit 0

# Seeds, made afresh each run (cheap) from the repository's own test files.
# Made aside and swapped in, so that a campaign starting meanwhile reads a whole set.
seeds="$work/seeds"
fresh="$work/seeds.$$"
rm -rf "$fresh"
mkdir -p "$fresh"/{obj,curve}
cp crates/willow/tests/data/*.obj "$fresh/obj/"
cp crates/willow/tests/data/curves/* "$fresh/curve/"
"$bin/make-seeds" "$fresh" crates/willow/tests/data/*.obj 2>/dev/null
rm -rf "$seeds"
mv "$fresh" "$seeds"

# One libFuzzer run of target $1; further arguments go to libFuzzer.
run_target() {
    local t="$1"; shift
    local corpus="$work/corpus/$t" artifacts="$work/artifacts/$t/"
    mkdir -p "$corpus" "$artifacts"
    local max_len=4096
    [[ "$t" == gltf || "$t" == grpc_upload ]] && max_len=16384
    local dict=()
    [[ -f "fuzz/dicts/$t.dict" ]] && dict=("-dict=fuzz/dicts/$t.dict")
    echo "fuzz.sh: $t $*"
    "$bin/$t" "$corpus" "$seeds/$t" "${dict[@]}" -max_len="$max_len" -timeout=10 \
        -rss_limit_mb=2048 -artifact_prefix="$artifacts" -print_final_stats=1 \
        "$@" "${extra[@]}"
}

if [[ "$mode" == smoke ]]; then
    # libFuzzer prints a line per new input, thousands in a smoke run: each target's output goes
    # to target/fuzz-work/logs/TARGET.log and the run prints one line of its final stats, or
    # the log's tail and the crash artifacts when it fails.
    logs="$work/logs"
    mkdir -p "$logs"
    final_stat() { sed -n "s/^stat::$1: *//p" "$log" | tail -n1; }
    for t in "${targets[@]}"; do
        log="$logs/$t.log"
        if ! run_target "$t" -max_total_time="${WILLOW_FUZZ_SMOKE_SECS:-20}" >"$log" 2>&1; then
            echo "fuzz.sh: $t FAILED; the last 60 lines of $log:" >&2
            tail -n 60 "$log" >&2
            ls -l "$work/artifacts/$t/" >&2 || true
            exit 1
        fi
        echo "fuzz.sh: $t: $(final_stat number_of_executed_units) runs, $(final_stat average_exec_per_sec)/s," \
            "$(final_stat new_units_added) new units, peak RSS $(final_stat peak_rss_mb) MB, no crash"
    done
    echo "fuzz.sh: smoke runs found nothing"
else
    args=()
    [[ -n "$runs" ]] && args+=(-runs="$runs")
    [[ -n "$secs" ]] && args+=(-max_total_time="$secs")
    run_target "$target" "${args[@]}"
fi
