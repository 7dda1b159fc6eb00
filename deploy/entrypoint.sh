#!/usr/bin/env bash
# Container entry point: ROS and the project's packages on the path, then the rover launch.
# Extra arguments go to the launch (e.g. arm:=true).
#
# The launch runs under the project's own launcher (rovercan launch), PID 1 here: `docker stop`'s
# SIGTERM reaches it, and it stops the driver with SIGINT first (every drive quick-stopped and
# disabled before the bus closes; `ros2 launch` would only cancel its own loop and leave the driver
# to the kernel's SIGKILL), and it exits non-zero when the driver does (systemd's restart; `ros2
# launch` exits 0 when its only process ended).
set -eo pipefail
ROS_SETUP="${ROS_SETUP:-/opt/ros/jazzy/setup.bash}"
ROVERCAN_HOME="${ROVERCAN_HOME:-/opt/rovercan}"
# ROS's setup scripts read variables they never set (AMENT_TRACE_SETUP_FILES, COLCON_TRACE): not
# under `set -u`, which would end this script before the launch
# shellcheck disable=SC1090
source "$ROS_SETUP"
# shellcheck disable=SC1091
source "$ROVERCAN_HOME/install/setup.bash"
set -u
export PATH="$ROVERCAN_HOME/venv/bin:$PATH"
export PYTHONPATH="$ROVERCAN_HOME:${PYTHONPATH:-}"
# the rover's graph spans machines: ROS's own default, which rovercan launch would narrow to loopback
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-SUBNET}"
if [[ ! -f "${ROVERCAN_CONFIG:-}" ]]; then
  echo "rovercan: no config at ${ROVERCAN_CONFIG:-(ROVERCAN_CONFIG unset)}; mount the rover config (-v /etc/rovercan:/etc/rovercan:ro)" >&2
  exit 2
fi
exec rovercan launch "$ROVERCAN_HOME/ros/rovercan_bringup/launch/rover_launch.xml" "config:=$ROVERCAN_CONFIG" "$@"
