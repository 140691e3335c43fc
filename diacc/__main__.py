"""``python -m diacc ...``: the ``diacc`` command, for environments whose scripts folder is
not on ``PATH`` (a notebook kernel, ``python -m`` in a job script)."""

import sys

from diacc.cli import main

if __name__ == "__main__":
    sys.exit(main())
