"""``python -m brdfjax``: the same as the ``brdfjax`` console script."""

from .cli import main

raise SystemExit(main())
