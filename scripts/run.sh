#!/usr/bin/env bash
# The main job: installs what is missing (scripts/setup.sh), then runs the thin slice — a real glTF
# mesh into BLASes and a TLAS, traced by the ray-query shader — writing out/engine.png.
# Extra arguments go to the example (try --help).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
cargo run --release --example engine
cargo run --release --example flythrough -- "$@"
