"""`python -m photoreal.cli …`, the same as `photoreal …`."""

import sys

from . import main

sys.exit(main())
