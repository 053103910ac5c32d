"""``python -m dego``: the ``dego`` command."""

import sys

from dego._entry import forget_caught_interrupts, main

status = main()
forget_caught_interrupts()
sys.exit(status)
