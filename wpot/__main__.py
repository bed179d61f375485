"""``python -m wpot ...`` runs the command-line tool (the same as the ``wpot`` script)."""
from wpot.cli import main

raise SystemExit(main())
