"""``python -m torchskin.cli``: the ``torchskin`` command."""

import sys

from . import main

sys.exit(main())
