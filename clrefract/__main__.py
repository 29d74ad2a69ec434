"""`python -m clrefract` runs the command line of this checkout."""

import sys

from .cli import main

sys.exit(main())
