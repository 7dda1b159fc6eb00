"""The CLI's exit codes, the one rule every command follows (README, "The bench"). Values only:
no state, no thread."""

from __future__ import annotations

EXIT_OK = 0  # done
EXIT_FAILED = 1  # the bus or a drive failed or refused
EXIT_USAGE = 2  # bad usage, a bad config or input, or a command refused before it was sent
