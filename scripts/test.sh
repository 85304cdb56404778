#!/usr/bin/env bash
# All tests: installs what is missing (scripts/setup.sh), then runs every test of the workspace
# with the Vulkan validation layer on (a validation message fails a test).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
export RTSTREAM_VALIDATION=1
start=$(date +%s)
cargo test --workspace --all-targets "$@"
cargo test --workspace --doc
# The API docs build without a warning (broken intra-doc links included).
RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --quiet
# The libFuzzer targets (streaming/fuzz) build on stable; running them needs nightly (docs/RELIABILITY.md).
CARGO_TARGET_DIR=target/fuzz cargo build --locked --manifest-path streaming/fuzz/Cargo.toml
echo "tests: wall time $(( $(date +%s) - start )) s"
