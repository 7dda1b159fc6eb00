"""The per-joint interfaces: each configured joint's topics and services, and its commands that must
wait for their drive.

Owner: the hot executor's one thread takes every joint's commands and publishes its state; the
services' executors answer their calls; a joint's handoff worker sends what must wait.

- :mod:`.driver_node`: the driver node: every joint's topics (commands in, MotorState and joint
  states out) and /diagnostics
- :mod:`.driver_services`: the driver's services as two nodes: the stops, which answer at once,
  and the rest
- :mod:`.handoff`: a command that must wait for its drive, taken off the hot thread
- :mod:`.messages`: driver snapshots into ROS messages, and header stamps
- :mod:`.rawcmd`: a Float32 command's raw CDR bytes, decoded
- :mod:`.refusals`: a refused command said once a second per joint
"""
