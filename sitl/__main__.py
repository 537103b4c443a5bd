"""``python -m sitl``."""

import sys

from sitl.cli import main

sys.exit(main())
