"""``python -m server [serve options]`` — the same as ``hippomap serve``."""

import sys

from .cli import main

sys.exit(main())
