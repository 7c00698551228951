"""``python -m skinpipe`` is the ``skinpipe`` command."""

import sys

from .cli import main

sys.exit(main())
