"""``python -m h3edge`` = the ``h3edge`` console script."""

import sys

from h3edge.cli import main

sys.exit(main())
