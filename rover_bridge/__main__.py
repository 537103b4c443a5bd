"""`python -m rover_bridge` is the same as the `rover-bridge` console script."""

import sys

from rover_bridge.cli import main

sys.exit(main())
