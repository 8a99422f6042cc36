"""`python -m topseg.services.cli`: the `topseg` command."""

import sys

from topseg.services.cli import main

sys.exit(main())
