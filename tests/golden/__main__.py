"""`python -m tests.golden {demo,nubot} RESULTS_DIR`: write that run's golden figures (tests/golden/__init__.py)."""

import sys

from tests.golden import main

sys.exit(main(sys.argv[1:]))
