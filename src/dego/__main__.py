"""``python -m dego``: the ``dego`` command."""

import sys

from dego._entry import main

sys.exit(main())
