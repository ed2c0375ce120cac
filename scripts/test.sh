#!/usr/bin/env bash
# The README's test command: sets up .venv if needed, then runs pytest with its own ROS_DOMAIN_ID.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$root/scripts/venv.sh"
cd "$root"
# This checkout's package first, whichever checkout the editable install in .venv points at.
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}"
# A domain of our own per run, so concurrent test sessions on one machine never hear each other.
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( (RANDOM % 200) + 1 ))}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
export ROS_LOCALHOST_ONLY=0
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
# What CI runs unless a marker is chosen: `-m slow` runs the long runs, `-m "slow or not slow"` everything.
marker=(-m "not slow")
for a in "$@"; do
  case "$a" in -m|-m*|--markexpr*) marker=() ;; esac
done
exec "$root/.venv/bin/python" -m pytest "${marker[@]}" "$@"
