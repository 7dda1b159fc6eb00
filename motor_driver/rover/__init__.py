"""The rover's own geometry, not a motor driver's concern: how a body twist becomes wheel
speeds and how the wheels' measured motion becomes a pose. Pure: no I/O, no clock, no thread;
the drive system (``nodes/rover/drive_system.py``) feeds them and owns their state.

What lives where: :mod:`.skid_steer` (the kinematics and acceleration ramp), :mod:`.odometry`
(the pose from each wheel's own position changes).
"""
