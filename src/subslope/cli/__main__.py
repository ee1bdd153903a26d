"""``python -m subslope.cli``: the ``subslope`` command."""

import sys

from subslope.cli import main

sys.exit(main())
