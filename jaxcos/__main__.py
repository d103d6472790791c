"""``python -m jaxcos``: the command line, as the ``jaxcos`` script."""

import sys

from .cli import main

sys.exit(main())
