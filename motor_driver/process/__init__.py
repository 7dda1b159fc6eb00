"""A process's life, for every entry point of the driver (the nodes, the CLI): what stops it, its
heap, and how often it may repeat itself. The simulator needs none of them.

What lives where: :mod:`.stop` (stop requests on SIGINT, SIGTERM and SIGHUP), :mod:`.heap` (the
heap settled once the process is up), :mod:`.ratelimit` (repeated log lines at a bounded rate), :mod:`.jobs` (background jobs
supervised: an unexpected exception counted, logged and retried, the counts read by the health),
:mod:`.held` (a wait's timeout that does not count the time its process was held).

Owner: the thread that calls; none of them starts a thread (a job's failures are counted under
its counter's own lock, from whichever thread ran it).
"""
