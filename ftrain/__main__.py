"""``python -m ftrain`` and ``torchrun -m ftrain``."""

import sys

from ftrain.cli import main

sys.exit(main())
