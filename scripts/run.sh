#!/usr/bin/env bash
# The main job: installs what is missing (scripts/setup.sh), runs the thin slice — a real glTF mesh
# into BLASes and a TLAS, traced by the ray-query shader — writing out/engine.png, then the open-world
# fly-through (streaming -> WorldBridge -> manager, vs the Naive and SeedR1R2 baselines), writing
# out/flythrough_*.png and the comparison table. Extra arguments go to the fly-through (try --help).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
cargo run --release --example engine
cargo run --release --example flythrough -- "$@"
