"""``python -m mavvo`` is the ``mavvo`` command."""

import sys

from mavvo.cli import main

sys.exit(main())
