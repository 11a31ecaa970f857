"""``python -m services.cli`` is ``swpc``."""

import sys

from services.cli import main

sys.exit(main())
