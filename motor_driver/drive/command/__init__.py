"""What the command channel owns: every controlword and set-point of one drive, and the parts that
command through it.

Owner: the command channel (:mod:`.channel`), under its lock: the controlword last sent, the
targets, the generation counter and the busy registry. Command threads (the API, ROS callbacks,
the handoff workers), the supervisor (watchdog, limit guard, the stop of a lost drive) and the
receive thread (the set-point handshake's reply) all come to it; nobody else builds such a frame.
The other modules here keep no state of their own but counters and caches their docstrings name.

- :mod:`.channel`: the one way out for a controlword or a set-point; a stop always wins
- :mod:`.busy`: the busy registry: the operations under way, each under a token of its own
- :mod:`.setpoint`: the profile-position set-point handshake the channel and the receive thread
  share
- :mod:`.power`: the CiA 402 power state machine (enable, the stops, recover) and the mode switch
- :mod:`.limits`: the stopping-distance limit guard and the velocity watchdog
- :mod:`.motion`: motion commands, one family per operation mode
- :mod:`.homing`: homing
"""
