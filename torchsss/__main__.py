"""``python -m torchsss``: see :mod:`torchsss.cli`."""

import sys

from torchsss.cli import main

sys.exit(main())
