"""``python -m mjx_supportfield``: the command line."""

import sys

from mjx_supportfield.cli import main

sys.exit(main())
