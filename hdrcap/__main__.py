"""``python -m hdrcap``: the command line."""

import sys

from hdrcap.acquire.cli import main

sys.exit(main())
