"""`python -m symfunnel ...`: the same command line as the `symfunnel` script."""

import sys

from .cli import main

sys.exit(main())
