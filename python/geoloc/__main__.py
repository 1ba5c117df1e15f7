"""``python -m geoloc`` is the ``geoloc`` command."""

from .cli import main

raise SystemExit(main())
