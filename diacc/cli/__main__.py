"""``python -m diacc.cli``: the ``diacc`` command."""

import sys

from diacc.cli import main

if __name__ == "__main__":
    sys.exit(main())
