"""`python -m services.cli` is `gridslam`."""

import sys

from services.cli import main

sys.exit(main())
