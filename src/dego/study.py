"""Former home of ``dego study``'s runner: moved to :mod:`dego.demo.study` (the statistics
to :mod:`dego.demo.stats`). Importing this module warns once and hands on the same names;
it will be removed in a later release."""

import warnings

from dego.demo.study import *  # noqa: F403
from dego.demo.study import __all__ as __all__

warnings.warn(
    "dego.study moved to dego.demo.study (statistics: dego.demo.stats); "
    "import from there, this alias will be removed",
    DeprecationWarning,
    stacklevel=2,
)
