"""``python -m motor_driver.recording INCIDENT.json``: draw the incident's PNG (a module of its
own, so that runpy does not run the package already imported by the driver).

Owner: the helper process's one thread.
"""

import sys

from motor_driver.recording.plot import main

sys.exit(main())
