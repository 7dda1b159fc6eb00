"""Diagnostics: drives graded by their verdict, buses and background jobs graded, frames lost
measured (pure: no I/O, no clock of its own).

Owner: none: pure functions of what the caller hands them, called on the thread that publishes
/diagnostics (the driver node's) or on the bus view's feeding thread.

- :mod:`.health`: the rules that grade a drive (from its verdict), a bus and the background jobs
  as OK / WARN / ERROR, with the cause and what helps
- :mod:`.frameloss`: frames lost, measured: each drive's TPDOs and heartbeats expected against
  those received
"""
