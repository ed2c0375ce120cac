#!/usr/bin/env bash
# The README's main job: replays the sample flight in bags/ through photogram_ros and writes the
# map and the report to output/sample (or the folder given as first argument).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"
out="${1:-output/sample}"
# The sample is simulated: --truth makes the report compare it with the simulator's ground truth.
exec "$root/.venv/bin/photogram-ros" replay "$root/bags/sample_flight" --out "$out" --truth "$root/bags/sample_flight" "${@:2}"
