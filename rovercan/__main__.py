import sys

from rovercan.cli import main

sys.exit(main())
