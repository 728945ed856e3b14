"""``python -m upscli ...``: the ``ups`` command."""

import contextlib
import sys

from upscli import main

with contextlib.suppress(BrokenPipeError):
    sys.exit(main())
