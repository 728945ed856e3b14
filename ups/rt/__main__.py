"""``python -m ups.rt FILE ...``: the CAN response-time analysis (same as ``ups analyze``)."""

import sys

from .cli import main

sys.exit(main())
