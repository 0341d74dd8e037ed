"""``python -m svr``: the same as the ``svr`` command."""

import sys

from svr.cli import main

sys.exit(main())
