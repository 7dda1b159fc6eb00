"""A process's life, for every entry point of the driver (the nodes, the CLI): what stops it, its
heap, and how often it may repeat itself. The simulator needs none of them.

What lives where: :mod:`.stop` (stop requests on SIGINT, SIGTERM and SIGHUP), :mod:`.heap` (the
heap settled once the process is up), :mod:`.ratelimit` (repeated log lines at a bounded rate).

Owner: the thread that calls; none of them starts a thread.
"""
