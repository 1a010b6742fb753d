"""``python -m hdrcap``: the command line."""

import sys

from hdrcap.cli import main

sys.exit(main())
