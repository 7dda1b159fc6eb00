import sys

from rovercan.entry import main

sys.exit(main())
