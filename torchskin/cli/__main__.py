"""``python -m torchskin.cli``: the ``torchskin`` command."""

import sys

from . import main

if __name__ == "__main__":  # importing the module (the API reference does) runs nothing
    sys.exit(main())
