"""``python -m services.cli``: the ``spine`` command."""

import sys

from services.cli import main

sys.exit(main())
