"""``python -m mjx_supportfield``: the command line."""

import sys

from mjx_supportfield.tools.cli import main

sys.exit(main())
