"""``python -m dego``: the ``dego`` command."""

import sys

from dego.cli import main

sys.exit(main())
