"""`python -m sitl`: the same as `companion-sitl`."""

import sys

from sitl.cli import main

sys.exit(main())
