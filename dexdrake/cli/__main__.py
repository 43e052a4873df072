"""`python -m dexdrake.cli`: the `dexdrake` command."""

import sys

from dexdrake.cli import main

sys.exit(main())
