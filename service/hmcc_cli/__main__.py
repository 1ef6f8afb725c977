"""``python -m hmcc_cli``: the same as the ``hmcc`` command."""

import sys

from . import main

sys.exit(main())
