# Sourced by the README's two commands: sets up .venv if needed, enters the checkout and gives the run a
# ROS 2 environment of its own. Defines $root.
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$root/scripts/venv.sh"
cd "$root"
# This checkout's package first, whichever checkout the editable install in .venv points at.
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}"
# A domain of our own per run, so concurrent sessions on one machine never hear each other; 1..101 keep
# Fast DDS's ports (7400 + 250 x domain) below Linux's ephemeral port range.
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( (RANDOM % 101) + 1 ))}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
