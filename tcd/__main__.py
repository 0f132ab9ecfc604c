"""`python -m tcd ...`: the `tcd` command without its console script."""
import sys

from .cli import main

sys.exit(main())
