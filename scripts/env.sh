# Sourced by the README's two commands: sets up .venv if needed, enters the checkout and gives the run a
# ROS 2 environment of its own. Defines $root.
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$root/scripts/venv.sh"
cd "$root"
# This checkout's package first, whichever checkout the editable install in .venv points at.
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}"
# ROS_DOMAIN_ID stays as the caller set it: a test session reserves a free domain of its own
# (tests/conftest.py), a replay takes one (photogram_ros/nodes/ros_domain.py), so concurrent sessions on
# one machine never hear each other.
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
