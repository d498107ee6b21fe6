"""`python -m dovesei.up`: the same as `dovesei up`."""

import sys

from dovesei.up import main

sys.exit(main())
