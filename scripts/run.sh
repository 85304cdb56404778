#!/usr/bin/env bash
# The main job: installs what is missing (scripts/setup.sh), runs the thin slice — a real glTF mesh
# into BLASes and a TLAS, traced by the ray-query shader — writing out/engine.png, then the open-world
# fly-through: every policy (managed with its far field, managed without it, naive, seed) on the
# real Vulkan backend, scored against the full-world ground truth, deterministic; the table on
# stdout, CSV, summary.json, maps and worst frames in out/flythrough/. Extra arguments go to the
# fly-through (try --help).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
cargo run --release --example engine
cargo run --release --example flythrough -- --deterministic --compare-far-field "$@"
