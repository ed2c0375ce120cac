#!/usr/bin/env bash
# The README's test command: sets up .venv if needed, then runs pytest with its own ROS_DOMAIN_ID.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"
export ROS_LOCALHOST_ONLY=0
# What CI runs unless a marker is chosen: `-m slow` runs the long runs, `-m "slow or not slow"` everything.
marker=(-m "not slow")
for a in "$@"; do
  case "$a" in -m|-m*|--markexpr*) marker=() ;; esac
done
exec "$root/.venv/bin/python" -m pytest "${marker[@]}" "$@"
