"""``python -m rovercan``: the console entry point as a module.

Owner: the CLI's main thread.
"""
import sys

from rovercan.entry import main

sys.exit(main())
