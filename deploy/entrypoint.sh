#!/usr/bin/env bash
# Container entry point: ROS and the project's packages on the path, then the rover launch.
# Extra arguments go to the launch (e.g. arm:=true).
set -euo pipefail
# shellcheck disable=SC1091
source /opt/ros/jazzy/setup.bash
# shellcheck disable=SC1091
source /opt/rovercan/install/setup.bash
export PATH="/opt/rovercan/venv/bin:$PATH"
export PYTHONPATH="/opt/rovercan:${PYTHONPATH:-}"
if [[ ! -f "$ROVERCAN_CONFIG" ]]; then
  echo "rovercan: no config at $ROVERCAN_CONFIG; mount the rover config (-v /etc/rovercan:/etc/rovercan:ro)" >&2
  exit 2
fi
exec ros2 launch rovercan_bringup rover_launch.xml "config:=$ROVERCAN_CONFIG" "$@"
