"""What the driver writes down and reads back: the flight recorder's incidents, CAN recordings,
and the bus as ROS 2 messages (no rclpy) for MCAP files and the live Foxglove view.

What lives where: :mod:`.flight` (the flight recorder: the last seconds of every frame and drive
state, written when something goes wrong), :mod:`.incident` (its incident files read back),
:mod:`.incident_mcap` (an incident's frames as MCAP), :mod:`.plot` (an incident's PNG, drawn by
``python -m motor_driver.recording INCIDENT.json``, :mod:`.__main__`), :mod:`.files` (reading CAN
recordings of every format), :mod:`.busview` (every frame, and each drive decoded, as ROS 2
messages), :mod:`.ros2defs` (the message definitions), :mod:`.cdr` (their CDR encoding),
:mod:`.mcap_out` (writing them to MCAP), :mod:`.published` (what the state topics say of a drive,
the one conversion the live nodes and recordings share), :mod:`.timemerge` (several buses' frames
in time order).

Owner: the flight recorder's ring is appended to by every thread and written by its own writer
thread (``rovercan-recorder``); the rest are values and functions of the caller's thread.
"""
