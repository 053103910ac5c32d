"""``python -m dego``: the ``dego`` command."""

import sys

try:  # importing torch takes seconds: Ctrl-C then is no traceback either
    from dego.cli import main
except KeyboardInterrupt:
    print("dego: interrupted", file=sys.stderr)
    sys.exit(130)

sys.exit(main())
