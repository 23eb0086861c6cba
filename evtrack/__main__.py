"""``python -m evtrack`` runs the ``evtrack`` command."""

from evtrack.cli import main

raise SystemExit(main())
