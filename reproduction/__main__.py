"""``python -m reproduction``: :func:`reproduction.reproduce.main`."""

import sys

from reproduction.reproduce import main

sys.exit(main())
