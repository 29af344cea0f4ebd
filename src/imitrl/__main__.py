"""``python -m imitrl ...`` is the ``imitrl`` command."""

import sys

from imitrl.cli import main

sys.exit(main())
