"""CANopen and CiA 402 as pure rules and codecs: what the standard says, with no bus, no clock
and no thread. Every other folder of the driver builds on these; they import none of them.

What lives where: :mod:`.cia402` (the drive profile's states, controlword commands and
transition table), :mod:`.pdo` (the PDO set planned from an EDS, and its codecs), :mod:`.codec`
(SDO values by their EDS data type), :mod:`.units` (engineering units at the API, drive units on
the wire) with :mod:`.unit_ranges` (the plausible range of each), :mod:`.safety` (what keeps a
drive safe with the host gone, judged from what it reports), :mod:`.errorframes` (SocketCAN
error frames decoded).

Owner: none; values and functions only.
"""
